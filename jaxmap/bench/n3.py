"""`jaxmap bench n3`: what a user waits for, and what the map is worth, on the default city.

Speed (each run a separate `jaxmap map` process, so the compile cache and the peak RSS are its own):
  cold   an empty XLA compile cache: wall-clock of the mapping loop / frames, compilation included
  warm   the same run again, the cache filled by the cold run
For each: median and p95 per-frame time of the frame program (the device's), the worst frame after
the 10th against 2x the median, compile time and count, the time outside the frame programs and
compilation (ms a frame and % of the wall: what the host adds), peak RSS of the mapping (getrusage,
before meshing) and of the whole process.

Quality: jaxmap against the TSDF baseline and the N3 paper's ablations (Table III), one row each:
Acc / Comp / C-L1 / Comp. ratio / F-score at 10 cm within the 20 m the mapper sees.

`--only speed --profile`: where a frame's time goes, stage by stage (`jaxmap.bench.n3_profile`: the frame
program under XLA's profiler, summed by its named scopes; what each feature costs in it; the host's
preprocessing).

`--only memory`: where the bytes are (`jaxmap.bench.n3_memory`), for the host and the device preprocessing.

`--long`: the 1.1 km drive of `jaxmap synth city --long` (1025 frames): per-frame medians over
frames 100-200 and 900-1000, and the store's pairs and the feature rows every 100 frames (the
store must stay flat once the window is full; features grow only with the explored area).
`--long --length-km X`: an X km drive that loops back over streets already driven (`jaxmap synth city
--long --length-km X`, made in data/city_long_<X>km). Both print, every 500 frames and every 100, the
median and p95 frame time, the RSS at the range's end, the peak RSS so far, the device memory and the
submaps resident / on disk where the records carry them (`long_table`), the last 500 frames' median
frame time over frames 500-1000's (`late_ratio`; the target: within 10 %) and the mapping process's
peak RSS (getrusage of the children). `--set KEY=VALUE` goes to the mapping run.

Everything goes to OUT/bench.json (and OUT/long.json); each run directory is under OUT/.
"""
from __future__ import annotations

import json
import os
import shutil
import time

import numpy as np

from jaxmap.config.ablations import VARIANTS
from jaxmap.n3.mapper import store_flat_after_full

DEFAULT_VARIANTS = ("jaxmap", "flat_ring", "projective", "corrected", "replay", "keyframe", "no_hier")
COLS = ("accuracy_cm", "completion_cm", "chamfer_l1_cm", "completion_ratio", "f_score")


def map_in_subprocess(data: str, out: str, cache_dir: str, overrides: list[str], evaluate: bool = True) -> dict:
    """`jaxmap map configs/city.yaml` in a fresh process with its own compile cache; its summary."""
    from jaxmap.bench import command_summary
    from jaxmap.runs.n3 import city_config_path

    argv = ["map", city_config_path(), "--data", data, "--out", out, "--no-progress", "--overwrite"] + [
        a for o in overrides for a in ("--set", o)]
    if not evaluate:
        argv += ["--no-mesh"]
    summary = command_summary(argv, cache_dir)
    with open(os.path.join(out, "timing.json")) as f:
        summary["frames"] = json.load(f)["frames"]
    return summary


