"""Run directories that cannot be lost or mixed up: one writer at a time, no silent reuse, writable outputs.

A run directory of `jaxmap map`, `imt` or `slam` holds, besides the run's outputs:

  .jaxmap.lock   an advisory lock (`fcntl.flock`) held by the process writing the directory, with its
                 command, pid, host and start time; removed when it exits. The kernel drops the lock
                 of a process that dies (even by kill -9), so a lock file left behind by a dead process
                 is taken over with a warning; a live owner makes a second writer fail at once.
  run.json       the command that made the run and its status: "running", "interrupted" (Ctrl-C,
                 SIGTERM), "failed" or "finished".

`claim(run_dir, command, resume=..., overwrite=...)` takes the lock and decides what may happen to the
directory: a new run goes into a missing or empty directory; one that holds a run needs `--resume`
(continue it) or `--overwrite` (delete everything in it first); a non-empty directory that is not a
jaxmap run is never touched. `output_dir` / `output_file` check an output path before any work, so
a path that is a file, lies under a file or is read-only is a one-line error naming it.

`interrupt_requests()` turns SIGINT and SIGTERM into a flag the mapping loop reads between frames,
so both stop the run at a frame boundary and save a checkpoint.
"""
from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import json
import logging
import os
import shutil
import signal
import socket
import threading
from dataclasses import dataclass

from jaxmap.errors import RunDirError

log = logging.getLogger("jaxmap")

LOCK = ".jaxmap.lock"
STATE = "run.json"
# Files that make a directory a jaxmap run (run.json; config.yaml and checkpoint/ for runs of jaxmap <= 0.1).
_RUN_MARKERS = (STATE, "config.yaml", "checkpoint")


def _now() -> str:
    return datetime.datetime.now().isoformat(timespec="seconds")


# ------------------------------------------------------------------------------------------------
# output paths
# ------------------------------------------------------------------------------------------------


def _blocking_file(path: str) -> str | None:
    """The nearest existing ancestor of `path` (or `path` itself) when it is not a directory, else None."""
    p = os.path.abspath(path)
    while not os.path.exists(p):
        parent = os.path.dirname(p)
        if parent == p:
            return None
        p = parent
    return None if os.path.isdir(p) else p


def _probe_writable(directory: str, flag: str, shown: str) -> None:
    """RunDirError unless a file can be created in existing `directory` (what counts, even as root)."""
    probe = os.path.join(directory, f".jaxmap-write-test-{os.getpid()}-{threading.get_ident()}")
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except OSError as e:
        raise RunDirError(f"{flag} {shown}: {directory} is not writable ({e.strerror}); "
                          f"pick a writable {flag} or fix its permissions") from None
    os.close(fd)
    os.unlink(probe)


def _make_dir(directory: str, flag: str, shown: str) -> None:
    """Create `directory` (for `flag` = `shown`) if needed; RunDirError when a file is in the way, it
    cannot be created or it is not writable."""
    blocker = _blocking_file(directory)
    if blocker == os.path.abspath(directory):
        raise RunDirError(f"{flag} {shown}: {'is' if shown == directory else directory + ' is'} a file, not a "
                          f"directory; pick another {flag}")
    if blocker is not None:
        raise RunDirError(f"{flag} {shown}: {blocker} is a file, so there can be no directory under it; "
                          f"pick another {flag}")
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as e:
        raise RunDirError(f"{flag} {shown}: cannot create {directory} ({e.strerror}); pick a writable {flag}") from None
    _probe_writable(directory, flag, shown)


def output_dir(path: str, flag: str = "--out") -> str:
    """Create directory `path` if needed and check that it is a writable directory; returns `path`.
    RunDirError (one line naming `flag` and the path) when it is a file, lies under a file, cannot be
    created or is read-only."""
    path = os.fspath(path)
    _make_dir(path, flag, path)
    return path


