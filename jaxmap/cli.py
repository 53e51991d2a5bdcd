"""The `jaxmap` command. Each subcommand imports its implementation lazily, so `jaxmap --help`
is instant and the mapping core never pulls open3d in unless a subcommand needs it."""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys


def _add_config_args(p: argparse.ArgumentParser, default_config: str | None = None,
                     example: str = "train.iters=20") -> None:
    p.add_argument("config", nargs="?" if default_config is not None else None, default=default_config or None,
                   help="YAML config (see configs/)")
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxmap", description="Neural implicit 3D mapping in JAX.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true",
                        help="show the Python traceback of an error (by default: one line saying what to fix)")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("synth", help="write a synthetic sequence with exact ground truth")
    p.add_argument("scene", choices=["city", "room"])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--small", action="store_true", help="small preset (tests, quick looks)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default per preset)")
    p.add_argument("--noise", type=float, default=0.0, help="range noise std in metres")
    p.add_argument("--pedestrians", action="store_true", help="city: add moving pedestrians (not in the GT)")
    p.add_argument("--long", action="store_true",
                   help="city: a 1.1 km serpentine drive through a 256 m x 200 m city, 1025 frames")
    p.add_argument("--layout", choices=["grid", "suburb"], default="grid",
                   help="city: the street grid (default) or a curved ring boulevard with detached houses")
    p.add_argument("--beams", type=int, default=None, help="city: LiDAR beams (default per preset: 64, small 32)")
    p.add_argument("--traffic", type=int, default=0, metavar="N",
                   help="city: N moving objects in the scans, never in the GT (~2/3 cars driving the lanes at 5-12 m/s "
                        "ahead / oncoming / overtaking, the rest pedestrians on the sidewalks and crossings); "
                        "per-frame boxes in moving_objects.json; grid and suburb layouts, not --long")
    p.add_argument("--realistic", nargs="?", const="all", default=None, metavar="LIST",
                   help="city: real spinning-LiDAR artifacts, all (no LIST) or a comma list of: mixed (mixed pixels: "
                        "at a > 0.3 m azimuth range jump, p = 0.5, a range uniform between foreground and background), "
                        "dropout (lost returns at grazing incidence, p = clip(1 - |cos|/0.2, 0, 1) * 0.8, and on dark "
                        "surfaces, p = 0.5-0.9 rising with range; intensity = reflectivity), outliers (1 in 2000 "
                        "returns at a range uniform in 0.5-50 m), beam_offsets (a constant N(0, 1 cm) range offset "
                        "per beam)")

    p = sub.add_parser("eval", help="reconstruction metrics of a mesh against a sequence's ground truth")
    p.add_argument("mesh")
    p.add_argument("--gt", required=True, help="sequence directory with gt_points.ply and scans")
    p.add_argument("--threshold", type=float, default=0.1, help="F-score threshold in metres")
    p.add_argument("--cull", type=float, default=0.3, help="cull GT farther than this from every scan point (m)")
    p.add_argument("--radius", type=float, default=-1.0, help="keep GT within this range of a sensor position (m)")
    p.add_argument("--max-range", type=float, default=-1.0,
                   help="count as observed only scan points within this range of their sensor (the mapper's crop)")
    p.add_argument("--json-out", default=None, metavar="PATH",
                   help="also write the metrics to this JSON file (they are always printed as one JSON line)")
    p.add_argument("--protocol", choices=["shine", "surface"], default="shine",
                   help="shine: N3/SHINE eval_mesh (default); surface: also completion_surface_cm (GT -> mesh, exact)")
    p.add_argument("--samples", type=int, default=10_000_000, help="points sampled on the cropped mesh (SHINE: 10M)")
    p.add_argument("--no-floor", action="store_true",
                   help="skip the protocol floor (the GT mesh evaluated as the prediction, under 'floor')")
    p.add_argument("--no-ghost", action="store_true",
                   help="skip the ghost area (predicted surface where only moving objects were; sequences with "
                        "moving_objects.json or pedestrians.json)")

    p = sub.add_parser("baseline", help="classical baselines on the same data")
    p.add_argument("method", choices=["tsdf"])
    p.add_argument("data")
    p.add_argument("--voxel", type=float, default=0.2, help="voxel size in metres")
    p.add_argument("--out", required=True, help="output mesh (.ply)")
    p.add_argument("--max-range", type=float, default=20.0, help="crop radius in metres")
    p.add_argument("--res", type=float, default=None, help="marching-cubes resolution (default = voxel)")

    p = sub.add_parser("map", help="N3 neural SDF mapping of a sequence")
    _add_config_args(p, default_config="")
    p.add_argument("--resume", metavar="RUN_DIR",
                   help="continue an interrupted run from its newest intact checkpoint")
    _add_overwrite_arg(p)
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--no-mesh", action="store_true", help="map and checkpoint only: no mesh, no metrics")
    _add_view_args(p)

    p = sub.add_parser("mesh", help="re-extract a mesh from a saved map")
    p.add_argument("run", help="run directory")
    p.add_argument("--res", type=float, default=None, help="marching-cubes resolution in metres")
    p.add_argument("--out", default=None, help="output mesh (default RUN/mesh_<res>.ply)")

    p = sub.add_parser("demo", help="synthetic city -> neural map -> mesh -> metrics")
    p.add_argument("--data", default="data/city_demo")
    p.add_argument("--out", default="runs/demo")

    p = sub.add_parser("prior", help="train or evaluate the equivariant encoder/decoder prior")
    p.add_argument("action", choices=["train", "eval"])
    _add_config_args(p, default_config="configs/prior.yaml", example="train.steps=2000")

    p = sub.add_parser("imt", help="transformable latent map of a sequence: encode, fuse, mesh, metrics")
    _add_config_args(p, default_config="configs/room_imt.yaml", example="map.voxel_size_m=0.05")
    _add_overwrite_arg(p)
    p.add_argument("--no-progress", action="store_true")
    _add_view_args(p)

    p = sub.add_parser("slam", help="ICP odometry, loop closure, pose graph and a remapped neural map")
    _add_config_args(p, default_config="configs/room_slam.yaml", example="frontend.odometry.method=kiss_icp")
    _add_overwrite_arg(p)
    p.add_argument("--no-progress", action="store_true")
    _add_view_args(p)

    p = sub.add_parser("info", help="what a sequence is: kind, frames, ROS bag topics with types and counts")
    p.add_argument("path", help="sequence directory or file (KITTI, depth, ROS bag/MCAP, TUM RGB-D, Replica, LAS)")
    p.add_argument("--kind", default="auto", help="sequence kind (default: detected, as data.kind)")
    p.add_argument("--topic", default="", help="ROS bag: the PointCloud2 topic to count frames of (data.topic)")

    p = sub.add_parser("view", help="open a finished run in the browser viewer (mesh, trajectory, errors)")
    p.add_argument("run", help="run directory (mesh.ply, config.yaml, trajectory_kitti.txt)")
    p.add_argument("--port", type=int, default=8080, help="viewer port (bound to 0.0.0.0)")
    p.add_argument("--no-wait", action="store_true", help="load the scene and exit (for tests)")

    p = sub.add_parser("bench", help="benchmarks: speed, memory and quality against baselines")
    p.add_argument("suite", choices=["n3", "imt", "slam"])
    p.add_argument("--data", default=None,
                   help="where the benchmark scene is, made if missing "
                        "(n3: data/city_bench, imt: data/room_bench, slam: data/room_noisy)")
    p.add_argument("--out", default=None, help="output directory (default runs/bench_SUITE)")
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--only", default=None, help="comma-separated subset of variants")
    p.add_argument("--long", action="store_true",
                   help="n3: the 1.1 km drive of `jaxmap synth city --long` (per-frame cost and memory over time)")
    p.add_argument("--suite", dest="validation_suite", action="store_true",
                   help="n3: the validation suite (4 cities: seeds, layouts, noise, beams) on which defaults are "
                        "chosen; rows, mean and worst; --only picks variants (default jaxmap)")
    p.add_argument("--cities", default=None,
                   help="n3 --suite: comma-separated subset of the suite's cities (the variant's other rows in "
                        "OUT/suite.json are kept)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    return parser


def main(argv: list[str] | None = None) -> int:
    from jaxmap import hostmem

    hostmem.limit_arenas()
    args = build_parser().parse_args(argv)
    # Our messages at INFO; other libraries' (jax's backend probing, orbax) only from WARNING. Records
    # of the "jaxmap" logger pass its own level and then reach the root handler whatever the root level.
    logging.basicConfig(level=logging.WARNING, format="[%(name)s] %(message)s", stream=sys.stderr)
    ours = logging.getLogger("jaxmap")
    ours.setLevel(logging.DEBUG if args.verbose else logging.INFO)
    from tqdm.contrib.logging import logging_redirect_tqdm

    from jaxmap.errors import JaxmapError
    from jaxmap.rundir import exit_code

    try:
        with logging_redirect_tqdm():  # log lines above the progress bars, not through them
            return _dispatch(args)
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


def _dispatch(args) -> int:
    if args.command == "synth":
        if args.scene == "city":
            from jaxmap.synth.city import generate_city as gen
        else:
            from jaxmap.synth.room import generate_room as gen
        from jaxmap.rundir import output_dir

        kw = {"pedestrians": True} if args.pedestrians else {}
        if args.pedestrians and args.scene != "city":
            raise SystemExit("jaxmap synth: --pedestrians is for the city scene")
        if args.long:
            if args.scene != "city":
                raise SystemExit("jaxmap synth: --long is for the city scene")
            if args.small:
                raise SystemExit("jaxmap synth: --long and --small are different presets; pick one")
            kw["long"] = True
        if args.scene == "city":
            kw["layout"] = args.layout
            if args.beams is not None:
                kw["beams"] = args.beams
            if args.traffic:
                kw["traffic"] = args.traffic
            if args.realistic is not None:
                kw["realistic"] = args.realistic
        elif args.layout != "grid" or args.beams is not None or args.traffic or args.realistic is not None:
            raise SystemExit("jaxmap synth: --layout, --beams, --traffic and --realistic are for the city scene")
        output_dir(args.out)
        stats = gen(args.out, seed=args.seed, small=args.small, n_frames=args.frames, noise_m=args.noise, **kw)
        print(json.dumps(stats))
        return 0
    if args.command == "eval":
        from jaxmap.metrics import evaluate_mesh_file, format_metrics
        from jaxmap.rundir import output_file

        if args.json_out:
            output_file(args.json_out, "--json-out")  # before the metrics are computed, not after
        m = evaluate_mesh_file(args.mesh, args.gt, threshold_m=args.threshold,
                               cull_distance_m=args.cull, eval_radius_m=args.radius, max_range_m=args.max_range,
                               n_samples=args.samples, protocol=args.protocol, floor=not args.no_floor,
                               ghost=not args.no_ghost)
        print(format_metrics(m, "mesh"))
        if args.json_out:
            with open(args.json_out, "w") as f:
                json.dump(m, f)
        print(json.dumps(m))
        return 0
    if args.command == "baseline":
        from jaxmap.baselines.tsdf import tsdf_from_sequence
        from jaxmap.rundir import output_file

        output_file(args.out)
        info = tsdf_from_sequence(args.data, voxel_m=args.voxel, out_mesh=args.out,
                                  max_range_m=args.max_range, mesh_res_m=args.res)
        print(json.dumps(info))
        return 0
    if args.command in ("map", "mesh", "demo"):
        from jaxmap.n3 import run as n3run

        return getattr(n3run, f"cli_{args.command}")(args)
    if args.command == "prior":
        from jaxmap.imt import training

        return training.cli_train(args) if args.action == "train" else training.cli_eval(args)
    if args.command == "slam":
        from jaxmap.slam import run as slam_run

        return slam_run.cli_slam(args)
    if args.command == "imt":
        from jaxmap.imt import run as imt_run

        return imt_run.cli_imt(args)
    if args.command == "info":
        from jaxmap.info import format_info, sequence_info

        print(format_info(sequence_info(args.path, kind=args.kind, topic=args.topic)))
        return 0
    if args.command == "view":
        from jaxmap.viewer import view_run

        return view_run(args.run, port=args.port, wait=not args.no_wait)
    if args.command == "bench":
        args.out = args.out or f"runs/bench_{args.suite}"
        if args.suite == "slam":
            from jaxmap.bench import slam as bench_slam

            args.data = args.data or "data/room_noisy"
            return bench_slam.main(args)
        if args.suite == "imt":
            from jaxmap.bench import imt as bench_imt

            args.data = args.data or "data/room_bench"
            return bench_imt.main(args)
        from jaxmap.bench import n3 as bench_n3

        args.data = args.data or "data/city_bench"
        return bench_n3.main(args)
    raise AssertionError(args.command)


if __name__ == "__main__":
    sys.exit(main())
