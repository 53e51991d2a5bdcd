"""What `jaxmap eval` scores: a mesh alone, or the mesh of a run as the run scored it.

A mesh alone (a baseline's, another system's) is scored against the ground truth of `--gt`'s sequence,
every frame's scans counting as observed unless `--frames A:B` says which. The mesh of a `jaxmap map` or
`jaxmap imt` run (the run directory, or a mesh file in it: mesh.ply, mesh_0.2.ply of `jaxmap mesh`) is
scored through `jaxmap.finish.evaluate_run_mesh` with the run's config.yaml, the code that wrote the
run's metrics.json: the ground truth is cropped to what the frames the run mapped observed
(data.begin_frame / end_frame / every_frame; a run that did not finish: the frames of its newest
checkpoint), within its range crop, with its eval settings. `--gt`, `--frames` and the protocol flags
override the run's values. A warning says when the frames scored are fewer than the sequence's, or more
than the run mapped.
"""
from __future__ import annotations

import dataclasses
import logging
import os

from jaxmap.errors import ConfigError, DataError

log = logging.getLogger("jaxmap")

# The flags' values for a mesh without a run (the standard protocol's MaiCity settings), and the run's
# config key each flag overrides.
DEFAULTS = {"threshold": 0.1, "cull": 0.3, "radius": -1.0, "max_range": -1.0, "samples": 10_000_000}
RUN_KEYS = {"threshold": ("eval", "threshold_m"), "cull": ("eval", "cull_distance_m"),
            "radius": ("eval", "eval_radius_m"), "max_range": ("preprocess", "max_range_m"),
            "samples": ("eval", "n_samples")}


def parse_frames(text: str) -> tuple[int, int]:
    """`--frames A:B` -> (begin_frame, end_frame): frames A to B-1 (B exclusive, as data.end_frame; an
    empty A is 0, an empty B the end, -1)."""
    a, sep, b = text.partition(":")
    try:
        begin, end = int(a or 0), int(b) if b else -1
    except ValueError:
        begin, end = -1, -1
    if not sep or begin < 0 or (end != -1 and end <= begin):
        raise ConfigError(f"--frames {text}: expected A:B, the frames A to B-1 of the sequence (e.g. --frames 0:20; "
                          "0: for all)")
    return begin, end


def find_run(path: str) -> tuple[str, str | None, str | None]:
    """(the mesh file, the run directory it belongs to or None, the run's command): `path` is a mesh file
    or the directory of a map or imt run (its mesh.ply)."""
    from jaxmap.rundir import inspect

    if os.path.isdir(path):
        state = inspect(path)
        if state.kind != "run":
            raise DataError(f"{path}: neither a mesh file nor a jaxmap run directory; pass a mesh (.ply) or a run's --out")
        mesh = os.path.join(path, "mesh.ply")
        if not os.path.isfile(mesh):
            raise DataError(f"{path}: the run has no mesh.ply (mapped with --no-mesh, or not finished); write one "
                            f"with `jaxmap mesh {path}` and evaluate that file")
        run = path
    else:
        mesh, run = path, os.path.dirname(path) or "."
    state = inspect(run)
    if state.kind != "run" or state.command not in ("map", "imt", None) \
            or not os.path.isfile(os.path.join(run, "config.yaml")):
        return mesh, None, None
    return mesh, run, state.command or "map"


def run_config(run: str, command: str, args):
    """The run's config as `evaluate_run_mesh` takes it: the frames it mapped, --gt, --frames and the
    flags given (not None) in place of its own values."""
    from jaxmap.config import ImtConfig, MapConfig, load_config
    from jaxmap.rundir import inspect

    cfg = load_config(os.path.join(run, "config.yaml"), schema=ImtConfig if command == "imt" else MapConfig)
    d = cfg.data
    state = inspect(run)
    if state.status != "finished" and state.frames:  # an interrupted run: the frames its newest checkpoint holds
        end = d.begin_frame + (state.frames - 1) * d.every_frame + 1
        d = dataclasses.replace(d, end_frame=end if d.end_frame == -1 else min(end, d.end_frame))
    mapped = d
    if args.frames:
        begin, end = parse_frames(args.frames)
        d = dataclasses.replace(d, begin_frame=begin, end_frame=end)
    if args.gt:
        d = dataclasses.replace(d, path=args.gt)
    elif not os.path.exists(d.path):
        raise DataError(f"{os.path.join(run, 'config.yaml')}: the run's data {d.path} is not found from "
                        f"{os.getcwd()}; pass its ground truth with --gt DIR")
    cfg = dataclasses.replace(cfg, data=d)
    for flag, (section, key) in RUN_KEYS.items():
        value = getattr(args, flag)
        if value is not None:
            cfg = dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **{key: value})})
    return cfg, mapped


def frame_range(path: str, begin: int, end: int, every: int) -> list[int]:
    """The frame numbers of sequence `path` that range(begin, end, every) selects (end -1: to the end)."""
    from jaxmap.io import open_sequence

    return [int(i) for i in open_sequence(path, begin_frame=begin, end_frame=end, every_frame=every).indices]


def _span(frames: list[int]) -> str:
    return f"{frames[0]}-{frames[-1]}" if frames else "none"


def warn_if_partial(run: str, cfg, mapped) -> None:
    """Warn when the frames scored cover less of the sequence than it holds, or more than the run mapped."""
    d = cfg.data
    every = frame_range(d.path, 0, -1, 1)
    scored = frame_range(d.path, d.begin_frame, d.end_frame, d.every_frame)
    ran = frame_range(d.path, mapped.begin_frame, mapped.end_frame, mapped.every_frame)
    if ran and scored and (scored[0] < ran[0] or scored[-1] > ran[-1]):
        log.warning("the mesh's run %s mapped frames %s only; frames %s of %s are scored, ground "
                    "truth the run never observed counts as missed", run, _span(ran), _span(scored), d.path)
    elif scored and (scored[0] > every[0] or scored[-1] < every[-1]):
        log.warning("the mesh's run %s mapped frames %s of the %d in %s: the ground truth is cropped "
                    "to what those frames observed, as the run's metrics.json (--frames %d:%d scores all of them)",
                    run, _span(scored), len(every), d.path, every[0], every[-1] + 1)


def evaluate(args) -> tuple[dict, str, str]:
    """(the metrics `jaxmap eval` prints (see the module docstring), the mesh file, the sequence scored
    against)."""
    from jaxmap.finish import evaluate_run_mesh
    from jaxmap.metrics import evaluate_mesh_file

    mesh, run, command = find_run(args.mesh)
    common = dict(floor=not args.no_floor, protocol=args.protocol, ghost=not args.no_ghost)
    if run is not None:
        cfg, mapped = run_config(run, command, args)
        warn_if_partial(run, cfg, mapped)
        return evaluate_run_mesh(mesh, cfg, **common), mesh, cfg.data.path
    if not args.gt:
        raise ConfigError(f"{args.mesh}: not the mesh of a jaxmap map or imt run (no config.yaml beside it), so "
                          "name its sequence: --gt DIR")
    v = {k: DEFAULTS[k] if getattr(args, k) is None else getattr(args, k) for k in DEFAULTS}
    begin, end = parse_frames(args.frames) if args.frames else (0, -1)
    m = evaluate_mesh_file(mesh, args.gt, threshold_m=v["threshold"], cull_distance_m=v["cull"],
                           eval_radius_m=v["radius"], max_range_m=v["max_range"], n_samples=v["samples"],
                           begin_frame=begin, end_frame=end, **common)
    return m, mesh, args.gt
