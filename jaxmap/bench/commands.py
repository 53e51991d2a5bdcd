"""`jaxmap bench commands`: what a user waits for, every command: the whole-run cost of `jaxmap map` (cold
and warm, host and device preprocessing), `jaxmap imt` and `jaxmap slam`, in one run and one file (on any
backend; issue 31 ran it on a GPU).

    jaxmap bench commands [--out runs/bench_commands] [--data data/city_bench] [--quick] [--only n3,imt,slam]

  1. the machine: jax version, backend and devices, CPU cores, the load average;
  2. the N3 speed table on the default city (`jaxmap synth city`, 130 frames, made once under --data):
     host and device preprocessing (`preprocess.device=false` / `true`), each cold (an empty compile
     cache) and warm (the cache the cold run filled), each run its own `jaxmap map --no-mesh` process
     (`jaxmap.bench.n3.map_in_subprocess`): wall s/frame, the frame program's median and p95, compile
     seconds, the time outside the frame programs (ms a frame, % of the wall), peak RSS;
  3. `jaxmap imt configs/room_imt.yaml` on the synthetic room (`jaxmap synth room`, made once beside the
     city): wall s/frame, the preprocessing and the encode program's medians;
  4. `jaxmap slam configs/city_slam.yaml` on the city: wall s/frame, its steps' medians.
Each part is written as soon as it is done to OUT/commands.json (and the tables to OUT/commands.txt), so a
run cut short keeps what it measured. --quick: the small city and room, a few frames each (a check, on a
CPU, that the whole script runs).
"""
from __future__ import annotations

import json
import os
import platform
import shutil
import time

QUICK_FRAMES = 6
EVAL_SAMPLES = ["--set", "eval.n_samples=1000000"]  # slam's and imt's metrics: their time is not what is measured


def machine() -> dict:
    import jax

    return {"jax": jax.__version__, "backend": jax.default_backend(),
            "devices": [d.device_kind for d in jax.devices()], "cpu_cores": os.cpu_count(),
            "python": platform.python_version(), "load_average": list(os.getloadavg())}


def n3_speed(city: str, out: str, quick: bool) -> dict:
    """Cold and warm `jaxmap map` of the city with host and with device preprocessing."""
    from jaxmap.bench.n3 import map_in_subprocess, speed_row

    frames = [f"data.end_frame={QUICK_FRAMES}"] if quick else []
    rows = {}
    for where, device in (("host", "false"), ("device", "true")):
        cache = os.path.join(out, f"xla_cache_{where}")
        shutil.rmtree(cache, ignore_errors=True)
        for run in ("cold", "warm"):
            name = f"{where} {run}"
            try:
                s = map_in_subprocess(city, os.path.join(out, f"map_{where}_{run}"), cache,
                                      frames + [f"preprocess.device={device}"], evaluate=False)
            except SystemExit as e:  # the run failed: say so in the file, go on with the others
                rows[name] = {"failed": str(e)[-3000:]}
                print(f"[bench commands] {name}: FAILED\n{e}", flush=True)
                continue
            rows[name] = {**speed_row(s), "process_s": s["process_s"]}
            print(f"[bench commands] {name}: {rows[name]['s_per_frame']:.3f} s/frame", flush=True)
    return rows


def command_run(args: list[str], out: str, cache: str) -> dict:
    """`jaxmap ARGS --out OUT` in its own process with the compile cache `cache`; its timing.json summary
    (with a SLAM run's steps, frames and keyframes from its slam.json), and the process's seconds."""
    from jaxmap.bench import in_subprocess

    res, seconds = in_subprocess([*args, "--out", out, "--overwrite", "--no-progress"], cache)
    if res.returncode != 0:
        return {"failed": " ".join(res.args), "stderr": res.stderr[-3000:]}
    with open(os.path.join(out, "timing.json")) as f:
        summary = json.load(f)["summary"]
    slam = os.path.join(out, "slam.json")  # a SLAM run's summary
    if os.path.isfile(slam):
        with open(slam) as f:
            summary.update({k: v for k, v in json.load(f).items() if k in ("step", "frames", "keyframes")})
    return {**summary, "process_s": seconds}


def command_speed(command: str, config: str, data: str, out: str, cache: str, sets: list[str],
                  keys: tuple) -> dict:
    """`jaxmap COMMAND <shipped config> --data DATA SETS` (`command_run`, into OUT/COMMAND): `keys` of its
    summary, and "failed" / "stderr" when it failed."""
    from jaxmap.config import shipped_config_path

    r = command_run([command, shipped_config_path(config), "--data", data, *sets], os.path.join(out, command), cache)
    return {k: r[k] for k in (*keys, "process_s", "failed", "stderr") if k in r}


