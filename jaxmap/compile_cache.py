"""The persistent XLA compilation cache, on for every jaxmap user (library and CLI).

Compiled programs are kept in `~/.cache/jaxmap/xla/<host>`, so a second run (or a second process)
skips the compiles. `<host>` is a fingerprint of the CPU (model and instruction-set flags): an XLA:CPU
executable compiled for one CPU can abort the process that loads it on another, and a home directory
is often shared by machines that differ (a cluster's NFS home, a CI image).
`JAXMAP_CACHE_DIR=/some/dir` moves the cache; `JAXMAP_CACHE_DIR=` (empty) turns it off. It is enabled
when `jaxmap` is imported; `enable()` can be called again with another path.
The last measured compile time of each program is kept beside it, so logs can say how long a
compile will take.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import platform

log = logging.getLogger("jaxmap")

ROOT_DIR = os.path.join(os.path.expanduser("~"), ".cache", "jaxmap", "xla")
_TIMES = "jaxmap_compile_seconds.json"


def host_key(cpuinfo: str | None = None) -> str:
    """12 hex digits naming this host's CPU: architecture, model name and instruction-set flags.

    `cpuinfo` is the text of /proc/cpuinfo (read when None; absent off Linux, where the architecture
    and `platform.processor()` name the CPU)."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as f:
                cpuinfo = f.read()
        except OSError:
            cpuinfo = ""
    fields = {}
    for line in cpuinfo.splitlines():
        name, sep, value = line.partition(":")
        name = name.strip()
        # The first processor's lines are enough: the cores of one host share them.
        if sep and name in ("model name", "flags", "Features", "CPU part") and name not in fields:
            fields[name] = " ".join(sorted(value.split())) if name in ("flags", "Features") else value.strip()
    text = "|".join([platform.machine(), platform.processor()] + [f"{k}={fields[k]}" for k in sorted(fields)])
    return hashlib.sha1(text.encode()).hexdigest()[:12]


DEFAULT_DIR = os.path.join(ROOT_DIR, host_key())


def cache_dir() -> str:
    """The configured cache directory, "" when disabled."""
    return os.environ.get("JAXMAP_CACHE_DIR", DEFAULT_DIR)


def enable(path: str | None = None) -> None:
    """Point JAX's persistent compilation cache at `path` (default: `cache_dir()`); "" disables."""
    path = cache_dir() if path is None else path
    if not path:
        return
    import jax

    try:
        jax.config.update("jax_compilation_cache_dir", path)
        # Cache every program that takes a noticeable time to compile (the frame program takes 5-20 s);
        # JAXMAP_CACHE_MIN_COMPILE_S lowers it (the test suite: 0, its modules drop their compiled programs).
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(os.environ.get("JAXMAP_CACHE_MIN_COMPILE_S", "0.5")))
    except Exception as e:  # an old jax without the option: run uncached rather than fail
        log.debug("no persistent compilation cache: %s", e)


def estimate(name: str) -> float | None:
    """Seconds the last compile of program `name` took on this machine, if known."""
    path = cache_dir()
    try:
        with open(os.path.join(path, _TIMES)) as f:
            return float(json.load(f)[name])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def record(name: str, seconds: float) -> None:
    path = cache_dir()
    if not path:
        return
    try:
        os.makedirs(path, exist_ok=True)
        f = os.path.join(path, _TIMES)
        times = {}
        if os.path.isfile(f):
            with open(f) as fh:
                times = json.load(fh)
        # The slowest compile seen: a cache hit takes a second and says nothing about a cold compile.
        times[name] = round(max(float(seconds), float(times.get(name, 0.0))), 2)
        with open(f + ".tmp", "w") as fh:
            json.dump(times, fh)
        os.replace(f + ".tmp", f)
    except (OSError, ValueError):
        pass


_LOWERED = "/jax/core/compile/jaxpr_to_mlir_module_duration"   # one event per program jax has to build


@contextlib.contextmanager
def programs_built():
    """Count the XLA programs built while the block runs: every jit call that found no executable in
    memory, whether XLA compiled it or it came from this cache (the frame program's compile counter
    cannot see an eager op's program, and XLA's compile event misses a cache hit). Yields a list
    whose length is the count so far (one entry, the seconds of lowering, per program)."""
    import jax

    built: list = []

    def listener(event: str, secs: float, **kw) -> None:
        if event == _LOWERED:
            built.append(secs)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield built
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
