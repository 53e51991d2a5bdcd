"""Typed, frozen configuration: YAML in, dataclasses out, unknown keys rejected.

Every command of `jaxmap` reads one YAML file into a tree of frozen dataclasses. A key the
dataclass does not declare is an error that names the file, the key and the closest valid key;
`--set section.key=value` overrides any leaf; the resolved tree is written next to each run.

The schema is generic: `load_config(path, schema=MapConfig)` works for any root dataclass
whose fields are scalars, tuples of scalars or nested dataclasses.
"""
from __future__ import annotations

import dataclasses
import difflib
import os
import typing
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import yaml


from jaxmap.errors import JaxmapError


class ConfigError(JaxmapError, ValueError):
    """A config file or override is wrong; the message says where and how to fix it."""


# ---------------------------------------------------------------------------------------------
# The N3 mapping config (jaxmap map). Names follow SHINE-Mapping / N3-Mapping where they exist.
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DataConfig:
    path: str = "data/city"          # sequence directory or file (KITTI, depth, ROS bag, TUM RGB-D, Replica, LAS/LAZ)
    kind: str = "auto"               # "auto", "kitti" (LiDAR scans), "depth" (depth images), "rosbag" (.bag/.mcap/.db3
                                     # or ROS 2 bag directory), "tum" (TUM RGB-D), "replica" or "las" (LAS/LAZ)
    topic: str = ""                  # ROS bag: the sensor_msgs/PointCloud2 topic to map ("" = the bag's only one)
    begin_frame: int = 0             # first frame to map (index into the sequence)
    end_frame: int = -1              # exclusive; -1 = to the end
    every_frame: int = 1             # map every n-th frame (1 = all)


@dataclass(frozen=True)
class PreprocessConfig:
    min_range_m: float = 1.5         # points closer to the sensor are dropped (ego vehicle)
    max_range_m: float = 20.0        # "pc_radius_m" of the anchors: crop radius
    min_z_m: float = -10.0           # height crop in the sensor frame
    max_z_m: float = 30.0            # upper height crop in the sensor frame
    vox_down_m: float = 0.05         # voxel downsample before sampling (0 = off)
    normal_knn: int = 20             # neighbours for PCA normals (grid: the fewest points a neighbourhood must hold)
    normals: str = "knn"             # "knn" (k nearest neighbours, scipy on the host), "cube_knn" (the k nearest
                                     # among the points of a hashed-grid cube) or "grid" (all of the cube)
    normal_cell_m: float = 0.15      # grid normals: the finest cell; a point's neighbourhood is 2 x 2 x 2 cells
    normal_levels: int = 3           # grid normals: cell sizes normal_cell_m * 2^l, l < this (the finest with >= knn)
    device: bool = False             # preprocess on the device, inside the frame program (needs normals: cube_knn or grid)
    outlier_mad: float = 0.0         # > 0: drop points whose range-scaled mean neighbour distance is this many
                                     # robust std above the scan's median (mixed pixels, stray returns); 0 = off


@dataclass(frozen=True)
class SamplingConfig:
    label_mode: str = "normal"       # "normal" (N3), "projective", "corrected" (ablations)
    surface_sample_range_m: float = 0.3   # truncation band half-width (tr)
    surface_sample_n: int = 3        # near-surface samples per scan point, inside the truncation band
    sigma_m: float = 0.05            # std of the Gaussian offset inside the band (~ range noise)
    free_sample_n: int = 3           # free-space samples per scan point, on the ray before the band
    free_band_m: float = 1.0         # free samples lie in the last free_band_m before the band
    free_ray_n: int = 6              # more free samples per scan point, stratified along the whole ray
                                     # (from preprocess.min_range_m to the band): they carve what moved
    free_ray_quiet_frames: int = 10  # ... in voxels no frame has hit within this many frames (static surfaces are
                                     # hit again and again; a ray's label is honest only about its own hit)
    free_label_m: float = -1.0       # label of free-space samples; <0 means "= truncation"
    free_point_filter_m: float = 0.0  # > 0: scan points where the map so far has an SDF above this (confidently
                                     # free: something moved in, a mixed pixel) get no samples; 0 = off
    free_label_mode: str = "projected"  # "projected": that label capped by the distance to the hit's
                                        # tangent plane; "truncation": the label as is (paper; ablation)


