"""The `jaxmap` command. Each subcommand imports its implementation lazily, so `jaxmap --help`
is instant and the mapping core never pulls open3d in unless a subcommand needs it."""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys


def _add_config_args(p: argparse.ArgumentParser, default_config: str | None = None) -> None:
    p.add_argument("config", nargs="?" if default_config is not None else None, default=default_config or None,
                   help="YAML config (see configs/)")
    p.add_argument("--data", help="sequence directory; overrides data.path")
    p.add_argument("--out", help="run directory; overrides output")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. --set train.iters=20 (repeatable)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxmap", description="Neural implicit 3D mapping in JAX.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("synth", help="write a synthetic sequence with exact ground truth")
    p.add_argument("scene", choices=["city", "room"])
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--small", action="store_true", help="small preset (tests, quick looks)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default per preset)")
    p.add_argument("--noise", type=float, default=0.0, help="range noise std in metres")
    p.add_argument("--pedestrians", action="store_true", help="city: add moving pedestrians (not in the GT)")

    p = sub.add_parser("eval", help="reconstruction metrics of a mesh against a sequence's ground truth")
    p.add_argument("mesh")
    p.add_argument("--gt", required=True, help="sequence directory with gt_points.ply and scans")
    p.add_argument("--threshold", type=float, default=0.1, help="F-score threshold in metres")
    p.add_argument("--cull", type=float, default=0.3, help="cull GT farther than this from every scan point (m)")
    p.add_argument("--radius", type=float, default=-1.0, help="keep GT within this range of a sensor position (m)")
    p.add_argument("--max-range", type=float, default=-1.0,
                   help="count as observed only scan points within this range of their sensor (the mapper's crop)")

    p = sub.add_parser("baseline", help="classical baselines on the same data")
    p.add_argument("method", choices=["tsdf"])
    p.add_argument("data")
    p.add_argument("--voxel", type=float, default=0.2, help="voxel size in metres")
    p.add_argument("--out", required=True, help="output mesh (.ply)")
    p.add_argument("--max-range", type=float, default=20.0, help="crop radius in metres")
    p.add_argument("--res", type=float, default=None, help="marching-cubes resolution (default = voxel)")

    p = sub.add_parser("map", help="N3 neural SDF mapping of a sequence")
    _add_config_args(p, default_config="")
    p.add_argument("--resume", metavar="RUN_DIR", help="continue an interrupted run")
    p.add_argument("--no-progress", action="store_true")

    p = sub.add_parser("mesh", help="re-extract a mesh from a saved map")
    p.add_argument("run", help="run directory")
    p.add_argument("--res", type=float, default=None, help="marching-cubes resolution in metres")
    p.add_argument("--out", default=None, help="output mesh (default RUN/mesh_<res>.ply)")

    p = sub.add_parser("demo", help="synthetic city -> neural map -> mesh -> metrics")
    p.add_argument("--data", default="data/city_demo")
    p.add_argument("--out", default="runs/demo")

    p = sub.add_parser("prior", help="train or evaluate the equivariant encoder/decoder prior")
    p.add_argument("action", choices=["train", "eval"])
    _add_config_args(p, default_config="configs/prior.yaml")

    p = sub.add_parser("imt", help="transformable latent map of a sequence: encode, fuse, mesh, metrics")
    _add_config_args(p, default_config="configs/room_imt.yaml")
    p.add_argument("--no-progress", action="store_true")

    p = sub.add_parser("slam", help="ICP odometry, loop closure, pose graph and a remapped neural map")
    _add_config_args(p, default_config="configs/room_slam.yaml")
    p.add_argument("--no-progress", action="store_true")

    p = sub.add_parser("bench", help="benchmarks: speed, memory and quality against baselines")
    p.add_argument("suite", choices=["n3", "imt", "slam"])
    p.add_argument("--data", default=None,
                   help="where the benchmark scene is, made if missing "
                        "(n3: data/city_bench, imt: data/room_bench, slam: data/room_noisy)")
    p.add_argument("--out", default=None, help="output directory (default runs/bench_SUITE)")
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--only", default=None, help="comma-separated subset of variants")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    return parser


def _enable_compilation_cache() -> None:
    """Keep XLA compilations on disk, so a second run skips the compiles that table growth triggers.
    JAXMAP_CACHE_DIR overrides the place; an empty value turns the cache off."""
    path = os.environ.get("JAXMAP_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "jaxmap", "xla"))
    if not path:
        return
    import jax

    try:
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    except Exception as e:  # an old jax without the option: run uncached rather than fail
        logging.getLogger("jaxmap").debug("no persistent compilation cache: %s", e)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Our messages at INFO; other libraries' (jax's backend probing, orbax) only from WARNING. Records
    # of the "jaxmap" logger pass its own level and then reach the root handler whatever the root level.
    logging.basicConfig(level=logging.WARNING, format="[%(name)s] %(message)s", stream=sys.stderr)
    ours = logging.getLogger("jaxmap")
    ours.setLevel(logging.DEBUG if args.verbose else logging.INFO)
    _enable_compilation_cache()
    from jaxmap.errors import JaxmapError

    try:
        return _dispatch(args)
    except JaxmapError as e:
        print(f"jaxmap {args.command}: error: {e}", file=sys.stderr)
        return 2


def _dispatch(args) -> int:
    if args.command == "synth":
        if args.scene == "city":
            from jaxmap.synth.city import generate_city as gen
        else:
            from jaxmap.synth.room import generate_room as gen
        kw = {"pedestrians": True} if args.pedestrians else {}
        if args.pedestrians and args.scene != "city":
            raise SystemExit("jaxmap synth: --pedestrians is for the city scene")
        stats = gen(args.out, seed=args.seed, small=args.small, n_frames=args.frames, noise_m=args.noise, **kw)
        print(json.dumps(stats))
        return 0
    if args.command == "eval":
        from jaxmap.metrics import evaluate_mesh_file

        m = evaluate_mesh_file(args.mesh, args.gt, threshold_m=args.threshold,
                               cull_distance_m=args.cull, eval_radius_m=args.radius, max_range_m=args.max_range)
        out = os.path.splitext(args.mesh)[0] + ".metrics.json"
        with open(out, "w") as f:
            json.dump(m, f)
        print(json.dumps(m))
        return 0
    if args.command == "baseline":
        from jaxmap.baselines.tsdf import tsdf_from_sequence

        info = tsdf_from_sequence(args.data, voxel_m=args.voxel, out_mesh=args.out,
                                  max_range_m=args.max_range, mesh_res_m=args.res)
        print(json.dumps(info))
        return 0
    if args.command in ("map", "mesh", "demo"):
        from jaxmap.n3 import run as n3run

        return getattr(n3run, f"cli_{args.command}")(args)
    if args.command == "prior":
        from jaxmap.imt import prior

        return prior.cli_train(args) if args.action == "train" else prior.cli_eval(args)
    if args.command == "slam":
        from jaxmap.slam import run as slam_run

        return slam_run.cli_slam(args)
    if args.command == "imt":
        from jaxmap.imt import run as imt_run

        return imt_run.cli_imt(args)
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
