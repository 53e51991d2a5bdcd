"""Every `jaxmap` command: one function per command, called by `jaxmap.cli.main` with the parsed
arguments; each returns the process's exit code.

Imports are made inside the commands on purpose: `jaxmap --help`, `jaxmap info` or `jaxmap synth` must
not pay for importing jax, flax and open3d (seconds) when they do not use them.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os

from jaxmap.config import ConfigError, config_from_args, lattice_problem, load_config, shipped_configs
from jaxmap.errors import CheckpointError, DataError, NoCheckpointError
from jaxmap.rundir import claim, exit_code, inspect, output_dir, output_file

log = logging.getLogger("jaxmap")


def synth(args) -> int:
    """`jaxmap synth {city,room} --out DIR`: a synthetic sequence with exact ground truth."""
    if args.scene == "city":
        from jaxmap.synth.city import generate_city as gen
    else:
        from jaxmap.synth.room import generate_room as gen
    kw = {"pedestrians": True} if args.pedestrians else {}
    if args.pedestrians and args.scene != "city":
        raise SystemExit("jaxmap synth: --pedestrians is for the city scene")
    if args.long:
        if args.scene != "city":
            raise SystemExit("jaxmap synth: --long is for the city scene")
        if args.small:
            raise SystemExit("jaxmap synth: --long and --small are different presets; pick one")
        kw["long"] = True
        if getattr(args, "length_km", None) is not None:
            kw["length_km"] = args.length_km
    if args.scene == "city":
        kw["layout"] = args.layout
        if args.beams is not None:
            from jaxmap.synth.beams import parse

            try:
                parse(args.beams)
            except ValueError as e:
                raise SystemExit(f"jaxmap synth: --beams: {e}") from None
            kw["beams"] = args.beams
        if args.traffic:
            kw["traffic"] = args.traffic
        if args.parking:
            kw["parking"] = True
        if args.realistic is not None:
            kw["realistic"] = args.realistic
        if args.lane_shift or args.start:
            if args.long or args.layout != "grid":
                raise SystemExit("jaxmap synth: --lane-shift and --start are for the grid loop (not --long, "
                                 "not --layout suburb)")
            kw.update(lane_shift_m=args.lane_shift, start_m=args.start)
    elif (args.layout != "grid" or args.beams is not None or args.traffic or args.parking
          or args.realistic is not None or args.lane_shift or args.start):
        raise SystemExit("jaxmap synth: --layout, --beams, --traffic, --parking, --realistic, --lane-shift and "
                         "--start are for the city scene")
    output_dir(args.out)
    try:
        stats = gen(args.out, seed=args.seed, small=args.small, n_frames=args.frames, noise_m=args.noise, **kw)
    except ValueError as e:  # (options that do not combine, a drive with no room for the parking cars)
        raise SystemExit(f"jaxmap synth: {e}") from None
    if args.frames is not None and not args.long:  # (a shorter drive is what users often expect of --frames)
        spacing = (stats.get("trajectory") or {}).get("frame_spacing_m")
        log.info("synth: --frames %d spreads the whole loop over %d frames%s; for part of the drive, map its "
                 "first frames instead: --set data.end_frame=N", args.frames, args.frames,
                 f" ({spacing:.2f} m apart)" if spacing else "")
    print(json.dumps(stats))
    return 0


def eval(args) -> int:  # noqa: A001 - the command's name
    """`jaxmap eval MESH|RUN [--gt DIR] [--frames A:B]`: the standard protocol's metrics of a mesh, a run's
    as the run scored it (`jaxmap.eval_run`; with the SA / DA of the points the run trained on, when the
    mesh's run directory has them for this data)."""
    from jaxmap.eval_run import evaluate
    from jaxmap.metrics import format_metrics
    from jaxmap.metrics.dynamic import scores_of_run

    if args.json_out:
        output_file(args.json_out, "--json-out")  # before the metrics are computed, not after
    m, mesh, data = evaluate(args)
    scores = scores_of_run(mesh, data)
    if scores:
        m["dynamic_points"] = scores
    print(format_metrics(m, "mesh"))
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(m, f)
    print(json.dumps(m))
    return 0


def baseline(args) -> int:
    """`jaxmap baseline tsdf --data DIR --out MESH`: the classical TSDF baseline."""
    from jaxmap.baselines.tsdf import tsdf_from_sequence

    output_file(args.out)
    info = tsdf_from_sequence(args.data, voxel_m=args.voxel, out_mesh=args.out,
                              max_range_m=args.max_range, mesh_res_m=args.res)
    print(json.dumps(info))
    return 0


def map(args) -> int:  # noqa: A001 - the command's name
    """`jaxmap map CONFIG [--data DIR] [--out RUN]` or `jaxmap map --resume RUN`: the N3 map of a sequence."""
    from jaxmap.runs.n3 import map_sequence
    from jaxmap.viewer import view_options

    if args.resume:
        if args.overrides or args.data or args.config or args.out:
            raise ConfigError(f"--resume {args.resume} continues a run with its own config.yaml; drop "
                              "CONFIG/--set/--data/--out (or start a new run with them)")
        out = args.resume
    else:
        if not args.config:
            raise ConfigError("jaxmap map needs a CONFIG: a YAML file or a shipped config's name (one of: "
                              f"{', '.join(shipped_configs())}), e.g. `jaxmap map city --data DIR`; or --resume RUN_DIR")
        cfg = config_from_args(args)  # validated before the run directory is touched
        out = cfg.output
    try:
        with claim(out, "map", resume=bool(args.resume), overwrite=args.overwrite):
            if args.resume:
                cfg_path = os.path.join(out, "config.yaml")
                if not os.path.isfile(cfg_path):
                    raise DataError(f"{cfg_path}: missing, so the run cannot be continued; start again with "
                                    "--overwrite")
                cfg = load_config(cfg_path)
            summary = map_sequence(cfg, out, resume=bool(args.resume), progress=not args.no_progress,
                                   mesh=not args.no_mesh, view=view_options(args))
    except KeyboardInterrupt as e:
        return exit_code(e)
    print(json.dumps(summary))
    return 0


def mesh(args) -> int:
    """`jaxmap mesh RUN [--res R] [--out PATH]`: a mesh of the newest intact checkpoint of a map run (or of
    an N3 SLAM run)."""
    from jaxmap.n3.submap_mapper import load_map
    from jaxmap.runs.n3 import no_usable_checkpoint

    run = args.run
    if not os.path.isdir(run):
        raise DataError(f"{run}: not a directory; pass the run directory of a jaxmap map run (--out of the run)")
    if args.res is not None and not args.res > 0:
        raise ConfigError(f"--res {args.res:g}: must be > 0 (metres), e.g. --res 0.1")
    state = inspect(run)
    n3_slam = state.command == "slam" and os.path.isfile(os.path.join(run, "n3_config.yaml"))  # map_kind n3
    if state.command not in (None, "map") and not n3_slam:
        raise DataError(f"{run}: holds a jaxmap {state.command} run; jaxmap mesh re-meshes jaxmap map runs and "
                        "jaxmap slam runs of map_kind n3")
    try:
        mapper = load_map(os.path.join(run, "checkpoint"))
    except NoCheckpointError:
        raise CheckpointError(f"{run}: no checkpoint yet; map at least `checkpoint_every` frames first "
                              f"(continue the run with: jaxmap {'slam' if n3_slam else 'map'} --resume {run})") from None
    except CheckpointError as e:
        raise no_usable_checkpoint(run, e) from None
    res = args.res or mapper.cfg.mesh.resolution_m
    problem = lattice_problem(res, mapper.cfg.grid.leaf_vox_size, "the run's grid.leaf_vox_size")
    if problem:
        raise ConfigError(f"--res {res:g} for {run}: {problem}")
    out = output_file(args.out or os.path.join(run, f"mesh_{res:g}.ply"), "--out")
    m = mapper.mesh(res)
    m.export(out)
    print(json.dumps({"mesh": out, "faces": int(len(m.faces)), "vertices": int(len(m.vertices))}))
    return 0


def demo(args) -> int:
    """`jaxmap demo`: synthesize the city (once), map it with the shipped config `city`, mesh, evaluate,
    say where it went."""
    from jaxmap.runs.n3 import map_sequence
    from jaxmap.synth.city import generate_city

    if not os.path.isfile(os.path.join(args.data, "poses.txt")):
        log.info("synthesizing the demo city into %s", args.data)
        generate_city(args.data, seed=0)
    cfg = load_config("city", [f"data.path={args.data}", f"output={args.out}"])
    with claim(args.out, "map", overwrite=True):  # `make demo` again replaces the last demo run
        summary = map_sequence(cfg, args.out)
    m = summary.get("metrics", {})
    print(f"\nmesh:    {summary['mesh']}")
    print(f"metrics: {os.path.join(args.out, 'metrics.json')}")
    print(f"timing:  {os.path.join(args.out, 'timing.json')}  ({summary.get('wall_s_per_frame', float('nan')):.2f} s "
          f"per frame wall-clock, compilation included; median {summary['median_total_s']:.2f} s)")
    if m:
        print(json.dumps(m))
    return 0


def imt(args) -> int:
    """`jaxmap imt CONFIG [--data DIR] [--out RUN]`: the transformable latent map of a sequence."""
    from jaxmap.config import ImtConfig
    from jaxmap.runs.imt import run_imt
    from jaxmap.viewer import view_options

    cfg = config_from_args(args, ImtConfig)
    with claim(cfg.output, "imt", overwrite=args.overwrite):  # one writer; an existing run needs --overwrite
        summary = run_imt(cfg, cfg.output, progress=cfg.progress and not args.no_progress, view=view_options(args))
    print(json.dumps(summary))
    return 0


def slam_config(args):
    """`jaxmap slam`'s config: `--set n3.<key>=<value>` goes to n3_set (the N3 map's config); a `--set` of a
    key the run would not read with its map kind is refused, naming the key (`SlamConfig.unused`)."""
    import argparse

    from jaxmap.config import ConfigError, SlamConfig
    from jaxmap.runs.slam_n3 import n3_map_config

    n3 = [o[3:] for o in args.overrides if o.startswith("n3.")]
    rest = [o for o in args.overrides if not o.startswith("n3.")]
    cfg = config_from_args(argparse.Namespace(**{**vars(args), "overrides": rest}), SlamConfig)
    unused = cfg.unused()
    for o in rest:
        key = o.split("=", 1)[0].strip()
        why = unused.get(key) or unused.get(key.split(".")[0])
        if why:
            raise ConfigError(f"--set '{o}': {why}")
    if n3 and not cfg.n3_config:
        raise ConfigError(f"--set 'n3.{n3[0]}': n3.<key> sets the N3 map's config, and this run has none (n3_config "
                          "is empty): set n3_config (e.g. --set n3_config=city)")
    cfg = dataclasses.replace(cfg, n3_set=[*cfg.n3_set, *n3])
    if cfg.n3_config:
        try:  # a ConfigError for a bad n3 key now, not after the front end started
            n3_map_config(cfg, cfg.output)
        except ConfigError as e:
            raise ConfigError(str(e).replace("--set '", "--set 'n3.")) from None
    return cfg


def slam(args) -> int:
    """`jaxmap slam CONFIG [--data DIR] [--out RUN]` or `jaxmap slam --resume RUN`: odometry, loop closure,
    pose graph, remapped map."""
    from jaxmap.config import SlamConfig
    from jaxmap.runs.slam import run_slam
    from jaxmap.viewer import view_options

    if args.resume:
        if args.overrides or args.data or args.out:
            raise ConfigError(f"--resume {args.resume} continues a run with its own config.yaml; drop "
                              "--set/--data/--out (or start a new run with them)")
        cfg_path = os.path.join(args.resume, "config.yaml")
        if not os.path.isfile(cfg_path):
            raise DataError(f"{cfg_path}: missing, so the run cannot be continued; start again with --overwrite")
        cfg = dataclasses.replace(load_config(cfg_path, schema=SlamConfig), output=args.resume)
    else:
        cfg = slam_config(args)
    try:  # one writer; an existing run needs --resume or --overwrite
        with claim(cfg.output, "slam", resume=bool(args.resume), overwrite=args.overwrite):
            out = run_slam(cfg, cfg.output, progress=cfg.progress and not args.no_progress, view=view_options(args),
                           resume=bool(args.resume), mesh=not getattr(args, "no_mesh", False))
    except KeyboardInterrupt as e:
        return exit_code(e)
    brief = {k: out[k] for k in ("run", "frames", "keyframes", "mesh") if k in out}
    brief["loops"] = len(out["loops"])
    for k in ("ate_odometry", "ate_slam"):
        if k in out:
            brief[k + "_rmse_m"] = out[k]["rmse_m"]
    if "axes_slam" in out:  # what the ATE hides: a trajectory a centimetre low maps the road that much low
        brief["height_error_mean_m"] = out["axes_slam"]["dz_mean_m"]
    if "metrics" in out:
        brief["chamfer_l1_cm"] = out["metrics"]["chamfer_l1_cm"]
        brief["f_score"] = out["metrics"]["f_score"]
    print(json.dumps(brief))
    return 0


def localize(args) -> int:
    """`jaxmap localize MAP --data SEQ [--init POSE] [--out RUN]`: localise a sequence in a saved N3 map."""
    from jaxmap.runs.localize import frame_ranges, localize_sequence, read_init, summary_table
    from jaxmap.slam.track import TrackOptions

    init = read_init(args.init) if args.init else None
    if not args.voxel > 0 or args.points < 16:
        raise ConfigError(f"--voxel {args.voxel:g} must be > 0 (metres) and --points {args.points} >= 16; "
                          "e.g. --voxel 0.2 --points 4096")
    opts = TrackOptions(max_points=args.points)
    with claim(args.out, "localize", overwrite=args.overwrite):
        m = localize_sequence(args.map, args.data, args.out, init=init, opts=opts, voxel_m=args.voxel,
                              progress=not args.no_progress)
    print(summary_table(m))
    brief = {k: m[k] for k in ("run", "frames", "localised", "localised_fraction")}
    if "position_error_cm" in m:
        brief["position_error_median_cm"] = m["position_error_cm"]["median"]
        brief["position_error_max_cm"] = m["position_error_cm"]["max"]
    if m["lost_frames"]:
        brief["lost_frames"] = frame_ranges(m["lost_frames"])
        if "localised_position_error_cm" in m:
            brief["localised_position_error_median_cm"] = m["localised_position_error_cm"]["median"]
    print(json.dumps(brief))
    return 0


def prior(args) -> int:
    """`jaxmap prior {train,eval} [config] [--out RUN] [--set k=v ...]`: train the equivariant encoder/decoder
    prior (its summary as one JSON line), or print the validation figures of the shipped weights (or of
    `RUN/prior.npz` with `--out RUN`)."""
    import dataclasses

    from jaxmap.config import PriorConfig
    from jaxmap.imt.prior import DEFAULT_CONFIG, WEIGHTS_FILE, load_prior, shipped_weights_path
    from jaxmap.imt.training import make_val_set, summary_of, train

    path = args.config or DEFAULT_CONFIG
    overrides = list(args.overrides) + ([f"output={args.out}"] if args.out and args.action == "train" else [])
    cfg = load_config(path, overrides, schema=PriorConfig)
    if args.action == "train":
        print(json.dumps(train(cfg, cfg.output)))
        return 0
    weights = os.path.join(args.out, WEIGHTS_FILE) if args.out else None
    model, meta = load_prior(weights, with_meta=True)
    cfg = dataclasses.replace(cfg, model=model.cfg)
    out = {"weights": weights or shipped_weights_path(), **summary_of(model, cfg, make_val_set(cfg), {}),
           "trained": {k: meta[k] for k in ("steps", "train_time_s", "total_time_s") if k in meta}}
    print(json.dumps(out))
    return 0


def configs(args) -> int:
    """`jaxmap configs [NAME]`: the shipped configs' names with the first line of each, or one of them
    printed (YAML, to copy and edit)."""
    from jaxmap.config import resolve_config, shipped_config_dir, shipped_config_path

    if args.name:
        with open(resolve_config(shipped_config_path(args.name) or args.name)) as f:
            print(f.read(), end="")
        return 0
    import dataclasses

    import yaml

    from jaxmap.config import ImtConfig, MapConfig, PriorConfig, SlamConfig

    names = shipped_configs()
    width = max(len(n) for n in names)
    for name in names:
        with open(shipped_config_path(name)) as f:
            text = f.read()
        first = text.split("\n", 1)[0].lstrip("# ").strip()
        keys = set(yaml.safe_load(text) or {})
        # the command is the first whose schema holds every top-level key (a slam config is an imt one and more)
        command = next((c for c, s in (("map", MapConfig), ("imt", ImtConfig), ("slam", SlamConfig),
                                       ("prior", PriorConfig)) if keys <= {f.name for f in dataclasses.fields(s)}), "?")
        first = first.removeprefix(f"jaxmap {command}").lstrip(": ")  # (the command is in its own column)
        print(f"{name:<{width}}  jaxmap {command:<6} {first if len(first) <= 80 else first[:77] + '...'}")
    print(f"\n(in {shipped_config_dir()}; every command takes a name in place of a YAML path, e.g. "
          "`jaxmap map city --data DIR`; `jaxmap configs NAME > my.yaml` to start your own)")
    return 0


def info(args) -> int:
    """`jaxmap info PATH`: what a sequence is (kind, frames, a bag's topics)."""
    from jaxmap.info import format_info, sequence_info

    print(format_info(sequence_info(args.path, kind=args.kind, topic=args.topic)))
    return 0


def view(args) -> int:
    """`jaxmap view RUN`: a finished run in the browser viewer."""
    from jaxmap.viewer import view_run

    return view_run(args.run, port=args.port, wait=not args.no_wait)


BENCH_DATA = {"slam": "data/room_noisy", "imt": "data/room_bench", "n3": "data/city_bench", "commands": "data/city_bench",
              "path": "data/city_bench"}


def bench(args) -> int:
    """`jaxmap bench {n3,imt,slam,commands,path}`: benchmarks (speed, memory, quality against baselines; commands:
    the whole-run cost of every command, `jaxmap.bench.commands`; path: a scan's way through `jaxmap map`)."""
    import importlib

    args.out = args.out or f"runs/bench_{args.suite}"
    args.data = args.data or BENCH_DATA[args.suite]
    return importlib.import_module(f"jaxmap.bench.{args.suite}").main(args)