@dataclass(frozen=True)
class GridConfig:
    leaf_vox_size: float = 0.2       # edge length of the leaf (finest) voxels, metres
    feature_levels: int = 3          # levels of corner features; level l has voxels of edge `leaf_vox_size * 2**l`
    feature_dim: int = 8             # feature channels per corner
    feature_std: float = 1e-4        # features initialised N(0, std)
    max_load: float = 0.5            # grow (rehash, outside jit) past this load factor


@dataclass(frozen=True)
class DecoderConfig:
    hidden_dim: int = 32             # width of the SDF decoder's hidden layers
    hidden_layers: int = 2           # hidden layers of the SDF decoder (ReLU)


@dataclass(frozen=True)
class TrainConfig:
    iters: int = 50                  # K iterations per frame
    nv: int = 1024                   # voxels per iteration (hierarchical stage 1)
    np_per_voxel: int = 8            # pairs per voxel (stage 2)
    nt: int = 10                     # voxels with fewer pairs get np/3
    hierarchical: bool = True        # False = uniform pairs (ablation)
    batch_size: int = 8192           # pairs per iteration when hierarchical is False
    lr: float = 0.01                 # Adam learning rate of the features and the decoder
    sigma_sigmoid_m: float = 0.1     # beta of the BCE sigmoid
    weight_e: float = 0.08           # eikonal weight
    freeze_after_frame: int = 20     # decoder frozen after this many frames
    reset_adam_each_frame: bool = False # restart the Adam moments every frame (as the original N3 code does)
    seed: int = 0                    # PRNG seed: feature and decoder initialisation, sampling


@dataclass(frozen=True)
class WindowConfig:
    mode: str = "voxel"              # "voxel" (N3), "replay" (all past pairs, drawn uniformly),
                                     # "keyframe" (the pairs of the last N frames, drawn uniformly)
    keyframes: int = 5               # window length for mode "keyframe"
    pairs_per_voxel: int = 64        # block capacity (pairs kept per leaf voxel)
    block_policy: str = "reservoir"  # "reservoir": a uniform sample of the pairs the voxel received in the
                                     # window; "ring": the newest pairs (ablation)
    pairs_per_frame: int = 8         # at most this many of a frame's pairs offered to a voxel (0 = all)
    initial_blocks: int = 1 << 14    # blocks in the store at start (grown outside jit when full)
    carve: bool = True               # free space along the ray replaces the stored pairs it contradicts
                                     # (needs sampling.free_ray_n > 0): erases what moved away
    carve_margin_m: float = 0.05     # a stored pair is contradicted when its label < free label - distance - this
    carve_samples: int = 16384       # at most this many ray samples carve per frame (a fixed-size gather)
    carve_rule: str = "replace"      # "replace": a free sample takes the place of the pair it contradicts most;
                                     # "raise": every contradicted pair's label rises to the Lipschitz bound
    carve_sign: bool = False         # also: every ray sample (it is outside every object) raises the pairs stored
                                     # deeper inside than |x - y| + margin, in any voxel, recently hit or not


@dataclass(frozen=True)
class MeshConfig:
    resolution_m: float = 0.1        # marching-cubes lattice spacing, metres (must divide leaf_vox_size)
    min_component_faces: int = 50    # drop connected components smaller than this
    mask_level: int = 1              # mesh inside allocated voxels of this feature level (0 = leaf)
    min_leaf_corners: int = 6        # ... where at least this many leaf-voxel corners have features


@dataclass(frozen=True)
class EvalConfig:
    threshold_m: float = 0.1         # F-score threshold
    cull_distance_m: float = 0.3     # GT points farther than this from every scan point are culled
    eval_radius_m: float = -1.0      # >0: keep GT within this radius of some sensor position
    n_samples: int = 10_000_000      # points sampled on the cropped predicted mesh (SHINE: 10M)