def speed_row(s: dict) -> dict:
    """One row of the speed table from a run's summary (with its per-frame records under "frames"):
    the per-frame times are the frame programs' (`program_s`: the device's time, as the wall-clock sees
    it), and "outside" is the rest of the wall-clock but compilation (`frame_loop.outside_programs`)."""
    frames = s["frames"]
    tot = np.array([r.get("program_s", r["total_s"]) for r in frames])
    med = float(np.median(tot[1:])) if len(tot) > 1 else float(tot[0])
    late = tot[10:] if len(tot) > 10 else tot[-1:]
    return {"wall_s": s["wall_s"], "s_per_frame": s["wall_s_per_frame"], "median_s": med,
            "p95_s": float(np.percentile(tot[1:], 95)) if len(tot) > 1 else med,
            "worst_after_10_over_median": float(late.max() / med), "frames_over_2x_median_after_10": int((late > 2 * med).sum()),
            "compile_s": s.get("compile_s", float("nan")), "compiles": s.get("compiles", -1),
            "outside_ms_per_frame": s.get("outside_ms_per_frame", float("nan")),
            "outside_pct": s.get("outside_pct", float("nan")), "final_save_s": s.get("final_save_s", float("nan")),
            "peak_rss_mapping_mb": s.get("peak_rss_mapping_mb", float("nan")), "peak_rss_mb": s.get("peak_rss_mb", float("nan")),
            "frames": len(frames)}


def _print_head(head: str) -> None:
    print(head)
    print("-" * len(head))


def print_speed(rows: dict) -> None:
    """The speed table; `outside ms` / `%`: the wall-clock outside the frame programs and compilation, in
    ms a frame and % of the wall (reading and waiting for scans, dispatching, stats, checkpoints)."""
    w = max([6] + [len(name) + 1 for name in rows])
    _print_head(f"{'run':<{w}}{'frames':>7}{'wall s':>8}{'s/frame':>8}{'median':>8}{'p95':>7}{'worst/med':>10}"
                f"{'>2x med':>8}{'compile s':>10}{'#':>3}{'outside ms':>11}{'%':>5}{'RSS map MB':>11}{'RSS all MB':>11}")
    for name, r in rows.items():
        print(f"{name:<{w}}{r['frames']:>7d}{r['wall_s']:>8.1f}{r['s_per_frame']:>8.3f}{r['median_s']:>8.3f}{r['p95_s']:>7.3f}"
              f"{r['worst_after_10_over_median']:>10.2f}{r['frames_over_2x_median_after_10']:>8d}{r['compile_s']:>10.1f}"
              f"{r['compiles']:>3d}{r['outside_ms_per_frame']:>11.1f}{r['outside_pct']:>5.1f}"
              f"{r['peak_rss_mapping_mb']:>11.0f}{r['peak_rss_mb']:>11.0f}")


def main(args) -> int:
    from jaxmap.bench import base_overrides, default_city

    if getattr(args, "long", False):
        return main_long(args)
    if getattr(args, "validation_suite", False):
        from jaxmap.bench.n3_suite import main_suite

        return main_suite(args, VARIANTS, map_in_subprocess)
    data, out = args.data, args.out
    os.makedirs(out, exist_ok=True)
    default_city(data)
    base = base_overrides(args, data)[1:]  # the data path goes on the command line
    names = _variant_names(args.only)
    if names == ["memory"]:
        from jaxmap.bench.n3_memory import main as main_memory

        return main_memory(args, data, base, VARIANTS)
    if getattr(args, "profile", False) and _profile(args, data, base, names):
        return 0
    results, speed = {}, {}

    if not args.only or "speed" in names or "jaxmap" in names:
        cache = os.path.join(out, "xla_cache")
        shutil.rmtree(cache, ignore_errors=True)
        for run in ("cold", "warm"):
            print(f"[bench] {run} run: jaxmap map on {data} (compile cache {cache})", flush=True)
            s = map_in_subprocess(data, os.path.join(out, f"jaxmap_{run}"), cache, base)
            speed[run] = speed_row(s)
            if run == "cold":
                results["jaxmap"] = _quality_row(s)
        print()
        print_speed(speed)
        print()
    if not args.only or "tsdf" in names:
        results["tsdf"] = _tsdf_row(data, out, base)
        _print_row("tsdf", results["tsdf"])
    for name in names:
        if name in ("tsdf", "speed", "jaxmap"):
            continue
        cache = os.path.join(out, "xla_cache")
        s = map_in_subprocess(data, os.path.join(out, name), cache, base + VARIANTS[name])
        results[name] = _quality_row(s)
        _print_row(name, results[name])
    with open(os.path.join(out, "bench.json"), "w") as f:
        json.dump({"speed": speed, "quality": results}, f, indent=1, default=float)
    print()
    print_table(results)
    print()
    print_signed_errors(results)
    if "tsdf" in results and "jaxmap" in results:
        a, b = results["jaxmap"]["metrics"], results["tsdf"]["metrics"]
        print(f"\nC-L1 jaxmap / TSDF = {a['chamfer_l1_cm'] / b['chamfer_l1_cm']:.3f}; "
              f"F-score jaxmap {a['f_score']:.2f} % vs TSDF {b['f_score']:.2f} %")
    return 0


