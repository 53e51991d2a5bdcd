"""The `jaxmap` command line: its arguments (one function per command) and `main`, which runs the
command of the same name in `jaxmap.commands` and turns a user's mistake into one line, not a traceback.
`jaxmap --help` is instant: nothing heavy is imported before a command needs it."""
from __future__ import annotations

import argparse
import logging
import math
import sys


def _add_config_args(p: argparse.ArgumentParser, default_config: str | None = None,
                     example: str = "train.iters=20") -> None:
    default = f" (default: {default_config})" if default_config else ""
    p.add_argument("config", nargs="?" if default_config is not None else None, default=default_config or None,
                   help=f"a shipped config by name{default} or a YAML file; `jaxmap configs` lists the names")
    p.add_argument("--data", help="sequence directory; overrides data.path")
    p.add_argument("--out", help="run directory; overrides output")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help=f"override a config key, e.g. --set {example} (repeatable)")


def _add_overwrite_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="the run directory holds a run already: delete everything in it first")


def _add_view_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--view", action="store_true",
                   help="live browser viewer (viser, bound to 0.0.0.0; pip install 'jaxmap[view]')")
    p.add_argument("--view-port", type=int, default=8080, help="viewer port")
    p.add_argument("--view-mesh-every", type=int, default=10,
                   help="re-extract the viewer's mesh every N frames, in a background thread (0 = never)")


