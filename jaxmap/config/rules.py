"""Value rules of the config keys, checked when a config is loaded (file, --set, a checkpoint's meta.json).

One table: RULES[dataclass][field] for single values, CHECKS[dataclass] for rules across fields. A key
without a rule loads as its type allows; add its rule here (every command's config is in this package).
"""
from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass
from typing import Any, Callable

from jaxmap.config.schema import (DataConfig, DecoderConfig, EvalConfig, GridConfig, ImtConfig, LatentMapConfig,
                                  LatentMeshConfig, MapConfig, MeshConfig, PreprocessConfig, EvidenceConfig, SamplingConfig,
                                  SubmapsConfig,
                                  TrainConfig, WindowConfig)
from jaxmap.config.prior import EncoderConfig
from jaxmap.config.slam import (EDGE_INFORMATION, MAP_KINDS, N3_LOOP_MODES, ODOMETRY_METHODS, FrontEndConfig,
                               OdometryConfig, SlamConfig)
from jaxmap.errors import ConfigError

DATA_KINDS = ("auto", "kitti", "depth", "rosbag", "tum", "replica", "las")


@dataclass(frozen=True)
class Rule:
    """What a valid value of one key is: `ok(value)`, and `expect` words it for the error message."""

    ok: Callable[[Any], bool]
    expect: str
    choices: tuple = ()

    def problem(self, value: Any) -> str | None:
        """None when `value` is valid, else "must be ..." (with the closest choice for a mistyped name)."""
        try:
            if self.ok(value):
                return None
        except TypeError:
            pass
        msg = f"must be {self.expect}"
        if self.choices and isinstance(value, str):
            close = difflib.get_close_matches(value, [str(c) for c in self.choices], n=1, cutoff=0.5)
            if close:
                msg += f" (did you mean {close[0]!r}?)"
        return msg


def one_of(*choices) -> Rule:
    return Rule(lambda v: v in choices, "one of " + ", ".join(repr(c) for c in choices), tuple(choices))


def at_least(lo) -> Rule:
    return Rule(lambda v: v >= lo, f">= {lo}")


def above(lo) -> Rule:
    return Rule(lambda v: v > lo, f"> {lo}")


def within(lo, hi) -> Rule:
    return Rule(lambda v: lo <= v <= hi, f"between {lo} and {hi}")


def strictly_within(lo, hi) -> Rule:
    return Rule(lambda v: lo < v < hi, f"strictly between {lo} and {hi}")


NONEMPTY = Rule(lambda v: bool(str(v).strip()), "a non-empty path")
EVEN_AT_LEAST_2 = Rule(lambda v: v >= 2 and v % 2 == 0, "an even number >= 2")


def lattice_problem(res: float, leaf: float, leaf_name: str = "grid.leaf_vox_size") -> str | None:
    """None when a marching-cubes spacing `res` divides the leaf voxel size `leaf`, else why not."""
    k = leaf / res if res > 0 else 0.0
    if res > 0 and round(k) >= 1 and abs(k - round(k)) <= 1e-6 * max(1.0, k):
        return None
    return f"must be > 0 and divide {leaf_name}={leaf:g} (e.g. {leaf:g}, {leaf / 2:g} or {leaf / 4:g})"


# A check across fields takes (a config dataclass, the prefix of its keys) and yields, per problem,
# (the full keys involved, the message naming them).
def _map_checks(c: "MapConfig", x: str):
    p = lattice_problem(c.mesh.resolution_m, c.grid.leaf_vox_size, f"{x}grid.leaf_vox_size")
    if p:
        yield (f"{x}mesh.resolution_m", f"{x}grid.leaf_vox_size"), f"{x}mesh.resolution_m={c.mesh.resolution_m!r} {p}"
    if c.submaps.enabled and c.window.mode != "voxel":
        yield (f"{x}submaps.enabled", f"{x}window.mode"), (
            f"{x}submaps.enabled=true maps with the voxel window only (window.mode={c.window.mode!r} is a replay "
            "ablation of one grid): set window.mode=voxel or submaps.enabled=false")


def host_preprocess_checks(c: Any, x: str):
    """`jaxmap imt` and `jaxmap slam` preprocess on the host only."""
    if c.preprocess.device == "true":
        yield (f"{x}preprocess.device",), (
            f"{x}preprocess.device=true is for `jaxmap map` (N3) only; this command preprocesses on the host: "
            "set it to false or auto")


def _slam_checks(c: SlamConfig, x: str):
    if c.map_kind == "n3" and not c.n3_config:
        yield (f"{x}map_kind", f"{x}n3_config"), (
            f"{x}map_kind=n3 maps into an N3 map: set {x}n3_config to its config (a YAML path or a shipped name, e.g. city)")
    if c.map_kind == "n3" and c.external_poses:
        yield (f"{x}map_kind", f"{x}external_poses"), (
            f"{x}external_poses drives the imt map only: use {x}map_kind=imt with it")