def _profile(args, data: str, base: list[str], names: list[str]) -> bool:
    """`--profile`: the per-stage profile (`jaxmap.bench.n3_profile`); True when it is all that was asked
    (`--only speed --profile`)."""
    from jaxmap.bench.n3_profile import main_profile

    main_profile(args, data, base)
    return names == ["speed"]


def _variant_names(only: str | None) -> list[str]:
    """The variants `--only` names (default all), each checked."""
    names = list(DEFAULT_VARIANTS) if not only else [v.strip() for v in only.split(",")]
    for name in names:
        if name not in VARIANTS and name not in ("tsdf", "speed", "memory"):
            raise SystemExit(f"unknown variant {name!r}; choose from speed, memory, tsdf, {', '.join(VARIANTS)}")
    return names


def _quality_row(s: dict) -> dict:
    frames = s["frames"]
    pairs = [r["store_pairs"] for r in frames]
    flat, ratio = store_flat_after_full(pairs)
    return {"metrics": s.get("metrics", {}), "s_per_frame": s["wall_s_per_frame"],
            "median_total_s": s["median_total_s"], "store_flat": flat, "store_growth_ratio": ratio,
            "store_mb_max": max(r["store_bytes"] for r in frames) / 2**20, "max_store_pairs": max(pairs),
            "peak_rss_mb": s.get("peak_rss_mapping_mb", float("nan")),
            "frames_held": s.get("store_frames_held", float("nan"))}


def _tsdf_row(data: str, out: str, base: list[str]) -> dict:
    from jaxmap.baselines.tsdf import tsdf_from_sequence
    from jaxmap.config import load_config
    from jaxmap.finish import evaluate_run_mesh
    from jaxmap.runs.n3 import city_config_path

    cfg0 = load_config(city_config_path(), [f"data.path={data}"] + base)
    t0 = time.perf_counter()
    mesh_path = os.path.join(out, "tsdf.ply")
    info = tsdf_from_sequence(data, voxel_m=cfg0.grid.leaf_vox_size, out_mesh=mesh_path,
                              max_range_m=cfg0.preprocess.max_range_m, min_range_m=cfg0.preprocess.min_range_m,
                              mesh_res_m=cfg0.mesh.resolution_m, end_frame=cfg0.data.end_frame, progress=True)
    secs = time.perf_counter() - t0
    m = evaluate_run_mesh(mesh_path, cfg0)
    n = info.get("frames", 1) or 1
    return {"metrics": m, "s_per_frame": secs / n, "median_total_s": float("nan"), "store_flat": True,
            "store_mb_max": 0.0, "max_store_pairs": 0, "peak_rss_mb": float("nan")}


def _print_row(name, r):
    m = r.get("metrics", {})
    print(f"[bench] {name}: " + ", ".join(f"{k}={m.get(k, float('nan')):.2f}" for k in COLS)
          + f", {r['s_per_frame']:.3f} s/frame")


def floor_of(results: dict) -> dict:
    """The protocol floor (GT mesh as the prediction) that the runs' metrics carry, or {}."""
    for r in results.values():
        f = r.get("metrics", {}).get("floor")
        if f:
            return f
    return {}