def _positive_km(text: str) -> float:
    """--length-km's type: a positive, finite number of km (argparse reports anything else)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of km: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number of km, not {text}")
    return value


def _synth_args(sub) -> None:
    p = sub.add_parser("synth", help="write a synthetic sequence with exact ground truth")
    p.add_argument("scene", choices=["city", "room"])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--small", action="store_true", help="small preset (tests, quick looks)")
    p.add_argument("--frames", type=int, default=None, metavar="N",
                   help="the preset's whole closed loop in N frames, evenly spaced (default per preset: city 130, "
                        "--small 64, room 120, room --small 10): fewer frames are farther apart, the drive is not "
                        "shorter (--long: its first N frames). For part of a drive, map its first frames: "
                        "jaxmap map city --data DIR --set data.end_frame=N")
    p.add_argument("--noise", type=float, default=0.0, help="range noise std in metres")
    p.add_argument("--pedestrians", action="store_true", help="city: add moving pedestrians (not in the GT)")
    p.add_argument("--long", action="store_true",
                   help="city: a 1.1 km serpentine drive through a 256 m x 200 m city, 1025 frames")
    p.add_argument("--length-km", type=_positive_km, default=None, metavar="X",
                   help="city --long: a drive of about X km through the same city instead: the serpentine, then "
                        "loops around groups of blocks back over streets already driven, passing its intersections "
                        "again (like KITTI's sequence 00); frames 1.09 m apart (3.7 km: 3400 frames, ~3.4 GB of "
                        "scans); meta.json records the route's length and revisits")
    p.add_argument("--layout", choices=["grid", "suburb"], default="grid",
                   help="city: the street grid (default) or a curved ring boulevard with detached houses")
    p.add_argument("--beams", default=None, metavar="N|hdl64|vlp32",
                   help="city: the LiDAR's beams: N uniform beams from -25 to +2 deg (default per preset: 64, small 32), "
                        "or a real sensor's beam table: hdl64 (KITTI's two-block HDL-64E, per-beam jitter, 1024 "
                        "azimuth steps), vlp32 (a VLP-32C, -25 to +15 deg, dense near the horizon, 1800 steps)")
    p.add_argument("--traffic", type=int, default=0, metavar="N",
                   help="city: N moving objects in the scans, never in the GT (~2/3 cars: ahead of the sensor in its "
                        "lane, oncoming, overtaking it at up to 17 m/s, moving like cars; the rest pedestrians crossing "
                        "the drive's street, on the sidewalks and side-street crossings); per-frame boxes in "
                        "moving_objects.json; grid and suburb layouts, not --long")
    p.add_argument("--parking", action="store_true",
                   help="city: two more cars by a curb of the drive's street: one parked at the start that drives off "
                        "mid-sequence (never in the GT) and one that parks mid-sequence and stays (in the GT at its "
                        "place, class parked_car: the GT is the static world at the end); alone or with --traffic")
    p.add_argument("--realistic", nargs="?", const="all", default=None, metavar="LIST",
                   help="city: real spinning-LiDAR artifacts, all (no LIST) or a comma list of: mixed (mixed pixels: "
                        "at a > 0.3 m azimuth range jump, p = 0.5, a range uniform between foreground and background), "
                        "dropout (lost returns at grazing incidence, p = clip(1 - |cos|/0.2, 0, 1) * 0.8, and on dark "
                        "surfaces, p = 0.5-0.9 rising with range; intensity = reflectivity), outliers (1 in 2000 "
                        "returns at a range uniform in 0.5-50 m), beam_offsets (a constant N(0, 1 cm) range offset "
                        "per beam)")
    p.add_argument("--lane-shift", type=float, default=0.0, metavar="M",
                   help="city: a second drive through the same city: the loop shifted outward by M metres "
                        "(negative: towards the centre line), same scene (for jaxmap localize)")
    p.add_argument("--start", type=float, default=0.0, metavar="M",
                   help="city: the drive starts M metres along the loop (same scene)")


def _eval_args(sub) -> None:
    p = sub.add_parser("eval", help="reconstruction metrics of a mesh against a sequence's ground truth",
                       description="Scores a mesh against a sequence's ground truth. The mesh of a jaxmap map or "
                                   "imt run (its directory, or a mesh file in it) is scored as the run scored it "
                                   "(its metrics.json): the ground truth cropped to the frames it mapped, its range "
                                   "crop and eval settings; the options below override them. Other meshes need "
                                   "--gt; every frame counts unless --frames says which.")
    p.add_argument("mesh", help="a mesh file, or a run directory (its mesh.ply)")
    p.add_argument("--gt", default=None,
                   help="sequence directory with gt_points.ply and scans (default: the run's data.path)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="the frames whose scans count as observed: A to B-1 (default: the frames the run mapped, "
                        "else all; a warning says when they are fewer than the sequence's)")
    p.add_argument("--threshold", type=float, default=None,
                   help="F-score threshold in metres (default: the run's eval.threshold_m, else 0.1)")
    p.add_argument("--cull", type=float, default=None,
                   help="cull GT farther than this from every scan point (m; default: the run's, else 0.3)")
    p.add_argument("--radius", type=float, default=None,
                   help="keep GT within this range of a sensor position (m; default: the run's eval.eval_radius_m, "
                        "else -1: no limit)")
    p.add_argument("--max-range", type=float, default=None,
                   help="count as observed only scan points within this range of their sensor (the mapper's crop; "
                        "default: the run's preprocess.max_range_m, else -1: no limit)")
    p.add_argument("--json-out", default=None, metavar="PATH",
                   help="also write the metrics to this JSON file (they are always printed as one JSON line)")
    p.add_argument("--protocol", choices=["shine", "surface"], default="shine",
                   help="shine: N3/SHINE eval_mesh (default); surface: also completion_surface_cm (GT -> mesh, exact)")
    p.add_argument("--samples", type=int, default=None,
                   help="points sampled on the cropped mesh (default: the run's eval.n_samples, else SHINE's 10M)")
    p.add_argument("--no-floor", action="store_true",
                   help="skip the protocol floor (the GT mesh evaluated as the prediction, under 'floor')")
    p.add_argument("--no-ghost", action="store_true",
                   help="skip the ghost area (predicted surface where only moving objects were; sequences with "
                        "moving_objects.json or pedestrians.json)")


def _baseline_args(sub) -> None:
    p = sub.add_parser("baseline", help="classical baselines on the same data")
    p.add_argument("method", choices=["tsdf"])
    p.add_argument("data")
    p.add_argument("--voxel", type=float, default=0.2, help="voxel size in metres")
    p.add_argument("--out", required=True, help="output mesh (.ply)")
    p.add_argument("--max-range", type=float, default=20.0, help="crop radius in metres")
    p.add_argument("--res", type=float, default=None, help="marching-cubes resolution (default = voxel)")


def _map_args(sub) -> None:
    p = sub.add_parser("map", help="N3 neural SDF mapping of a sequence")
    _add_config_args(p, default_config="")
    p.add_argument("--resume", metavar="RUN_DIR",
                   help="continue an interrupted run from its newest intact checkpoint")
    _add_overwrite_arg(p)
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--no-mesh", action="store_true", help="map and checkpoint only: no mesh, no metrics")
    _add_view_args(p)


def _mesh_args(sub) -> None:
    p = sub.add_parser("mesh", help="re-extract a mesh from a saved map")
    p.add_argument("run", help="run directory of jaxmap map (or of jaxmap slam with map_kind n3)")
    p.add_argument("--res", type=float, default=None, help="marching-cubes resolution in metres")
    p.add_argument("--out", default=None, help="output mesh (default RUN/mesh_<res>.ply)")


def _demo_args(sub) -> None:
    p = sub.add_parser("demo", help="synthetic city -> neural map -> mesh -> metrics")
    p.add_argument("--data", default="data/city_demo")
    p.add_argument("--out", default="runs/demo")


def _prior_args(sub) -> None:
    p = sub.add_parser("prior", help="train or evaluate the equivariant encoder/decoder prior")
    p.add_argument("action", choices=["train", "eval"])
    _add_config_args(p, default_config="prior", example="train.steps=2000")


def _imt_args(sub) -> None:
    p = sub.add_parser("imt", help="transformable latent map of a sequence: encode, fuse, mesh, metrics")
    _add_config_args(p, default_config="room_imt", example="map.voxel_size_m=0.05")
    _add_overwrite_arg(p)
    p.add_argument("--no-progress", action="store_true")
    _add_view_args(p)


def _slam_args(sub) -> None:
    p = sub.add_parser("slam", help="ICP odometry, loop closure, pose graph and a remapped neural map")
    _add_config_args(p, default_config="room_slam", example="frontend.odometry.method=kiss_icp")
    p.add_argument("--resume", metavar="RUN_DIR",
                   help="continue a map_kind n3 run stopped by Ctrl-C or SIGTERM from its saved state")
    _add_overwrite_arg(p)
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--no-mesh", action="store_true",
                   help="trajectory, map and checkpoint only: no mesh, no reconstruction metrics (the ATE is kept)")
    _add_view_args(p)


def _localize_args(sub) -> None:
    p = sub.add_parser("localize", help="localise a sequence in a saved N3 map (tracking against it, no map update)")
    p.add_argument("map", help="run directory of a jaxmap map run (or its checkpoint/ directory)")
    p.add_argument("--data", required=True, help="sequence directory to localise")
    p.add_argument("--init", default=None, metavar="POSE",
                   help="the first scan's pose in the map's world frame: 12 numbers (a KITTI line) or 16 (4x4), "
                        "in quotes, or a file holding them (default: the sequence's first pose from its poses.txt, "
                        "else the identity)")
    p.add_argument("--out", default="runs/localize", help="run directory (default runs/localize)")
    p.add_argument("--voxel", type=float, default=0.2, help="scans are downsampled to this voxel (m) for tracking")
    p.add_argument("--points", type=int, default=4096, help="scan points used per frame (a random subset)")
    _add_overwrite_arg(p)
    p.add_argument("--no-progress", action="store_true")


def _configs_args(sub) -> None:
    p = sub.add_parser("configs", help="list the configs shipped with jaxmap (every command takes them by name)")
    p.add_argument("name", nargs="?", default=None,
                   help="print this shipped config (YAML), e.g. `jaxmap configs city > my.yaml` to start your own")


def _info_args(sub) -> None:
    p = sub.add_parser("info", help="what a sequence is: kind, frames, ROS bag topics with types and counts")
    p.add_argument("path", help="sequence directory or file (KITTI, depth, ROS bag/MCAP, TUM RGB-D, Replica, LAS)")
    p.add_argument("--kind", default="auto", help="sequence kind (default: detected, as data.kind)")
    p.add_argument("--topic", default="", help="ROS bag: the PointCloud2 topic to count frames of (data.topic)")


def _view_args(sub) -> None:
    p = sub.add_parser("view", help="open a finished run in the browser viewer (mesh, trajectory, errors)")
    p.add_argument("run", help="run directory (mesh.ply, config.yaml, trajectory_kitti.txt)")
    p.add_argument("--port", type=int, default=8080, help="viewer port (bound to 0.0.0.0)")
    p.add_argument("--no-wait", action="store_true", help="load the scene and exit (for tests)")


def _bench_args(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks: speed, memory and quality against baselines")
    p.add_argument("suite", choices=["n3", "imt", "slam", "commands", "path"],
                   help="commands: what a user waits for, every command (jaxmap map cold and warm with host and "
                        "device preprocessing, jaxmap imt, jaxmap slam); path: the way one scan (--frames K, "
                        "default 3) takes through jaxmap map to the frame program (modules, moves between them)")
    p.add_argument("--data", default=None,
                   help="where the benchmark scene is, made if missing "
                        "(n3, commands and path: data/city_bench, imt: data/room_bench, slam: data/room_noisy)")
    p.add_argument("--out", default=None, help="output directory (default runs/bench_SUITE)")
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--only", default=None, help="comma-separated subset of variants")
    p.add_argument("--long", action="store_true",
                   help="n3: the 1.1 km drive of `jaxmap synth city --long` (per-frame cost and memory over time)")
    p.add_argument("--length-km", type=_positive_km, default=None, metavar="X",
                   help="n3 --long: an X km drive with loops over streets already driven (`jaxmap synth city --long "
                        "--length-km X`, made in data/city_long_<X>km if missing and no --data); tables every 500 "
                        "and 100 frames of time, RSS, device memory and submaps")
    p.add_argument("--suite", dest="validation_suite", action="store_true",
                   help="n3: the validation suite (7 cities: seeds, layouts, noise, real sensors' beam tables, traffic, "
                        "artifacts) on which defaults are "
                        "chosen; rows, mean and worst; --only picks variants (default jaxmap). slam: five 130-frame "
                        "streets (layouts, noise, beam tables), jaxmap slam against the true-pose map on each (ATE, "
                        "height and tilt error, C-L1 ratio, road error, loop seconds); --only names the row, --set "
                        "its settings")
    p.add_argument("--cities", default=None,
                   help="n3 or slam --suite: comma-separated subset of the suite's cities or streets (the variant's "
                        "other rows in OUT/suite.json or OUT/slam_suite.json are kept)")
    p.add_argument("--profile", action="store_true",
                   help="n3 --only speed: where a frame's time goes, stage by stage: the frame program under XLA's profiler "
                        "(summed by stage), what each feature costs in it, and the host's preprocessing")
    p.add_argument("--profile-at", type=int, default=40, help=argparse.SUPPRESS)
    p.add_argument("--profile-frames", type=int, default=5, help=argparse.SUPPRESS)
    p.add_argument("--profile-rounds", type=int, default=5, help=argparse.SUPPRESS)
    p.add_argument("--quick", action="store_true",
                   help="commands: the small city and room, a few frames each (checks that the whole bench runs)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key of the benchmark's runs, e.g. --set train.iters=20 (repeatable)")


def _check_combinations(parser: argparse.ArgumentParser, args) -> None:
    """Option combinations argparse does not check by itself, reported as argparse reports errors (the
    command's usage and one line, exit status 2)."""
    if getattr(args, "length_km", None) is not None and not args.long:
        what = "jaxmap synth city --long" if args.command == "synth" else "jaxmap bench n3 --long"
        parser.subcommand_parsers[args.command].error(f"--length-km is the length of the long drive: use it with "
                                                      f"--long ({what} --length-km X)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxmap", description="Neural implicit 3D mapping in JAX.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true",
                        help="show the Python traceback of an error (by default: one line saying what to fix)")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_synth_args, _eval_args, _baseline_args, _map_args, _mesh_args, _demo_args, _prior_args, _imt_args, _slam_args, _localize_args, _configs_args, _info_args, _view_args, _bench_args):
        add(sub)
    parser.subcommand_parsers = sub.choices  # (for errors in the command's usage: _check_combinations)
    return parser