@dataclass(frozen=True)
class MapConfig:
    """Root config of `jaxmap map` (N3-Mapping)."""

    data: DataConfig = field(default_factory=DataConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    output: str = "runs/map"         # run directory (`--out` overrides it)
    checkpoint_every: int = 50       # frames between checkpoints (also written at the end and on Ctrl-C or SIGTERM)


# ---------------------------------------------------------------------------------------------
# The transformable latent map config (jaxmap imt, jaxmap slam); indoor settings of the IMT paper.
# ---------------------------------------------------------------------------------------------


def _room_data() -> DataConfig:
    return DataConfig(path="data/room", every_frame=2)


def _room_preprocess() -> PreprocessConfig:
    return PreprocessConfig(min_range_m=0.1, max_range_m=8.0, vox_down_m=0.025)


@dataclass(frozen=True)
class LatentMapConfig:
    voxel_size_m: float = 0.1         # PLIVox side (IMT paper: 0.1 m indoors)
    min_points: int = 10              # voxels fed by fewer points of a frame are dropped
    interpolation: str = "trilinear"  # "trilinear" (splat, weight-conserving) or "softmax" (paper eq. 9)
    jacobian_sign: float = -1.0       # first-order term F - J t (-1); +1 = the paper's eq. 5; 0 = none
    softmax_temperature: float = 1.0  # softmax only: weights exp(-|t|^2 / T), t in voxel units
    k_neighbours: int = 8             # softmax only: local voxels gathered per global voxel
    splat_power: float = 2.0          # trilinear only: splat weights^power, renormalised (1 = plain trilinear)
    remap_min_rotation_deg: float = 0.05  # remap a keyframe whose pose moved more than this ...
    remap_min_translation_m: float = 0.002  # ... or this
    remap_rebuild_fraction: float = 0.5  # rebuild the map from every keyframe when more than this share moved
    cells_per_voxel: int = 1          # points are pooled into cells of voxel / this before encoding (0 = none)
    transform_cells_per_voxel: int = 2  # the same for local maps encoded with Jacobians (for `transform`)
    initial_capacity: int = 16384     # hash-table slots of the global map at start (grows, logged)
    prior: str = ""                   # prior weights (.npz); "" = the weights shipped in the package


@dataclass(frozen=True)
class LatentMeshConfig:
    resolution: int = 4               # marching-cubes lattice points per voxel side (even)
    sigma_threshold_m: float = 0.15   # drop triangles where the decoded SDF std exceeds this (<= 0: keep all)
    min_weight: float = 10.0          # voxels with less observation weight are not meshed
    min_component_faces: int = 0      # drop connected components smaller than this


@dataclass(frozen=True)
class ImtConfig:
    """Root config of `jaxmap imt` (transformable neural implicit map)."""

    data: DataConfig = field(default_factory=_room_data)
    preprocess: PreprocessConfig = field(default_factory=_room_preprocess)
    map: LatentMapConfig = field(default_factory=LatentMapConfig)
    mesh: LatentMeshConfig = field(default_factory=LatentMeshConfig)
    eval: EvalConfig = field(default_factory=lambda: EvalConfig(threshold_m=0.05, cull_distance_m=0.1,
                                                                n_samples=1_000_000))
    output: str = "runs/imt"            # run directory (`--out` overrides it)
    progress: bool = True             # tqdm progress bar


# ---------------------------------------------------------------------------------------------
# Value rules, checked when a config is loaded (file, --set, a checkpoint's meta.json). One table:
# RULES[dataclass][field] for single values, CHECKS[dataclass] for rules across fields. A key
# without a rule loads as its type allows; add its rule here (or `register_rules` from the module
# that defines a config dataclass elsewhere).
# ---------------------------------------------------------------------------------------------

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


def _host_preprocess_checks(c: Any, x: str):
    """`jaxmap imt` and `jaxmap slam` preprocess on the host only."""
    if c.preprocess.device:
        yield (f"{x}preprocess.device",), (
            f"{x}preprocess.device=true is for `jaxmap map` (N3) only; this command preprocesses on the host: "
            "set it to false")


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
    if p.device and p.normals == "knn":
        yield (f"{x}device", f"{x}normals"), (
            f"{x}device=true needs {x}normals=cube_knn or grid (k nearest neighbours over the whole scan run on "
            "the host only); set one of them")
    if p.device and p.outlier_mad > 0:
        yield (f"{x}device", f"{x}outlier_mad"), (
            f"{x}device=true cannot remove outliers ({x}outlier_mad={p.outlier_mad!r} runs on the host); "
            f"set {x}device=false or {x}outlier_mad=0")
    if p.normals != "knn":
        yield from _grid_checks(p, x)


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
                       "outlier_mad": at_least(0.0), "normals": one_of("knn", "grid", "cube_knn"),
                       "normal_cell_m": above(0.0), "normal_levels": at_least(1)},
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
                      "cells_per_voxel": at_least(0), "transform_cells_per_voxel": at_least(0)},
    LatentMeshConfig: {"resolution": EVEN_AT_LEAST_2, "min_weight": at_least(0.0), "min_component_faces": at_least(0)},
    ImtConfig: {"output": NONEMPTY},
}

