"""`jaxmap bench`: n3, imt, slam and commands suites (one module each) and what they share."""
from __future__ import annotations

import os
import subprocess
import sys
import time


def in_subprocess(argv: list[str], cache_dir: str, module: str = "jaxmap.cli") -> tuple[subprocess.CompletedProcess, float]:
    """`python -m MODULE ARGV` in a fresh process whose persistent compile cache is `cache_dir` (its own:
    cold when empty, warm once a run filled it), its output captured; (the finished process, its seconds)."""
    env = dict(os.environ, JAXMAP_CACHE_DIR=cache_dir)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # set by this process's `import jaxmap`
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", module, *argv], env=env, capture_output=True, text=True)
    return res, time.perf_counter() - t0


def command_summary(argv: list[str], cache_dir: str) -> dict:
    """A jaxmap command (`in_subprocess`); its summary, the last line it prints, with `process_s` its
    seconds. A failed command stops the bench with its stderr's end."""
    import json

    res, seconds = in_subprocess(argv, cache_dir)
    if res.returncode != 0:
        raise SystemExit(f"[bench] {' '.join(res.args)} failed:\n{res.stderr[-3000:]}")
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    summary["process_s"] = seconds
    return summary


def synthesized(root: str, specs: dict, only=None, stale=None, what: str = "scenes") -> dict:
    """{name: directory} of the `jaxmap synth city` scenes `specs` ({name: generate_city keywords}) under
    root (those named in `only`, default all), synthesized where missing or where `stale(dir, kw)` says
    the one there is an older generator's. An unknown name in `only` stops the bench, naming the choices."""
    from jaxmap.synth.city import generate_city

    unknown = set(only or ()) - set(specs)
    if unknown:
        raise SystemExit(f"unknown {what} {', '.join(sorted(unknown))}; choose from {', '.join(specs)}")
    out = {}
    for name, kw in specs.items():
        if only and name not in only:
            continue
        d = os.path.join(root, name)
        if not os.path.isfile(os.path.join(d, "poses.txt")):
            print(f"[bench] synthesizing {name} into {d}", flush=True)
            generate_city(d, **kw)
        elif stale is not None and stale(d, kw):
            print(f"[bench] synthesizing {name} into {d} again (it is an older generator's)", flush=True)
            generate_city(d, **kw)
        out[name] = d
    return out


def default_city(data: str) -> None:
    """The default city (`jaxmap synth city`, seed 0, 130 frames) in directory `data`, synthesized when it is
    not there (the scene of `jaxmap bench n3` and `jaxmap bench path`)."""
    if not os.path.isfile(os.path.join(data, "poses.txt")):
        from jaxmap.synth.city import generate_city

        print(f"[bench] synthesizing the default city into {data}")
        generate_city(data, seed=0)


def base_overrides(args, data: str, output: str | None = None) -> list[str]:
    """Config overrides every bench starts from: the scene directory, the output directory (if
    given), the user's `--set`s, and `--frames` as data.end_frame."""
    base = [f"data.path={data}"] + ([f"output={output}"] if output else []) + list(args.overrides)
    if args.frames:
        base.append(f"data.end_frame={args.frames}")
    return base


MAP_COLS = ("accuracy_cm", "completion_cm", "chamfer_l1_cm", "completion_ratio", "f_score")


def print_map_table(rows: dict, width: int = 22, rule: bool = True) -> None:
    """The reconstruction rows `{name: metrics}` (Acc / Comp / C-L1 / CR / F), preceded by the protocol's
    floor (the ground truth scored against itself) when a row's metrics carry one."""
    floor = next((m["floor"] for m in rows.values() if isinstance(m.get("floor"), dict)), None)
    print(f"{'map':{width}s} {'Acc cm':>7s} {'Comp cm':>8s} {'C-L1 cm':>8s} {'CR %':>6s} {'F %':>6s}")
    if rule:
        print("-" * (width + 40))
    for name, m in (({"floor (GT)": floor} if floor else {}) | rows).items():
        v = [m.get(c, float("nan")) for c in MAP_COLS]
        print(f"{name:{width}s} {v[0]:7.2f} {v[1]:8.2f} {v[2]:8.2f} {v[3]:6.2f} {v[4]:6.2f}")