def output_file(path: str, flag: str = "--out") -> str:
    """Check before any work that file `path` can be written: its directory is created if needed and
    must be writable, and `path` must not be a directory. Returns `path`; RunDirError otherwise."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise RunDirError(f"{flag} {path}: is a directory; name a file, e.g. {os.path.join(path, 'out.json')}")
    _make_dir(os.path.dirname(os.path.abspath(path)), flag, path)
    return path


# ------------------------------------------------------------------------------------------------
# the lock
# ------------------------------------------------------------------------------------------------


def _describe(owner: dict) -> str:
    cmd = f"jaxmap {owner['command']}" if owner.get("command") else "a jaxmap process"
    return f"{cmd} (pid {owner.get('pid', '?')} on {owner.get('host', '?')}, since {owner.get('since', '?')})"


def _read_owner(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        raw = os.read(fd, 4096)
        return json.loads(raw) if raw.strip() else {}
    except (OSError, ValueError):
        return {}


class RunLock:
    """The advisory lock of one run directory (see the module docstring). `acquire()` fails at once with
    a RunDirError naming the live owner; `release()` removes the lock file."""

    def __init__(self, run_dir: str, command: str):
        self.run_dir, self.command = os.fspath(run_dir), command
        self.path = os.path.join(self.run_dir, LOCK)
        self.fd: int | None = None

    def acquire(self) -> "RunLock":
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                owner = _read_owner(fd)
                os.close(fd)
                if e.errno not in (errno.EAGAIN, errno.EACCES):
                    raise RunDirError(f"{self.run_dir}: cannot lock {self.path} ({e.strerror})") from None
                raise RunDirError(f"{self.run_dir}: in use by {_describe(owner)}; wait for it to finish or "
                                  f"stop it (kill {owner.get('pid', 'PID')}), or pick another --out") from None
            try:  # the owner before us may have removed the file we locked: lock the one at the path
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        stale = _read_owner(fd)
        if stale:
            log.warning("%s: taking over the lock left by %s, which is no longer running", self.run_dir,
                        _describe(stale))
        me = {"command": self.command, "pid": os.getpid(), "host": socket.gethostname(), "since": _now()}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(me).encode(), 0)
        os.fsync(fd)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)  # while still locked, so nobody takes a lock on a file about to vanish
        os.close(self.fd)
        self.fd = None


# ------------------------------------------------------------------------------------------------
# what a directory holds
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunState:
    """What a directory holds. kind: "empty" (missing, or nothing but a lock file), "run" (a jaxmap
    run) or "other" (anything else). command and status come from run.json (None for runs of jaxmap
    <= 0.1); frames is the step of the newest checkpoint (None without one)."""

    kind: str
    command: str | None = None
    status: str | None = None
    frames: int | None = None
    entries: tuple = ()


def inspect(run_dir: str) -> RunState:
    """The `RunState` of directory `run_dir`."""
    from jaxmap.checkpoint import steps

    if not os.path.isdir(run_dir):
        return RunState("empty")
    entries = tuple(sorted(n for n in os.listdir(run_dir) if n != LOCK))
    if not entries:
        return RunState("empty")
    if not any(m in entries for m in _RUN_MARKERS):
        return RunState("other", entries=entries)
    info = {}
    with contextlib.suppress(OSError, ValueError):
        with open(os.path.join(run_dir, STATE)) as f:
            info = json.load(f)
    status = info.get("status") if isinstance(info, dict) else None
    if status is None and "mesh.ply" in entries:
        status = "finished"
    have = steps(os.path.join(run_dir, "checkpoint"))
    return RunState("run", info.get("command") if isinstance(info, dict) else None, status,
                    have[0] if have else None, entries)


def write_status(run_dir: str, command: str, status: str) -> None:
    """Record `status` of the run in run_dir/run.json (atomically)."""
    path = os.path.join(run_dir, STATE)
    info = {}
    with contextlib.suppress(OSError, ValueError):
        with open(path) as f:
            info = json.load(f)
    if not isinstance(info, dict) or info.get("command") != command:
        info = {"command": command, "started": _now()}
    info.update(status=status, updated=_now())
    with open(path + ".tmp", "w") as f:
        json.dump(info, f)
    os.replace(path + ".tmp", path)


def clear(run_dir: str) -> None:
    """Delete everything in `run_dir` but the lock file (`--overwrite`)."""
    for name in os.listdir(run_dir):
        if name == LOCK:
            continue
        p = os.path.join(run_dir, name)
        if os.path.isdir(p) and not os.path.islink(p):
            shutil.rmtree(p)
        else:
            os.unlink(p)


def _refusal(run_dir: str, command: str, state: RunState) -> str:
    what = f"jaxmap {state.command} run" if state.command else "jaxmap run"
    done = state.status == "finished"
    at = f" (checkpoint at frame {state.frames})" if state.frames is not None and not done else ""
    head = f"{run_dir}: holds a {'finished' if done else 'started, unfinished'} {what}{at}; "
    if command in ("map", "slam") and not done and state.command in (None, command):
        return head + f"continue it with: jaxmap {command} --resume {run_dir}, or replace it with --overwrite"
    return head + "replace it with --overwrite, or pick another --out"


# ------------------------------------------------------------------------------------------------
# signals
# ------------------------------------------------------------------------------------------------


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal (SIGINT or SIGTERM); `signum` says which."""

    def __init__(self, signum: int = signal.SIGINT):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def exit_code(e: KeyboardInterrupt) -> int:
    """The shell's exit code for a run stopped by `e`: 128 + the signal number (130 SIGINT, 143 SIGTERM)."""
    return 128 + int(getattr(e, "signum", signal.SIGINT))