CHECKS: dict[type, list[Callable[[Any, str], Any]]] = {
    MapConfig: [_map_checks],
    ImtConfig: [_host_preprocess_checks],
    DataConfig: [_data_checks],
    PreprocessConfig: [_preprocess_checks],
}


def register_rules(schema: type, checks: Sequence[Callable[[Any, str], Any]] = (), **rules: Rule) -> None:
    """Add rules for the fields of config dataclass `schema` (defined outside this module), and checks
    across its fields (see `_map_checks`)."""
    RULES.setdefault(schema, {}).update(rules)
    CHECKS.setdefault(schema, []).extend(c for c in checks if c not in CHECKS.get(schema, []))


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


# ---------------------------------------------------------------------------------------------
# Generic loading, validation and overrides.
# ---------------------------------------------------------------------------------------------


def unknown_key_message(source: str, keys: Sequence[str], depth: int, here: dict[str, bool]) -> str:
    """The error for `keys[depth]`, unknown among `here` ({name: is a section} at that depth): an unknown
    section (the key goes on, or names a mapping) is matched against section names, a key against keys."""
    prefix = ".".join(keys[:depth]) + "." if depth else ""
    name, section = keys[depth], depth < len(keys) - 1
    kind = "section" if section else "key"
    pool = [n for n, is_sec in here.items() if is_sec == section] or list(here)
    close = difflib.get_close_matches(name, pool, n=1, cutoff=0.6)
    if close:
        hint = f"did you mean '{prefix}{close[0]}'?"
    else:
        hint = f"valid {kind}s here: {', '.join(prefix + n for n in pool)}"
    return f"{source}: unknown config {kind} '{prefix}{name}'; {hint}"


def _coerce(value: Any, typ: Any, where: str) -> Any:
    """Check/convert a YAML scalar to the declared field type (int->float is allowed)."""
    origin = typing.get_origin(typ)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (elem, *_rest) = typing.get_args(typ)
        return tuple(_coerce(v, elem, where) for v in value)
    if typ is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0"):
            return value.lower() in ("true", "yes", "1")
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        try:
            return int(value)
        except ValueError:
            raise ConfigError(f"{where}: expected an integer, got {value!r}") from None
    if typ is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if typ is str:
        if not isinstance(value, (str, int, float)):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return str(value)
    return value