def print_signed_errors(results: dict) -> None:
    """Mean signed surface error per GT class (cm; + = outside / above the true surface), one row per
    variant, the floor first."""
    rows = {"floor (GT)": floor_of(results).get("signed_error_cm", {})}
    rows.update({k: r.get("metrics", {}).get("signed_error_cm", {}) for k, r in results.items()})
    classes = [c for c in next((v for v in rows.values() if v), {})]
    if not classes:
        return
    w = max(11, *(len(name) + 1 for name in rows))  # (the variants' names fit 11; bench slam's maps' do not)
    _print_head(f"{'signed cm':<{w}}" + "".join(f"{c[:10]:>11}" for c in classes))
    for name, se in rows.items():
        print(f"{name:<{w}}" + "".join(f"{se.get(c, {}).get('mean_cm', np.nan):>11.2f}" for c in classes))


def print_table(results: dict) -> None:
    _print_head(f"{'variant':<11}{'Acc cm':>8}{'Comp cm':>8}{'C-L1 cm':>8}{'CR %':>7}{'F %':>7}"
                f"{'s/frame':>8}{'store MB':>9}{'flat':>6}{'RSS MB':>8}{'views':>7}")
    fl = floor_of(results)
    if fl:  # the protocol floor: the best any method can score here
        print(f"{'floor (GT)':<11}{fl['accuracy_cm']:>8.2f}{fl['completion_cm']:>8.2f}{fl['chamfer_l1_cm']:>8.2f}"
              f"{fl['completion_ratio']:>7.2f}{fl['f_score']:>7.2f}")
    for name, r in results.items():
        m = r.get("metrics", {})
        print(f"{name:<11}{m.get('accuracy_cm', np.nan):>8.2f}{m.get('completion_cm', np.nan):>8.2f}"
              f"{m.get('chamfer_l1_cm', np.nan):>8.2f}{m.get('completion_ratio', np.nan):>7.2f}"
              f"{m.get('f_score', np.nan):>7.2f}{r.get('s_per_frame', np.nan):>8.3f}{r.get('store_mb_max', 0.0):>9.1f}"
              f"{str(r.get('store_flat', '')):>6}{r.get('peak_rss_mb', np.nan):>8.0f}"
              f"{r.get('frames_held', np.nan) or np.nan:>7.2f}")
    print("views: for the window's voxels seen by >= 10 frames at the end, the median fraction of those frames "
          "whose pairs the voxel's block still holds")


LONG_EVERY = (500, 100)  # the long drive's tables: frames per row
LATE_TARGET = 1.10  # the last 500 frames' median frame time at most 10 % above frames 500-1000's


def _last_of(records, key):
    """The last value of `key` among the records that carry it, or None."""
    return next((r[key] for r in reversed(records) if r.get(key) is not None), None)


def long_table(records: list, every: int) -> list:
    """Rows of the long drive's table, one per `every` frames of per-frame records (timing.json "frames"):
    {"frames": [first, last] (indices into records), "median_s", "p95_s" (total_s), "rss_mb" (the range's
    last record), "peak_rss_mb" (the largest peak_rss_mb (else rss_mb) of the records so far), "device_mb",
    "submaps_resident", "submaps_on_disk" (the range's last record that carries them; None if none does)}."""
    rows, peak = [], float("-inf")
    for a in range(0, len(records), every):
        part = records[a:a + every]
        t = np.array([r["total_s"] for r in part], dtype=np.float64)
        for r in part:
            peak = max(peak, float(r.get("peak_rss_mb", r.get("rss_mb", float("nan")))))
        rows.append({"frames": [a, a + len(part) - 1], "median_s": float(np.median(t)),
                     "p95_s": float(np.percentile(t, 95)), "rss_mb": part[-1].get("rss_mb"), "peak_rss_mb": peak,
                     "device_mb": _last_of(part, "device_mb"), "submaps_resident": _last_of(part, "submaps_resident"),
                     "submaps_on_disk": _last_of(part, "submaps_on_disk")})
    return rows


