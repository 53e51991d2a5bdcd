"""`jaxmap bench n3`: jaxmap N3 against the TSDF baseline and the N3 paper's ablations, one table.

For each variant: median per-frame time after the first (compiling) frames, split into
preprocess / sampling / training; peak RSS of the process; the training-pair store size (max, and
whether it stopped growing once the window was full); and Acc / Comp / C-L1 / Comp.ratio / F-score
at 10 cm, evaluated within the 20 m the mapper sees. Everything is written to OUT/bench.json and
each variant's run directory under OUT/.
"""
from __future__ import annotations

import json
import os
import resource
import time

import numpy as np

VARIANTS = {
    "jaxmap": [],
    "projective": ["sampling.label_mode=projective"],
    "corrected": ["sampling.label_mode=corrected"],
    "replay": ["window.mode=replay"],
    "keyframe": ["window.mode=keyframe"],
    "no_hier": ["train.hierarchical=false"],
}
COLS = ("accuracy_cm", "completion_cm", "chamfer_l1_cm", "completion_ratio", "f_score")


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def store_flat_after_full(store_pairs: list[int], tail: float = 0.5) -> tuple[bool, float]:
    """Did the store stop growing? Compares the max of the last `tail` fraction of frames with the
    max of the frames before it: growth ratio <= 1.25 counts as flat (the window is full)."""
    n = len(store_pairs)
    if n < 4:
        return True, 1.0
    cut = int(n * (1 - tail))
    ratio = max(store_pairs[cut:]) / max(max(store_pairs[:cut]), 1)
    return ratio <= 1.25, float(ratio)


def main(args) -> int:
    from jaxmap.baselines.tsdf import tsdf_from_sequence
    from jaxmap.bench import base_overrides
    from jaxmap.config import load_config
    from jaxmap.metrics import evaluate_mesh_file
    from jaxmap.n3.run import _frame_selection, city_config_path, map_sequence
    from jaxmap.synth.city import generate_city

    data, out = args.data, args.out
    os.makedirs(out, exist_ok=True)
    if not os.path.isfile(os.path.join(data, "poses.txt")):
        print(f"[bench] synthesizing the default city into {data}")
        generate_city(data, seed=0)
    base = base_overrides(args, data)
    names = list(VARIANTS) if not args.only else [v.strip() for v in args.only.split(",")]
    cfg0 = load_config(city_config_path(), base)
    results = {}

    if not args.only or "tsdf" in names:
        t0 = time.perf_counter()
        mesh_path = os.path.join(out, "tsdf.ply")
        info = tsdf_from_sequence(data, voxel_m=cfg0.grid.leaf_vox_size, out_mesh=mesh_path,
                                  max_range_m=cfg0.preprocess.max_range_m, min_range_m=cfg0.preprocess.min_range_m,
                                  mesh_res_m=cfg0.mesh.resolution_m, end_frame=cfg0.data.end_frame, progress=True)
        secs = time.perf_counter() - t0
        m = evaluate_mesh_file(mesh_path, data, threshold_m=cfg0.eval.threshold_m,
                               cull_distance_m=cfg0.eval.cull_distance_m, eval_radius_m=cfg0.eval.eval_radius_m,
                               n_samples=cfg0.eval.n_samples, **_frame_selection(cfg0))
        n_frames = info.get("frames", 1) or 1
        results["tsdf"] = {"metrics": m, "median_total_s": secs / n_frames, "median_preprocess_s": float("nan"),
                           "median_sampling_s": float("nan"), "median_training_s": float("nan"),
                           "max_store_pairs": 0, "store_flat": True, "peak_rss_mb": _peak_rss_mb()}
        _print_row("tsdf", results["tsdf"])
    for name in names:
        if name == "tsdf":
            continue
        if name not in VARIANTS:
            raise SystemExit(f"unknown variant {name!r}; choose from tsdf, {', '.join(VARIANTS)}")
        cfg = load_config(city_config_path(), base + VARIANTS[name] + [f"output={os.path.join(out, name)}"])
        summary = map_sequence(cfg, cfg.output, progress=True)
        with open(os.path.join(cfg.output, "timing.json")) as f:
            frames = json.load(f)["frames"]
        pairs = [r["store_pairs"] for r in frames]
        flat, ratio = store_flat_after_full(pairs)
        results[name] = {**summary, "store_flat": flat, "store_growth_ratio": ratio,
                         "store_mb_max": max(r["store_bytes"] for r in frames) / 2**20,
                         "peak_rss_mb": _peak_rss_mb()}
        _print_row(name, results[name])
    with open(os.path.join(out, "bench.json"), "w") as f:
        json.dump(results, f, indent=1, default=float)
    print()
    print_table(results)
    if "tsdf" in results and "jaxmap" in results:
        a, b = results["jaxmap"]["metrics"], results["tsdf"]["metrics"]
        print(f"\nC-L1 jaxmap / TSDF = {a['chamfer_l1_cm'] / b['chamfer_l1_cm']:.3f} "
              f"({100 * (1 - a['chamfer_l1_cm'] / b['chamfer_l1_cm']):.1f} % lower); "
              f"F-score jaxmap {a['f_score']:.2f} % vs TSDF {b['f_score']:.2f} %")
    return 0


def _print_row(name, r):
    m = r.get("metrics", {})
    print(f"[bench] {name}: " + ", ".join(f"{k}={m.get(k, float('nan')):.2f}" for k in COLS)
          + f", {r['median_total_s']:.3f} s/frame")


def print_table(results: dict) -> None:
    head = (f"{'variant':<11}{'Acc cm':>8}{'Comp cm':>8}{'C-L1 cm':>8}{'CR %':>7}{'F %':>7}"
            f"{'prep s':>8}{'samp s':>8}{'train s':>8}{'total s':>8}{'store MB':>9}{'flat':>6}{'RSS MB':>8}")
    print(head)
    print("-" * len(head))
    for name, r in results.items():
        m = r.get("metrics", {})
        print(f"{name:<11}{m.get('accuracy_cm', np.nan):>8.2f}{m.get('completion_cm', np.nan):>8.2f}"
              f"{m.get('chamfer_l1_cm', np.nan):>8.2f}{m.get('completion_ratio', np.nan):>7.2f}"
              f"{m.get('f_score', np.nan):>7.2f}{r.get('median_preprocess_s', np.nan):>8.3f}"
              f"{r.get('median_sampling_s', np.nan):>8.3f}{r.get('median_training_s', np.nan):>8.3f}"
              f"{r.get('median_total_s', np.nan):>8.3f}{r.get('store_mb_max', 0.0):>9.1f}"
              f"{str(r.get('store_flat', '')):>6}{r.get('peak_rss_mb', np.nan):>8.0f}")