def from_dict(schema: type, data: dict | None, source: str = "<config>", prefix: str = "", base: Any = None,
              check: bool = True) -> Any:
    """Build dataclass `schema` from a nested dict, rejecting unknown keys with a suggestion and (the
    root call, unless `check=False`) values that break a rule of `RULES` / `CHECKS` (see `validate`).

    Missing keys keep the defaults of `base` (an instance of `schema`; default: `schema()`), so a
    section whose default differs from its class defaults (e.g. `ImtConfig.data`) keeps them.
    """
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: section '{prefix or '<root>'}' must be a mapping, got {data!r}")
    hints = typing.get_type_hints(schema)
    fields = {f.name: f for f in dataclasses.fields(schema)}
    kwargs = {}
    for key, value in data.items():
        full = f"{prefix}{key}"
        if key not in fields:
            here = {k: dataclasses.is_dataclass(hints[k]) for k in fields}
            keys = full.split(".") + ([""] if isinstance(value, dict) else [])  # a mapping: an unknown section
            raise ConfigError(unknown_key_message(source, keys, len(keys) - 1 - isinstance(value, dict), here))
        typ = hints[key]
        if dataclasses.is_dataclass(typ):
            sub = getattr(base, key) if base is not None else _field_default(fields[key])
            kwargs[key] = from_dict(typ, value, source, prefix=f"{full}.", base=sub)
        else:
            kwargs[key] = _coerce(value, typ, f"{source}: {full}")
    cfg = dataclasses.replace(base, **kwargs) if base is not None else schema(**kwargs)
    if check and not prefix:
        validate(cfg, source)
    return cfg


def _field_default(f: dataclasses.Field) -> Any:
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None if f.default is dataclasses.MISSING else f.default


def to_dict(cfg: Any) -> dict:
    """Dataclass tree -> plain nested dict (tuples as lists), for YAML/JSON."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = to_dict(v)
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


def apply_overrides(cfg: Any, overrides: Sequence[str], source: str = "--set") -> Any:
    """Apply `section.key=value` strings (value parsed as YAML) to a dataclass tree, then `validate` it."""
    cfg, origins = _override(cfg, overrides, source)
    validate(cfg, source, origins)
    return cfg


def _override(cfg: Any, overrides: Sequence[str], source: str) -> tuple[Any, dict[str, str]]:
    """(`cfg` with the overrides applied, not yet validated; {key: the override that set it})."""
    if not overrides:
        return cfg, {}
    tree, origins = to_dict(cfg), {}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"{source} '{item}': expected section.key=value, e.g. train.iters=20")
        path, raw = item.split("=", 1)
        keys = path.strip().split(".")
        node = tree
        for depth, k in enumerate(keys):
            if not isinstance(node, dict) or k not in node:
                here = {n: isinstance(v, dict) for n, v in node.items()} if isinstance(node, dict) else {}
                raise ConfigError(unknown_key_message(f"{source} '{item}'", keys, depth, here))
            if depth == len(keys) - 1:
                if isinstance(node[k], dict):
                    raise ConfigError(f"{source} '{item}': '{path}' is a section, name one of its keys")
                node[k] = yaml.safe_load(raw)
                origins[path.strip()] = f"{source} '{item}'"
            else:
                node = node[k]
    return from_dict(type(cfg), tree, source, check=False), origins


def load_config(path: str | os.PathLike | None, overrides: Sequence[str] = (), schema: type = MapConfig) -> Any:
    """Load a YAML config file into `schema`, then apply overrides. `path=None` gives defaults."""
    if path is None:
        cfg, origins = _override(schema(), overrides, "--set")
        validate(cfg, "<defaults>", origins)
        return cfg
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigError(f"config file not found: {path} (the shipped ones are in configs/)")
    with open(path) as f:
        try:
            data = yaml.safe_load(f)
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {e}") from None
    cfg, origins = _override(from_dict(schema, data, source=path, check=False), overrides, "--set")
    validate(cfg, path, origins)
    return cfg


def shipped_config_path(name: str) -> str | None:
    """`configs/<name>` of the source checkout (what `make demo` and `jaxmap bench` use), wherever the
    command runs from; None for an installed package without it (the dataclass defaults then)."""
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "configs", name)
    return os.path.normpath(path) if os.path.isfile(path) else None


def config_from_args(args, schema: type = MapConfig) -> Any:
    """The config of a mapping command: `args.config` with `--set` overrides, then `--data` and `--out`
    (which override data.path and output)."""
    overrides = list(args.overrides)
    if getattr(args, "data", None):
        overrides.append(f"data.path={args.data}")
    if getattr(args, "out", None):
        overrides.append(f"output={args.out}")
    return load_config(args.config, overrides, schema=schema)


def save_config(cfg: Any, path: str | os.PathLike) -> None:
    """Write the resolved config as YAML (what the run actually used)."""
    with open(path, "w") as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)