def slam_speed(city: str, out: str, quick: bool) -> dict:
    sets = ["--set", "n3." + EVAL_SAMPLES[1]] + (["--set", f"data.end_frame={QUICK_FRAMES}"] if quick else [])
    return command_speed("slam", "city_slam.yaml", city, out, os.path.join(out, "xla_cache_host"), sets,
                         ("wall_s", "wall_s_per_frame", "frames_run", "compile_s", "step"))


def imt_speed(room: str, out: str, quick: bool) -> dict:
    sets = EVAL_SAMPLES + (["--set", f"data.end_frame={2 * QUICK_FRAMES}"] if quick else [])
    return command_speed("imt", "room_imt.yaml", room, out, os.path.join(out, "xla_cache_imt"), sets,
                         ("wall_s", "wall_s_per_frame", "frames_run", "median_preprocess_s", "median_encode_s",
                          "median_fuse_s"))


def tables(res: dict) -> str:
    """The results as text: the machine, the N3 speed table, SLAM's and IMT's lines."""
    import contextlib
    import io

    from jaxmap.bench.n3 import print_speed

    m = res["machine"]
    lines = [f"jax {m['jax']}, backend {m['backend']}, {', '.join(m['devices'])}, {m['cpu_cores']} CPU cores, "
             f"load {m['load_average'][0]:.1f}"]
    if "n3" in res:
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            print_speed({k: r for k, r in res["n3"].items() if "failed" not in r})
        lines += ["", "N3 (jaxmap map --no-mesh on the city; median / p95: the frame program)", buf.getvalue().rstrip()]
        for k, r in res["n3"].items():
            if "failed" in r:
                lines.append(f"{k}: FAILED: {r['failed']}")
                continue
            steady = (r["wall_s"] - r["compile_s"]) / r["frames"]
            lines.append(f"{k}: wall {r['s_per_frame']:.3f} s/frame = {r['s_per_frame'] / r['median_s']:.2f}x the "
                         f"frame program's median {r['median_s']:.4f} s; without compiling {steady:.3f} s/frame "
                         f"({steady / r['median_s']:.2f}x)")
    for name in ("imt", "slam"):
        r = res.get(name)
        if not r:
            continue
        if "failed" in r:
            lines += ["", f"{name}: FAILED: {r['failed']}", r.get("stderr", "")]
            continue
        parts = {k: v for k, v in (r.get("step") or r).items() if k.startswith("median_") and k.endswith("_s")}
        compiling = f", of which compiling the N3 frame program {r['compile_s']:.1f} s" if "compile_s" in r else ""
        lines += ["", f"{name}: {r['wall_s_per_frame']:.3f} s/frame wall over {r.get('frames_run', '?')} frames "
                      f"({r['wall_s']:.1f} s{compiling}; process {r['process_s']:.1f} s); "
                  + ", ".join(f"{k} {v:.3f}" for k, v in parts.items())]
    return "\n".join(lines) + "\n"


def main(args) -> int:
    from jaxmap.synth.city import generate_city
    from jaxmap.synth.room import generate_room

    out, quick = args.out, bool(getattr(args, "quick", False))
    os.makedirs(out, exist_ok=True)
    city = args.data + ("_small" if quick else "")
    room = os.path.join(os.path.dirname(os.path.abspath(city)), "room_bench" + ("_small" if quick else ""))
    res: dict = {"machine": machine(), "quick": quick, "city": city, "room": room}
    only = set((args.only or "n3,slam,imt").split(","))
    t0 = time.perf_counter()

    def save():
        res["elapsed_s"] = time.perf_counter() - t0
        with open(os.path.join(out, "commands.json"), "w") as f:
            json.dump(res, f, indent=1, default=float)
        with open(os.path.join(out, "commands.txt"), "w") as f:
            f.write(tables(res))

    for path, make in ((city, lambda: generate_city(city, seed=0, small=quick)),
                       (room, lambda: generate_room(room, seed=0, small=quick))):
        if not os.path.isfile(os.path.join(path, "poses.txt")):
            t = time.perf_counter()
            print(f"[bench commands] synthesizing {path}", flush=True)
            make()
            res.setdefault("synth_s", {})[path] = time.perf_counter() - t
    save()
    for name, run in (("n3", lambda: n3_speed(city, out, quick)), ("imt", lambda: imt_speed(room, out, quick)),
                      ("slam", lambda: slam_speed(city, out, quick))):
        if name in only:
            print(f"[bench commands] {name} ({time.perf_counter() - t0:.0f} s in)", flush=True)
            res[name] = run()
            save()
    print()
    print(tables(res))
    print(f"[bench commands] written to {os.path.join(out, 'commands.json')} and commands.txt ({time.perf_counter() - t0:.0f} s)")
    return 0