def _data_checks(d: DataConfig, x: str):
    if not (d.end_frame == -1 or d.end_frame > d.begin_frame):
        yield (f"{x}end_frame", f"{x}begin_frame"), (
            f"{x}end_frame={d.end_frame} must be -1 (to the end) or greater than {x}begin_frame={d.begin_frame} "
            "(it is exclusive)")


def _preprocess_checks(p: PreprocessConfig, x: str):
    if not p.max_range_m > p.min_range_m:
        yield (f"{x}max_range_m", f"{x}min_range_m"), (
            f"{x}max_range_m={p.max_range_m!r} must be greater than {x}min_range_m={p.min_range_m!r}")
    if not p.max_z_m > p.min_z_m:
        yield (f"{x}max_z_m", f"{x}min_z_m"), f"{x}max_z_m={p.max_z_m!r} must be greater than {x}min_z_m={p.min_z_m!r}"
    if p.device == "true" and p.outlier_mad > 0:
        yield (f"{x}device", f"{x}outlier_mad"), (
            f"{x}device=true cannot remove outliers ({x}outlier_mad={p.outlier_mad!r} runs on the host); "
            f"set {x}device=false or {x}outlier_mad=0")
    if p.normals in ("grid", "cube_knn"):
        yield from _grid_checks(p, x)
    if p.image_beams_deg and (len(set(p.image_beams_deg)) != len(p.image_beams_deg) or len(p.image_beams_deg) < 2):
        yield (f"{x}image_beams_deg",), (
            f"{x}image_beams_deg needs at least 2 distinct beam elevations (degrees), got {list(p.image_beams_deg)}")
    elif p.image_beams_deg and p.image_rows not in (0, len(p.image_beams_deg)):
        yield (f"{x}image_rows", f"{x}image_beams_deg"), (
            f"{x}image_rows={p.image_rows} but {x}image_beams_deg lists {len(p.image_beams_deg)} beams: one row per "
            f"beam (set image_rows=0 or {len(p.image_beams_deg)})")
    elif p.image_beams_deg and p.image_rows > 0 and p.image_cols <= 0:
        yield (f"{x}image_cols",), f"{x}image_rows={p.image_rows} sets the range image by hand: set {x}image_cols too"
    elif p.image_rows > 0 and not p.image_beams_deg and not (p.image_cols > 0 and p.image_elev_step_deg > 0):
        yield (f"{x}image_rows", f"{x}image_cols", f"{x}image_elev_step_deg"), (
            f"{x}image_rows={p.image_rows} sets the range image by hand: set {x}image_cols and "
            f"{x}image_elev_step_deg (> 0) and {x}image_elev0_deg too, or image_rows=0 to read them off the first scan")


def _grid_checks(p: PreprocessConfig, x: str):
    from jaxmap.preprocess import check_grid, key_span  # numpy and scipy: only for the grid modes

    if not check_grid(p.max_range_m, p.normal_cell_m):
        yield (f"{x}normal_cell_m", f"{x}max_range_m"), (
            f"{x}normal_cell_m={p.normal_cell_m!r} is too fine for {x}max_range_m={p.max_range_m!r}: "
            f"{key_span(p.max_range_m, p.normal_cell_m)}^3 cells do not fit 32-bit keys; use a cell of at least "
            f"{p.max_range_m / 600:.3g} m")