@contextlib.contextmanager
def terminate_raises():
    """Within the block (main thread only), SIGTERM raises `Interrupted(SIGTERM)` as Ctrl-C raises
    KeyboardInterrupt, so `finally` blocks run (lock released, status written) instead of a silent death."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Interrupted(signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


class StopRequests:
    """Set by SIGINT/SIGTERM inside `interrupt_requests()`; `check()` raises `Interrupted` once set.
    `forced`: a second Ctrl-C raised at once, possibly in the middle of a frame."""

    def __init__(self):
        self.signum: int | None = None
        self.forced = False

    def check(self) -> None:
        if self.signum is not None:
            raise Interrupted(self.signum)


@contextlib.contextmanager
def interrupt_requests():
    """Within the block (main thread only), the first SIGINT or SIGTERM only sets the yielded
    `StopRequests` (the loop calls `check()` between frames, so a frame is never cut in half and the
    state it donated is never lost); a second SIGINT raises KeyboardInterrupt at once."""
    stop = StopRequests()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, frame):
        if stop.signum is not None and signum == signal.SIGINT:
            stop.forced = True
            raise Interrupted(signum)
        stop.signum = signum
        log.warning("%s: stopping after this frame and saving a checkpoint (Ctrl-C again to stop now, "
                    "without one)", signal.Signals(signum).name)

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


# ------------------------------------------------------------------------------------------------
# claiming a run directory
# ------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def claim(run_dir: str, command: str, *, resume: bool = False, overwrite: bool = False, flag: str = "--out"):
    """Hold `run_dir` for a run of `jaxmap command` for the duration of the block (see the module
    docstring). resume: the directory must hold an unfinished or finished run of this command;
    overwrite: a run there is deleted first. Yields the `RunState` found before the run started;
    run.json says "running" during the block, then "finished", "interrupted" or "failed"; a new run
    that fails before writing anything but its config leaves the directory empty."""
    if resume and overwrite:
        raise RunDirError(f"{run_dir}: --resume continues the run there and --overwrite deletes it; pick one")
    if resume and not os.path.isdir(run_dir):
        raise RunDirError(f"--resume {run_dir}: no such run directory; pass the --out of the run to continue")
    output_dir(run_dir, flag)
    lock = RunLock(run_dir, command).acquire()
    try:
        state = inspect(run_dir)
        if resume:
            if state.kind != "run":
                raise RunDirError(f"{run_dir}: no jaxmap run to resume there; start one with: "
                                  f"jaxmap {command} CONFIG --out {run_dir}")
            if state.command not in (None, command):
                raise RunDirError(f"{run_dir}: holds a jaxmap {state.command} run, not a jaxmap {command} run; "
                                  f"pass the directory of a jaxmap {command} run")
        elif state.kind == "run":
            if not overwrite:
                raise RunDirError(_refusal(run_dir, command, state))
            log.info("--overwrite: deleting the previous run in %s", run_dir)
            clear(run_dir)
        elif state.kind == "other":
            shown = ", ".join(state.entries[:3]) + (", ..." if len(state.entries) > 3 else "")
            raise RunDirError(f"{flag} {run_dir}: not empty ({shown}) and not a jaxmap run directory; "
                              f"pick a new or empty {flag}")
        write_status(run_dir, command, "running")
        status = "failed"
        try:
            with terminate_raises():
                yield state
            status = "finished"
        except KeyboardInterrupt:
            status = "interrupted"
            raise
        finally:
            with contextlib.suppress(OSError):
                left = set(os.listdir(run_dir)) - {LOCK}
                if status == "failed" and not resume and left <= {STATE, "config.yaml"}:
                    clear(run_dir)  # a new run failed before any output (a wrong --data...): leave no run behind
                else:
                    write_status(run_dir, command, status)
    finally:
        lock.release()
