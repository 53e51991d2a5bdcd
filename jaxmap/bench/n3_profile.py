"""`jaxmap bench n3 --only speed --profile`: where one frame's time goes, stage by stage.

The default city is mapped up to frame `--profile-at` (default 40: the decoder is frozen, the window
full), then the next `--profile-frames` frames are mapped under XLA's profiler:

* the frame program (device): every operation XLA ran, timed by the profiler, summed by the stage its
  code belongs to. The stages are the named scopes of the frame program (`jax.named_call` /
  `jax.named_scope` in `jaxmap.n3.integrate`, `train` and `frame`: screen, sample, allocate, pairs, store,
  carve, evidence/{image, candidates, test, observe, raise}, train/{batch, loss, adam}, preprocess), so
  the figures are those of the real, fused program the run compiles, not of parts compiled apart. Time
  in operations no scope names (XLA's own copies, the loop and branch control) is "other".
* what a feature costs inside the fused program: the frame program again without the evidence, the
  raise, the carving, the ray samples, each compiled and run on the same map and scan, in interleaved
  rounds (median and minimum: this machine's timings scatter by 10-20 % from run to run);
* host stages (what the prefetch thread does for a frame when the host preprocesses: reading it, the
  range image, the veil, crop and downsampling, normals, the move to the map frame and the upload),
  each timed on its own.

Per-operation events need XLA's `--xla_cpu_enable_xprof_traceme` flag, which is read when the backend
starts, so the profile runs in a child process (`python -m jaxmap.bench.n3_profile`). Printed as one
table (ms a frame, and the share of the frame program); written to OUT/profile.json.
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import glob
import json
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

# The frame program again without one feature (what it costs inside the fused program)
WITHOUT = {"evidence": dict(evidence=False), "raise": dict(raise_pairs=False), "carve": dict(carve=False),
           "rays": dict(n_ray=0, carve=False)}
SCOPES = ("preprocess", "screen", "sample", "allocate", "pairs", "store", "carve", "evidence", "train")
TRACE_FLAG = "--xla_cpu_enable_xprof_traceme=true"


def host_stage_ms(seq, i: int, cfg_pre, origin, bucket: int) -> tuple[dict, object]:
    """{stage: ms} of frame i's host preprocessing, each stage timed on its own, and its ScanBatch on the
    device (`jaxmap.n3.scan.preprocess` and `to_batch`, step by step)."""
    import jax

    from jaxmap import preprocess as pre
    from jaxmap import range_image
    from jaxmap.n3 import scan

    ms, t = {}, time.perf_counter()

    def lap(name):
        nonlocal t
        now = time.perf_counter()
        ms[name] = 1e3 * (now - t)
        t = now

    fr = seq.frame(i)
    lap("read")
    pts, pose = scan.check_frame(fr.points, fr.pose, i)
    lap("check")
    layout = pre.layout_of(cfg_pre)
    img = range_image.min_range_image(pts, layout) if layout is not None else None
    lap("range_image")
    raw = pre.drop_veil(pts, cfg_pre, img)
    lap("veil")
    p = pre.crop(raw, cfg_pre.min_range_m, cfg_pre.max_range_m, cfg_pre.min_z_m, cfg_pre.max_z_m)
    p = pre.voxel_downsample(p, cfg_pre.vox_down_m)
    if cfg_pre.outlier_mad > 0:  # (as `preprocess_points`)
        p = pre.remove_outliers(p, cfg_pre.normal_knn, cfg_pre.outlier_mad)
    p = p.astype(np.float32)
    lap("crop_downsample")
    nrm = pre.normals_of(p, cfg_pre, raw)
    lap("normals")
    batch = jax.block_until_ready(jax.device_put(scan.to_batch(p, nrm, pose, origin, bucket, img)))
    lap("to_map_upload")
    return ms, batch


_INSTR = re.compile(r'^\s*(?:ROOT )?%?([\w.\-]+) = .*?metadata=\{[^}]*op_name="([^"]*)"')


def scope_of_instructions(hlo_text: str) -> dict:
    """{instruction name: scope} of a compiled program's HLO text: the first of SCOPES in the operation's
    name stack (with the evidence's and training's second level: "evidence/test", "train/loss")."""
    out = {}
    for line in hlo_text.splitlines():
        m = _INSTR.match(line)
        if not m:
            continue
        parts = [p for p in m.group(2).split("/") if p]
        for j, p in enumerate(parts):
            name = p.split("(")[0]
            if name in SCOPES:
                sub = [q for q in parts[j + 1:] if q in ("image", "candidates", "test", "observe", "raise",
                                                         "batch", "loss", "adam")]
                out[m.group(1)] = f"{name}/{sub[0]}" if sub and name in ("evidence", "train") else name
                break
    return out


def exclusive_by_name(events) -> collections.Counter:
    """{name: ns} of one thread's events [(start ns, duration ns, name)], each exclusive of the events nested
    in it (a loop's or a branch's own time without its body's)."""
    total = collections.Counter()
    stack = []  # [end, name, time of its children, duration]

    def close():
        _, name, child, dur = stack.pop()
        total[name] += dur - child
        if stack:
            stack[-1][2] += dur

    for start, dur, name in sorted(events, key=lambda e: (e[0], -e[1])):
        while stack and stack[-1][0] <= start:
            close()
        stack.append([start + dur, name, 0, dur])
    while stack:
        close()
    return total


def exclusive_ms(pb_path: str) -> dict:
    """{operation: ms} of every XLA operation event in a profiler trace (xplane.pb), summed over the
    compute threads, each exclusive of the operations nested in it (`exclusive_by_name`)."""
    import jax

    pd = jax.profiler.ProfileData.from_file(pb_path)
    total = collections.Counter()
    for plane in pd.planes:
        for line in plane.lines:
            if "XLA" not in line.name:
                continue
            total.update(exclusive_by_name([(e.start_ns, e.duration_ns, e.name) for e in line.events
                                            if not e.name.startswith("ThunkExecutor")]))
    return {k: v / 1e6 for k, v in total.items()}


def traced_frames(mapper, seq, frames: range) -> tuple[dict, float]:
    """Map `frames` of seq under the profiler: ({scope: ms a frame}, wall ms a frame)."""
    import jax

    from jaxmap.n3 import frame as n3frame

    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        with jax.profiler.trace(d):
            for i in frames:
                fr = seq.frame(i)
                mapper.add_frame(fr.points, fr.pose)
        wall = 1e3 * (time.perf_counter() - t0) / len(frames)
        (pb,) = glob.glob(os.path.join(d, "**", "*.xplane.pb"), recursive=True)
        ops = exclusive_ms(pb)
    scope = {}
    for fn in n3frame.PROGRAMS.programs():
        scope.update(scope_of_instructions(fn.as_text()))
    by = collections.Counter()
    for name, ms in ops.items():
        by[scope.get(name, "other")] += ms / len(frames)
    return dict(by), wall


def feature_costs(mapper, seq, i: int, rounds: int) -> dict:
    """{variant: (median ms, min ms)} of the whole frame program of frame i on the map as it is, and of it
    without each feature (`WITHOUT`), run in interleaved rounds."""
    import jax
    import jax.numpy as jnp

    from jaxmap.n3.frame import step

    _, batch = host_stage_ms(seq, i, mapper.cfg.preprocess, mapper.origin, mapper.bucket)
    state, static = mapper.state, mapper.static
    variants = {"whole": static, **{f"without {k}": dataclasses.replace(static, **v) for k, v in WITHOUT.items()}}
    programs = {}
    for name, st in variants.items():
        programs[name] = jax.jit(lambda s, b, st=st: step(st, s, b), donate_argnums=0).lower(state, batch).compile()
    times = collections.defaultdict(list)
    for r in range(rounds + 1):
        for name, fn in programs.items():
            s = jax.block_until_ready(jax.tree_util.tree_map(jnp.copy, state))
            t0 = time.perf_counter()
            jax.block_until_ready(fn(s, batch))
            if r:  # (the first round warms up)
                times[name].append(1e3 * (time.perf_counter() - t0))
    return {k: (float(np.median(v)), float(np.min(v))) for k, v in times.items()}


def profile_city(cfg, at: int = 40, frames: int = 5, rounds: int = 5, progress: bool = True) -> dict:
    """The profile (module docstring) of `cfg`'s data after `at` frames."""
    from jaxmap.frame_loop import open_run_sequence
    from jaxmap.n3.mapper import N3Mapper

    seq = open_run_sequence(cfg)
    if len(seq) < at + frames + 1:
        raise SystemExit(f"[bench] --profile needs {at + frames + 1} frames; {cfg.data.path} has {len(seq)}")
    first = seq.frame(0)
    mapper = N3Mapper(cfg, first_scan=(first.points, first.pose))
    cfg = mapper.cfg  # (the layout read off the first scan)
    t0 = time.perf_counter()
    for i in range(at):
        fr = seq.frame(i)
        mapper.add_frame(fr.points, fr.pose)
        if progress and (i + 1) % 10 == 0:
            print(f"[bench] profile: mapped {i + 1} / {at} frames ({time.perf_counter() - t0:.0f} s)", flush=True)
    host = [host_stage_ms(seq, i, cfg.preprocess, mapper.origin, mapper.bucket)[0] for i in range(at, at + frames)]
    if progress:
        print(f"[bench] profile: frames {at}-{at + frames - 1} under the profiler", flush=True)
    device, wall = traced_frames(mapper, seq, range(at, at + frames))
    if progress:
        print(f"[bench] profile: the frame program without each feature, {rounds} rounds", flush=True)
    costs = feature_costs(mapper, seq, at + frames, rounds)
    return {"at": at, "frames": frames, "device_ms": device, "traced_wall_ms": wall,
            "host_ms": {k: float(np.median([h[k] for h in host])) for k in host[0]},
            "feature_costs_ms": costs}


def print_profile(prof: dict) -> None:
    dev = prof["device_ms"]
    total = sum(dev.values())
    order = sorted(dev, key=lambda k: (SCOPES.index(k.split("/")[0]) if k.split("/")[0] in SCOPES else 99, k))
    print(f"frames {prof['at']}-{prof['at'] + prof['frames'] - 1}: the frame program under XLA's profiler "
          "(ms a frame, operations summed by scope)")
    print(f"  {'stage':<26}{'ms':>9}{'share':>9}")
    for k in order:
        print(f"  {k:<26}{dev[k]:>9.1f}{100 * dev[k] / total:>8.1f}%")
    print(f"  {'frame program':<26}{total:>9.1f}      (wall a frame under the profiler {prof['traced_wall_ms']:.0f})")
    costs = prof["feature_costs_ms"]
    whole = costs["whole"][0]
    print(f"the frame program without one feature (frame {prof['at'] + prof['frames']}, interleaved rounds)")
    print(f"  {'program':<26}{'median':>9}{'min':>9}{'costs':>9}")
    for k, (med, lo) in costs.items():
        print(f"  {k:<26}{med:>9.1f}{lo:>9.1f}{'' if k == 'whole' else f'{whole - med:>9.1f}'}")
    host = prof["host_ms"]
    tot = sum(host.values())
    print("host preprocessing (the prefetch thread; ms a frame, medians)")
    for k, v in host.items():
        print(f"  {k:<26}{v:>9.1f}{100 * v / tot:>8.1f}%")
    print(f"  {'host total':<26}{tot:>9.1f}")


def main_profile(args, data: str, overrides: list[str]) -> dict:
    """Run the profile in a child process (the XLA flag it needs is read when the backend starts)."""
    os.makedirs(args.out, exist_ok=True)
    out = os.path.join(args.out, "profile.json")
    env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + TRACE_FLAG).strip())
    cmd = [sys.executable, "-m", "jaxmap.bench.n3_profile", "--data", data, "--json", out,
           "--at", str(args.profile_at), "--frames", str(args.profile_frames), "--rounds", str(args.profile_rounds)]
    cmd += [a for o in overrides for a in ("--set", o)]
    res = subprocess.run(cmd, env=env)
    if res.returncode != 0:
        raise SystemExit(f"[bench] the profile failed ({' '.join(cmd)})")
    with open(out) as f:
        prof = json.load(f)
    print()
    print_profile(prof)
    return prof


def _child(argv=None) -> int:
    from jaxmap.config import load_config
    from jaxmap.runs.n3 import city_config_path

    p = argparse.ArgumentParser()
    p.add_argument("--data", required=True)
    p.add_argument("--json", required=True)
    p.add_argument("--at", type=int, default=40)
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--set", dest="overrides", action="append", default=[])
    a = p.parse_args(argv)
    cfg = load_config(city_config_path(), [f"data.path={a.data}"] + a.overrides)
    prof = profile_city(cfg, at=a.at, frames=a.frames, rounds=a.rounds)
    with open(a.json, "w") as f:
        json.dump(prof, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(_child())