RULES: dict[type, dict[str, Rule]] = {
    DataConfig: {"kind": one_of(*DATA_KINDS), "begin_frame": at_least(0), "every_frame": at_least(1),
                 "path": NONEMPTY},
    PreprocessConfig: {"min_range_m": at_least(0.0), "vox_down_m": at_least(0.0), "normal_knn": at_least(3),
                       "outlier_mad": at_least(0.0), "normals": one_of("knn", "grid", "cube_knn", "range_image"),
                       "device": one_of("auto", "true", "false"),
                       "normal_cell_m": above(0.0), "normal_levels": at_least(1), "veil_m": at_least(0.0),
                       "image_rows": at_least(0), "image_cols": at_least(0), "image_elev_step_deg": at_least(0.0)},
    EvidenceConfig: {"margin_m": at_least(0.0), "void_frames": at_least(1), "max_range_m": above(0.0)},
    SubmapsConfig: {"length_m": above(0.0), "blend_m": at_least(0.0), "resident": at_least(1), "auto_m": at_least(0.0)},
    SamplingConfig: {"label_mode": one_of("normal", "projective", "corrected"),
                     "free_label_mode": one_of("projected", "truncation"),
                     "surface_sample_range_m": above(0.0), "surface_sample_n": at_least(0), "sigma_m": at_least(0.0),
                     "free_sample_n": at_least(0), "free_band_m": at_least(0.0),
                     "free_ray_n": at_least(0), "free_ray_quiet_frames": at_least(0),
                     "free_point_filter_m": at_least(0.0)},
    GridConfig: {"leaf_vox_size": above(0.0), "feature_levels": at_least(1), "feature_dim": at_least(1),
                 "feature_std": at_least(0.0), "max_load": strictly_within(0.0, 1.0)},
    DecoderConfig: {"hidden_dim": at_least(1), "hidden_layers": at_least(0)},
    TrainConfig: {"iters": at_least(1), "nv": at_least(1), "np_per_voxel": at_least(1), "nt": at_least(0),
                  "batch_size": at_least(1), "lr": above(0.0), "sigma_sigmoid_m": above(0.0),
                  "weight_e": at_least(0.0), "freeze_after_frame": at_least(0)},
    WindowConfig: {"mode": one_of("voxel", "replay", "keyframe"), "keyframes": at_least(1),
                   "pairs_per_voxel": at_least(1), "initial_blocks": at_least(1),
                   "block_policy": one_of("reservoir", "ring"), "pairs_per_frame": at_least(0),
                   "carve_margin_m": at_least(0.0), "carve_samples": at_least(1),
                   "carve_rule": one_of("replace", "raise")},
    MeshConfig: {"resolution_m": above(0.0), "min_component_faces": at_least(0), "mask_level": at_least(0),
                 "min_leaf_corners": within(0, 8)},
    EvalConfig: {"threshold_m": above(0.0), "cull_distance_m": above(0.0), "n_samples": at_least(1)},
    MapConfig: {"output": NONEMPTY, "checkpoint_every": at_least(1)},
    LatentMapConfig: {"voxel_size_m": above(0.0), "min_points": at_least(1),
                      "interpolation": one_of("trilinear", "softmax"), "softmax_temperature": above(0.0),
                      "k_neighbours": at_least(1), "splat_power": above(0.0), "remap_min_rotation_deg": at_least(0.0),
                      "remap_min_translation_m": at_least(0.0), "initial_capacity": at_least(1),
                      "cells_per_voxel": at_least(0), "transform_cells_per_voxel": at_least(0),
                      "remap": one_of("reencode", "transform")},
    LatentMeshConfig: {"resolution": EVEN_AT_LEAST_2, "min_weight": at_least(0.0), "min_component_faces": at_least(0)},
    ImtConfig: {"output": NONEMPTY},
    OdometryConfig: {"method": one_of(*ODOMETRY_METHODS), "max_iter": at_least(1), "normals_k": at_least(3)},
    FrontEndConfig: {"edge_information": one_of(*EDGE_INFORMATION), "level_gain": within(0.0, 1.0),
                     "level_reference_frames": at_least(1)},
    SlamConfig: {"map_kind": one_of(*MAP_KINDS), "n3_loop": one_of(*N3_LOOP_MODES),
                 "n3_loop_min_move_m": at_least(0.0), "n3_loop_readd_iters": at_least(0),
                 "n3_loop_readd_per_frame": at_least(0), "n3_track_submap_min_frames": at_least(1),
                 "n3_track_points": at_least(16),
                 "n3_track_min_valid": within(0.0, 1.0),
                 "n3_track_max_range_m": at_least(0.0), "n3_track_min_seen": at_least(0), "n3_submap_m": above(0.0),
                 "checkpoint_every": at_least(0)},
    EncoderConfig: {"inputs": one_of("joint", "split")},
}

CHECKS: dict[type, list[Callable[[Any, str], Any]]] = {
    MapConfig: [_map_checks],
    ImtConfig: [host_preprocess_checks],
    DataConfig: [_data_checks],
    PreprocessConfig: [_preprocess_checks],
    SlamConfig: [host_preprocess_checks, _slam_checks],
}


def validate(cfg: Any, source: str = "<config>", origins: dict[str, str] | None = None) -> None:
    """ConfigError for the first value of dataclass tree `cfg` that breaks a rule of `RULES` / `CHECKS`,
    naming where it came from: `origins[key]` (e.g. "--set 'train.iters=-5'") or else `source` (the file)."""
    origins = origins or {}

    def walk(node: Any, prefix: str) -> None:
        rules = RULES.get(type(node), {})
        for f in dataclasses.fields(node):
            value, key = getattr(node, f.name), prefix + f.name
            if dataclasses.is_dataclass(value):
                walk(value, key + ".")
            elif f.name in rules:
                problem = rules[f.name].problem(value)
                if problem:
                    raise ConfigError(f"{origins.get(key, source)}: {key}={value!r} {problem}")
        for check in CHECKS.get(type(node), ()):
            for keys, message in check(node, prefix):
                raise ConfigError(f"{next((origins[k] for k in keys if k in origins), source)}: {message}")

    walk(cfg, "")
