"""`jaxmap bench path`: the way one scan takes through `jaxmap map`, from its read to the frame program.

    jaxmap bench path [--data data/city_bench] [--frames K] [--out runs/bench_path]

`jaxmap map` runs on the first K + 3 frames (default K = 3) in this process with a profile hook on every
thread (`sys.setprofile`): the points of frame K as read (`Sequence.frame(K)`) are marked, and so is what
a jaxmap function returns when it was called with a marked argument (a tuple's, list's or dataclass's
fields too, two levels down). Every call of a jaxmap function that received a marked argument is a step of
the scan's way, up to the frame program's dispatch (`FramePipeline._dispatch`; frame 0: the first
compile, `compiled_step`). Printed: the modules the scan crosses, the calls between modules, and the
distinct moves between functions (caller -> callee, the generated dataclass methods left out), of them
those between modules; the whole way is written to OUT/path_<K>.txt.

Frame 0 takes the set-up with it (the range-image layout read off its scan, the map frame at its pose,
the program compiled from its batch); a later frame is the way every scan takes. The numbers of frame 0
vary a little from run to run: the prefetch thread prepares frames while the main thread compiles.
"""
from __future__ import annotations

import dataclasses
import os
import sys
import threading

STOPS = ("FramePipeline._dispatch", "compiled_step")  # where the scan reaches a frame program


class ScanTrace:
    """The profile hook: marks (`taint`) objects derived from one scan and records the jaxmap calls that
    received one, until `STOPS`."""

    def __init__(self, frame: int):
        self.frame, self.marked, self.keep, self.calls, self.open = frame, set(), [], [], set()
        self.done = False

    def taint(self, obj, depth: int = 0) -> None:
        if obj is None or isinstance(obj, (bool, int, float, str)) or depth > 2:
            return
        self.marked.add(id(obj))
        self.keep.append(obj)  # alive while traced: an id stays this object's
        for child in _children(obj):
            self.taint(child, depth + 1)

    def marked_in(self, obj, depth: int = 0) -> bool:
        if id(obj) in self.marked:
            return True
        return depth < 2 and any(self.marked_in(c, depth + 1) for c in _children(obj))

    def __call__(self, fr, event, arg):
        module = fr.f_globals.get("__name__", "")
        if self.done or not module.startswith("jaxmap") or module == __name__:
            return
        name = fr.f_code.co_qualname
        if event == "call":
            code = fr.f_code
            args = [fr.f_locals.get(v) for v in code.co_varnames[:code.co_argcount + code.co_kwonlyargcount]]
            if any(self.marked_in(a) for a in args):
                self.open.add(id(fr))
                caller = fr.f_back
                self.calls.append((threading.current_thread().name, module, name,
                                   caller.f_globals.get("__name__", "") if caller else "",
                                   caller.f_code.co_qualname.split(".<locals>")[0] if caller else ""))
                self.done = name.endswith(STOPS)
        elif event == "return":
            if id(fr) in self.open:
                self.open.discard(id(fr))
                self.taint(arg)
            if name.endswith(".frame") and module.startswith("jaxmap.io") and fr.f_locals.get("i") == self.frame:
                self.taint(arg)  # the scan as read: the way's first step
                self.calls.append((threading.current_thread().name, module, name, "", ""))


def _children(obj) -> list:
    if isinstance(obj, (tuple, list)):
        return list(obj[:8])
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return [getattr(obj, f.name, None) for f in dataclasses.fields(obj)]
    return []


def summary(calls: list[tuple]) -> dict:
    """The figures of a traced way (calls: (thread, module, function, caller module, caller function))."""
    steps = [c for c in calls if "__create_fn__" not in c[2] and "<lambda>" not in c[2]]
    modules = list(dict.fromkeys(c[1] for c in steps))
    moves = {((cm, cf), (m, f)) for _, m, f, cm, cf in steps if cm.startswith("jaxmap") and (cm, cf) != (m, f)}
    return {"modules": modules, "calls_between_modules": sum(1 for c in steps if c[3] and c[3] != c[1]),
            "moves": len(moves), "moves_between_modules": sum(1 for a, b in moves if a[0] != b[0]),
            "steps": steps}


def main(args) -> int:
    from jaxmap.bench import default_city
    from jaxmap.cli import main as cli_main

    k = args.frames if args.frames is not None else 3
    os.makedirs(args.out, exist_ok=True)
    default_city(args.data)
    trace = ScanTrace(k)
    sys.setprofile(trace)
    threading.setprofile(trace)
    sets = [a for o in [f"data.end_frame={k + 3}", *args.overrides] for a in ("--set", o)]
    try:
        cli_main(["map", "city", "--data", args.data, "--out", os.path.join(args.out, "run"), "--overwrite",
                  "--no-mesh", "--no-progress", *sets])
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    s = summary(trace.calls)
    with open(os.path.join(args.out, f"path_{k}.txt"), "w") as f:
        for t, m, fn, cm, cf in s["steps"]:
            f.write(f"{t:20s} {m}.{fn}  <-  {cm}.{cf}\n")
    print(f"frame {k}'s scan through `jaxmap map`: {len(s['modules'])} modules, {s['calls_between_modules']} calls "
          f"between modules, {s['moves']} distinct moves between functions ({s['moves_between_modules']} between "
          f"modules)\n  modules: {', '.join(s['modules'])}\n  the way: {os.path.join(args.out, f'path_{k}.txt')}")
    return 0
