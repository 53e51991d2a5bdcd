"""`jaxmap bench n3 --only memory`: where the bytes are while jaxmap maps the default city.

Maps the first `FRAMES` frames (`JAXMAP_MEMORY_FRAMES`, default 30) in a fresh process with an empty
compile cache (so the compile is in the figures, as on a user's first run), then again with the cache
filled (warm), and prints, in MB:
  process     resident memory after the imports, while compiling the frame program (before the map is
              allocated, as `jaxmap map` does), after the allocation, after the first frame, the most between frames, and the peak before and after
              one checkpoint save (what `jaxmap map` writes every `checkpoint_every` frames)
  state       the device buffers of the map by field (feature table, Adam moments, hash tables, pair store)
  program     the compiled frame program's arguments, outputs (aliased to the donated arguments) and
              temporaries (XLA's own figures), and the raw scan it is handed
  capacities  each table's rows in use against its capacity

`python -m jaxmap.bench.n3_memory DATA FRAMES [--set k=v ...]` is the child; it prints one JSON line.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile


def _mb(n: float) -> float:
    return float(n) / 2**20


def state_by_field(state) -> dict:
    """MB of the map's buffers per top-level field of the state."""
    import jax

    out = {}
    for path, x in jax.tree_util.tree_leaves_with_path(state):
        name = jax.tree_util.keystr(path).lstrip(".").split(".")[0].split("[")[0]
        out[name] = out.get(name, 0.0) + _mb(x.size * x.dtype.itemsize)
    return out


def measure(data: str, frames: int, overrides: list[str]) -> dict:
    """The child: map `frames` frames of `data` and record where the memory is (MB)."""
    from jaxmap import hostmem

    hostmem.limit_arenas()  # as `jaxmap map` does
    import jax

    from jaxmap.config import load_config
    from jaxmap.frame_loop import Frame, Prefetcher, Progress, run_frames
    from jaxmap.io import open_sequence
    from jaxmap.n3 import core
    from jaxmap.n3.mapper import N3Mapper
    from jaxmap.runs.n3 import city_config_path

    jax.devices()  # the runtime up, as before the first frame
    out = {"rss_imports": hostmem.rss_mb()}

    cfg = load_config(city_config_path(), [f"data.path={data}"] + overrides)
    seq = open_sequence(data)
    first = seq.frame(0)
    m = N3Mapper(cfg, first_scan=(first.points, first.pose))   # as `jaxmap map`: compile, then allocate
    out["rss_peak_compile"] = hostmem.peak_rss_mb()
    out["rss_state"] = hostmem.rss_mb()
    out["state"] = state_by_field(m.state)
    rss = []

    def step(frame: Frame):
        info = m.add_frame(frame.points, frame.pose)
        rss.append(hostmem.rss_mb())
        return info, frame.pose

    n = min(frames, len(seq))
    run_frames(Prefetcher(seq, 0, n), step, total=n, progress=Progress(enabled=False))
    out["rss_after_first_frame"], out["rss_frames_max"] = rss[0], max(rss)
    info = m.timings[-1]
    out["rss_peak_frames"] = hostmem.peak_rss_mb()
    import tempfile

    with tempfile.TemporaryDirectory(prefix="jaxmap-memory-ckpt-") as d:
        m.save(d)                          # what `jaxmap map` does every checkpoint_every frames
    out["rss_peak"] = hostmem.peak_rss_mb()
    key, fn = core.PROGRAMS.newest()
    ma = fn.memory_analysis()
    out["program"] = {"arguments": _mb(ma.argument_size_in_bytes), "outputs": _mb(ma.output_size_in_bytes),
                      "aliased": _mb(ma.alias_size_in_bytes), "temporaries": _mb(ma.temp_size_in_bytes)}
    out["scan_rows"] = key[2]
    caps = core.Capacities.of(m.state)
    st = m.state.store
    out["capacities"] = {
        "voxel rows": (info["leaf_voxels"], caps.voxel_rows),
        "feature rows": (info["feature_rows"], caps.feature_rows),
        "store blocks": (int(jax.device_get(st.window_n)), caps.store_blocks),
        "store pairs": (info["store_pairs"], caps.store_blocks * caps.pairs_per_block),
    }
    out["frames"] = min(frames, len(seq))
    out["compiles"] = core.PROGRAMS.compiles()
    return out


def run(data: str, frames: int, overrides: list[str]) -> tuple[dict, dict]:
    """`measure` in a fresh process with an empty compile cache (cold), then again with the cache it
    filled (warm: no compile)."""
    from jaxmap.bench import in_subprocess

    out = []
    with tempfile.TemporaryDirectory(prefix="jaxmap-memory-") as cache:
        argv = [data, str(frames)] + [a for o in overrides for a in ("--set", o)]
        for _ in ("cold", "warm"):
            res, _seconds = in_subprocess(argv, cache, module="jaxmap.bench.n3_memory")
            if res.returncode != 0:
                raise SystemExit(f"[bench] {' '.join(res.args)} failed:\n{res.stderr[-3000:]}")
            out.append(json.loads(res.stdout.strip().splitlines()[-1]))
    return out[0], out[1]


def print_report(name: str, r: dict) -> None:
    print(f"memory of {name}: {r['frames']} frames, {r['compiles']} compile(s), scan bucket {r['scan_rows']} points")
    print(f"  process (RSS MB): imports {r['rss_imports']:.0f} | peak while compiling {r['rss_peak_compile']:.0f} | "
          f"map allocated {r['rss_state']:.0f} | after the first frame {r['rss_after_first_frame']:.0f} | "
          f"frames max {r['rss_frames_max']:.0f} | peak while mapping {r['rss_peak_frames']:.0f} | "
          f"peak with a checkpoint save {r['rss_peak']:.0f}")
    st = r["state"]
    print(f"  state (MB, {sum(st.values()):.0f} in all): " + ", ".join(
        f"{k} {v:.1f}" for k, v in sorted(st.items(), key=lambda kv: -kv[1]) if v >= 0.05))
    p = r["program"]
    print(f"  frame program (MB): arguments {p['arguments']:.0f}, outputs {p['outputs']:.0f} "
          f"(aliased to the donated state: {p['aliased']:.0f}), temporaries {p['temporaries']:.0f}")
    print("  capacities (in use / capacity): " + ", ".join(
        f"{k} {u:,} / {c:,} ({100 * u / max(c, 1):.0f} %)" for k, (u, c) in r["capacities"].items()))
    print(f"  => compiling takes {r['rss_peak_compile'] - r['rss_imports']:.0f} MB above the imports (before the map "
          f"is allocated); the map and the program's buffers {sum(st.values()) + p['temporaries']:.0f} MB; a "
          f"checkpoint save {r['rss_peak'] - r['rss_peak_frames']:+.0f} MB on the peak")


def main(args, data: str, base: list[str], variants: dict) -> int:
    frames = int(os.environ.get("JAXMAP_MEMORY_FRAMES", "30"))
    rows = {}
    for name in ("jaxmap", "device"):
        print(f"[bench] memory: {name}, {frames} frames of {data}, cold (empty compile cache) and warm", flush=True)
        cold, warm = run(data, frames, base + variants.get(name, []))
        rows[name] = {"cold": cold, "warm": warm}
        print_report(f"{name}, cold", cold)
        print_report(f"{name}, warm", warm)
        print()
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "memory.json"), "w") as f:
        json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    argv = sys.argv[1:]
    sets = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
    print(json.dumps(measure(argv[0], int(argv[1]), sets)))