def main(argv: list[str] | None = None) -> int:
    from jaxmap import hostmem

    hostmem.limit_arenas()
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_combinations(parser, args)
    # Our messages at INFO; other libraries' (jax's backend probing, orbax) only from WARNING. Records
    # of the "jaxmap" logger pass its own level and then reach the root handler whatever the root level.
    logging.basicConfig(level=logging.WARNING, format="[%(name)s] %(message)s", stream=sys.stderr)
    ours = logging.getLogger("jaxmap")
    ours.setLevel(logging.DEBUG if args.verbose else logging.INFO)
    from tqdm.contrib.logging import logging_redirect_tqdm

    from jaxmap.errors import JaxmapError
    from jaxmap.rundir import exit_code

    from jaxmap import commands

    try:
        with logging_redirect_tqdm():  # log lines above the progress bars, not through them
            return getattr(commands, args.command)(args)
    except JaxmapError as e:
        if args.debug:
            raise
        print(f"jaxmap {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        if args.debug:
            raise
        print(f"jaxmap {args.command}: interrupted ({e or 'SIGINT'})", file=sys.stderr)
        return exit_code(e)
    except OSError as e:
        # A path the user gave that cannot be read or written (permissions, a full or read-only disk):
        # one line naming it. Errors without a file name are not about a path: a traceback.
        if args.debug or not e.filename:
            raise
        print(f"jaxmap {args.command}: error: {e.filename}: {e.strerror}; check the path and its permissions "
              "(--debug shows the traceback)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