def late_ratio(records: list, window: int = 500) -> dict | None:
    """The last `window` frames' median total_s over frames window-2*window's (500-1000): {"late": [first,
    last], "median_late_s", "median_500_1000_s", "ratio", "within_10pct" (ratio <= LATE_TARGET)}; None with
    fewer than 2 * window frames."""
    n = len(records)
    if n < 2 * window:
        return None
    ref = float(np.median([r["total_s"] for r in records[window:2 * window]]))
    late = float(np.median([r["total_s"] for r in records[n - window:]]))
    ratio = late / ref
    return {"late": [n - window, n - 1], "median_late_s": late, "median_500_1000_s": ref, "ratio": ratio,
            "within_10pct": bool(ratio <= LATE_TARGET)}


def print_long_table(rows: list, title: str) -> None:
    """A long_table: n/a where no record carries the device memory, - where none carries the submaps."""
    def num(v, fmt, none):
        return none if v is None else format(v, fmt)

    print(title)
    _print_head(f"{'frames':>11}{'median s':>9}{'p95 s':>8}{'RSS MB':>8}{'peak MB':>8}{'device MB':>10}"
                f"{'submaps res':>12}{'on disk':>8}")
    for r in rows:
        a, b = r["frames"]
        print(f"{a:>5d}-{b:<5d}{r['median_s']:>9.3f}{r['p95_s']:>8.3f}{num(r['rss_mb'], '.0f', 'n/a'):>8}"
              f"{r['peak_rss_mb']:>8.0f}{num(r['device_mb'], '.0f', 'n/a'):>10}"
              f"{num(r['submaps_resident'], 'd', '-'):>12}{num(r['submaps_on_disk'], 'd', '-'):>8}")


def long_data_dir(args) -> str:
    """Where the long drive is: --data, else data/city_long (with --length-km X: data/city_long_<X>km)."""
    if args.data != "data/city_bench":
        return args.data
    km = getattr(args, "length_km", None)
    return "data/city_long" if km is None else f"data/city_long_{km:g}km"


def _children_peak_rss_mb() -> float:
    """The largest peak RSS of this process's finished children (getrusage; MB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


def _print_sizes(frames: list, tot: np.ndarray) -> None:
    """Per 100 frames: median frame time, the block's last frame's store and map sizes, its largest RSS."""
    n = len(frames)
    print(f"\n{'frames':>10}{'median s':>9}{'store pairs':>12}{'store MB':>9}{'window vox':>11}{'leaf voxels':>12}"
          f"{'feature rows':>13}{'capacity':>9}{'RSS MB':>8}{'peak MB':>8}")
    for a in range(0, n, 100):
        r, b = frames[min(a + 99, n - 1)], min(a + 100, n)  # the block's last frame; RSS: the block's largest
        print(f"{a:>4d}-{b - 1:<5d}{float(np.median(tot[a:b])):>9.3f}{r['store_pairs']:>12d}{r['store_bytes'] / 2**20:>9.1f}"
              f"{r['window_voxels']:>11d}{r['leaf_voxels']:>12d}{r['feature_rows']:>13d}{r['feature_capacity']:>9d}"
              f"{max(f['rss_mb'] for f in frames[a:b]):>8.0f}{r['peak_rss_mb']:>8.0f}")


def _long_data(args, km: float | None) -> str:
    """The long drive's directory (`long_data_dir`), synthesized when missing; SystemExit when it holds a
    drive of another length than --length-km."""
    from jaxmap.synth.city import generate_city

    data = long_data_dir(args)
    if not os.path.isfile(os.path.join(data, "poses.txt")):
        what = "the long drive" if km is None else f"the {km:g} km long drive"
        print(f"[bench] synthesizing {what} into {data}")
        generate_city(data, seed=0, long=True, length_km=km)
    elif km is not None and os.path.isfile(os.path.join(data, "meta.json")):
        with open(os.path.join(data, "meta.json")) as f:
            have = (json.load(f).get("trajectory") or {}).get("length_km")
        if have != km:
            raise SystemExit(f"[bench] {data} holds a drive of {'the serpentine' if have is None else f'{have:g} km'}, "
                             f"not {km:g} km; give another --data (or delete it to synthesize it again)")
    return data


def main_long(args) -> int:
    """The long drive: flat per-frame cost and a store bounded by the window."""
    from jaxmap.bench import base_overrides

    km = getattr(args, "length_km", None)
    data = _long_data(args, km)
    out = args.out
    os.makedirs(out, exist_ok=True)
    base = base_overrides(args, data)[1:] + ["checkpoint_every=100000"]
    cache = os.path.join(out, "xla_cache")
    print(f"[bench] long drive: jaxmap map on {data}" + (f" (--set {' --set '.join(args.overrides)})"
                                                         if args.overrides else ""), flush=True)
    s = map_in_subprocess(data, os.path.join(out, "long"), cache, base, evaluate=False)
    child_peak = _children_peak_rss_mb()  # (the mapping process: this process's only child)
    frames = s["frames"]
    tot = np.array([r["total_s"] for r in frames])
    n = len(tot)
    a = tot[100:200] if n >= 200 else tot[n // 10: n // 5]
    b = tot[900:1000] if n >= 1000 else tot[-max(n // 10, 1):]
    ma, mb = float(np.median(a)), float(np.median(b))
    print(f"\nframes {n}, wall {s['wall_s']:.0f} s = {s['wall_s_per_frame']:.3f} s/frame (compilation included: "
          f"{s.get('compile_s', float('nan')):.1f} s in {s.get('compiles', -1)} compiles), peak RSS "
          f"{s.get('peak_rss_mapping_mb', float('nan')):.0f} MB")
    print(f"median s/frame, frames 100-200: {ma:.3f}; frames 900-1000: {mb:.3f}; ratio {mb / ma:.3f}")
    _print_sizes(frames, tot)
    pairs = [r["store_pairs"] for r in frames]
    flat, ratio = store_flat_after_full(pairs)
    print(f"store flat once the window is full: {flat} (last half / first half max = {ratio:.2f})")
    tables = {f"every_{k}": long_table(frames, k) for k in LONG_EVERY}
    for k in LONG_EVERY:
        print()
        print_long_table(tables[f"every_{k}"], f"every {k} frames:")
    late = late_ratio(frames)
    print()
    if late is None:
        print(f"median s/frame, last 500 frames over frames 500-1000: n/a ({n} frames, fewer than 1000)")
    else:
        print(f"median s/frame, frames {late['late'][0]}-{late['late'][1]}: {late['median_late_s']:.3f}; frames "
              f"500-999: {late['median_500_1000_s']:.3f}; ratio {late['ratio']:.3f} (target <= {LATE_TARGET:.2f}: "
              f"{'met' if late['within_10pct'] else 'NOT met'})")
    print(f"peak RSS of the mapping process (getrusage of the children): {child_peak:.0f} MB")
    with open(os.path.join(out, "long.json"), "w") as f:
        json.dump({"median_100_200": ma, "median_900_1000": mb, "ratio": mb / ma, "wall_s": s["wall_s"],
                   "s_per_frame": s["wall_s_per_frame"], "compile_s": s.get("compile_s"),
                   "peak_rss_mapping_mb": s.get("peak_rss_mapping_mb"), "store_flat": flat,
                   "data": data, "length_km": km, "overrides": list(args.overrides), "tables": tables,
                   "late_ratio": late, "process_peak_rss_mb": child_peak,
                   "frames": [{k: r[k] for k in ("frame", "total_s", "store_pairs", "leaf_voxels", "feature_rows",
                                                 "feature_capacity", "rss_mb", "peak_rss_mb", "device_mb",
                                                 "submaps_resident", "submaps_on_disk") if k in r}
                              for r in frames]}, f, indent=1)
    return 0
