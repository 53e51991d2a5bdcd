"""Runs that cannot be lost or mixed up (issue 12): one writer per run directory, no silent reuse of a
run, checkpoints that survive damage, SIGTERM and kill -9, configs validated when loaded, and a
one-line error (exit code 2) naming the path at fault for every user mistake, never a traceback."""
import json
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from jaxmap.cli import main

TINY = ["--no-progress", "--set", "data.end_frame=6", "--set", "train.iters=3", "--set", "train.nv=64",
        "--set", "eval.n_samples=20000", "--set", "mesh.resolution_m=0.2", "--set", "checkpoint_every=2",
        "--set", "preprocess.max_range_m=10.0"]
EMPTY = 3  # frame of the test city whose scan is empty


def _map_args(city, out, *extra):
    return ["map", "configs/city.yaml", "--data", str(city), "--out", str(out)] + TINY + list(extra)


def _steps(run):
    d = os.path.join(run, "checkpoint")
    return sorted((int(n) for n in os.listdir(d) if n.isdigit()), reverse=True) if os.path.isdir(d) else []


def _copy_run(src, dst):
    shutil.copytree(src, dst)
    return dst


@pytest.fixture(scope="module")
def city(small_city, tmp_path_factory):
    """The small city (symlinked) with the scan of frame EMPTY replaced by an empty file."""
    d = tmp_path_factory.mktemp("city_empty_scan") / "city"
    (d / "velodyne").mkdir(parents=True)
    for p in small_city.iterdir():
        if p.name != "velodyne":
            (d / p.name).symlink_to(p)
    for p in (small_city / "velodyne").iterdir():
        (d / "velodyne" / p.name).symlink_to(p)
    (d / "velodyne" / f"{EMPTY:06d}.bin").unlink()
    (d / "velodyne" / f"{EMPTY:06d}.bin").write_bytes(b"")
    return d


@pytest.fixture(scope="module")
def ref(city, tmp_path_factory):
    """An uninterrupted run of 6 frames, checkpoints every 2: the reference of every resume below."""
    out = tmp_path_factory.mktemp("ref") / "run"
    assert main(_map_args(city, out)) == 0
    return out


@pytest.fixture
def read_only(tmp_path):
    """A directory nobody may write in: chmod 555, or /sys where root ignores permissions."""
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        yield d
        d.chmod(0o755)
        return
    if not os.path.isdir("/sys") or _can_create("/sys"):
        pytest.skip("running as root without a read-only directory to test with")
    yield pathlib.Path("/sys")


def _can_create(d):
    try:
        os.mkdir(os.path.join(d, "jaxmap_probe"))
    except OSError:
        return False
    os.rmdir(os.path.join(d, "jaxmap_probe"))
    return True


def _one_line_error(capsys, *names):
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    for n in names:
        assert str(n) in lines[0], (n, lines[0])
    return lines[0]


# ------------------------------------------------------------------------------------------------
# the run directory: layout, state, refusal, overwrite, lock
# ------------------------------------------------------------------------------------------------


def test_a_finished_run_keeps_two_checksummed_checkpoints_and_counts_empty_scans(ref):
    steps = _steps(ref)
    assert len(steps) == 2 and steps[0] == 6, steps
    for s in steps:
        m = json.loads((ref / "checkpoint" / str(s) / "manifest.json").read_text())
        assert m["step"] == s and "meta.json" in m["files"] and any(f.startswith("arrays/") for f in m["files"])
    assert json.loads((ref / "run.json").read_text())["status"] == "finished"
    assert not (ref / ".jaxmap.lock").exists()
    timing = json.loads((ref / "timing.json").read_text())
    assert timing["summary"]["empty_frames"] == 1
    assert timing["frames"][EMPTY]["points"] == 0


def test_rerun_into_a_finished_run_is_refused(ref, city, capsys):
    before = (ref / "mesh.ply").stat().st_mtime_ns
    assert main(_map_args(city, ref)) == 2
    _one_line_error(capsys, ref, "finished", "--overwrite")
    assert (ref / "mesh.ply").stat().st_mtime_ns == before


def test_rerun_into_an_unfinished_run_is_refused_with_the_resume_command(ref, city, tmp_path, capsys):
    run = _copy_run(ref, tmp_path / "run")
    (run / "run.json").write_text(json.dumps({"command": "map", "status": "running"}))
    assert main(_map_args(city, run)) == 2
    _one_line_error(capsys, run, f"jaxmap map --resume {run}", "--overwrite", "checkpoint at frame 6")
    # another command's run is not continued by jaxmap map
    (run / "run.json").write_text(json.dumps({"command": "imt", "status": "finished"}))
    assert main(["map", "--resume", str(run), "--no-progress"]) == 2
    _one_line_error(capsys, run, "jaxmap imt run")


def test_a_directory_that_is_not_a_run_is_never_touched(city, tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    assert main(_map_args(city, tmp_path)) == 2
    _one_line_error(capsys, tmp_path, "not a jaxmap run directory")
    assert main(_map_args(city, tmp_path, "--overwrite")) == 2
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_overwrite_clears_old_outputs_and_the_bar_says_it_compiles(ref, city, tmp_path, capsys):
    run = _copy_run(ref, tmp_path / "run")
    (run / "mesh_0.2.ply").write_bytes(b"stale")
    (run / "mesh.metrics.json").write_text("{}")
    args = [a for a in _map_args(city, run, "--overwrite") if a != "--no-progress"]
    assert main(args) == 0
    assert not (run / "mesh_0.2.ply").exists() and not (run / "mesh.metrics.json").exists()
    assert (run / "mesh.ply").read_bytes() == (ref / "mesh.ply").read_bytes()
    assert "mapping (compiling" in capsys.readouterr().err


HOLD_LOCK = textwrap.dedent("""
    import sys, time
    from jaxmap.rundir import RunLock
    RunLock(sys.argv[1], "map").acquire()
    print("locked", flush=True)
    time.sleep(120)
""")


def test_a_second_writer_fails_at_once_naming_the_first_and_a_dead_ones_lock_is_taken_over(
        city, tmp_path, capsys, caplog):
    from jaxmap.rundir import RunLock

    run = tmp_path / "run"
    run.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert main(_map_args(city, run)) == 2
        _one_line_error(capsys, run, f"pid {holder.pid}", "jaxmap map", "in use")
        assert main(["map", "--resume", str(run), "--no-progress"]) == 2
        _one_line_error(capsys, run, f"pid {holder.pid}")
    finally:
        holder.kill()
        holder.wait()
    # kill -9 left the lock file behind, but the kernel dropped the lock: the next run takes it over
    assert (run / ".jaxmap.lock").exists()
    lock = RunLock(str(run), "map").acquire()
    try:
        assert any("taking over" in r.getMessage() and str(holder.pid) in r.getMessage() for r in caplog.records)
    finally:
        lock.release()
    assert not (run / ".jaxmap.lock").exists()


# ------------------------------------------------------------------------------------------------
# kill -9, SIGTERM and damaged checkpoints, then --resume: the same mesh as the uninterrupted run
# ------------------------------------------------------------------------------------------------

SLOW_MAP = textwrap.dedent("""
    import sys, time
    from jaxmap.frame_loop import SubmitSteps
    real = SubmitSteps.submit  # the frame loop hands each frame to the map here
    def slow(self, *a, **k):
        out = real(self, *a, **k)
        time.sleep(0.5)  # leaves time to signal the run between its checkpoints
        return out
    SubmitSteps.submit = slow
    from jaxmap.cli import main
    sys.exit(main(sys.argv[1:]))
""")


def _start_slow_map(city, run):
    """`jaxmap map` in a subprocess (0.5 s per frame more), returned once its first checkpoint is on disk."""
    proc = subprocess.Popen([sys.executable, "-c", SLOW_MAP] + _map_args(city, run),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not _steps(run):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < 600, "no checkpoint after 600 s"
        time.sleep(0.02)
    assert proc.poll() is None, "the run finished before it could be interrupted"
    return proc


def test_kill9_between_checkpoints_then_resume_gives_the_same_mesh(ref, city, tmp_path):
    run = tmp_path / "run"
    proc = _start_slow_map(city, run)
    proc.kill()
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    assert 0 < _steps(run)[0] < 6
    assert main(["map", "--resume", str(run), "--no-progress"]) == 0
    assert (run / "mesh.ply").read_bytes() == (ref / "mesh.ply").read_bytes()
    assert json.loads((run / "metrics.json").read_text()) == json.loads((ref / "metrics.json").read_text())


def test_sigterm_saves_a_checkpoint_then_resume_gives_the_same_mesh(ref, city, tmp_path):
    run = tmp_path / "run"
    proc = _start_slow_map(city, run)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and f"jaxmap map --resume {run}" in err and "terminated (SIGTERM)" in err
    saved = _steps(run)[0]
    assert 2 <= saved < 6
    assert json.loads((run / "run.json").read_text())["status"] == "interrupted"
    assert not (run / ".jaxmap.lock").exists()
    assert main(["map", "--resume", str(run), "--no-progress"]) == 0
    assert (run / "mesh.ply").read_bytes() == (ref / "mesh.ply").read_bytes()


def _damage(ckpt, how):
    """Damage checkpoint directory `ckpt`; returns the file at fault."""
    if how == "truncated meta.json":
        f = ckpt / "meta.json"
        f.write_bytes(f.read_bytes()[:20])
        return f
    data = sorted((p for p in (ckpt / "arrays").rglob("*") if p.is_file() and p.stat().st_size > 64),
                  key=lambda p: -p.stat().st_size)[0]
    if how == "deleted state file":
        data.unlink()
    else:  # a flipped bit
        b = bytearray(data.read_bytes())
        b[len(b) // 2] ^= 0x10
        data.write_bytes(bytes(b))
    return data


@pytest.mark.parametrize("how", ["truncated meta.json", "deleted state file", "flipped bit"])
def test_a_damaged_checkpoint_falls_back_to_the_previous_one(ref, tmp_path, caplog, capsys, how):
    run = _copy_run(ref, tmp_path / "run")
    newest, older = _steps(run)
    bad = _damage(run / "checkpoint" / str(newest), how)
    assert main(["mesh", str(run), "--res", "0.2"]) == 0
    assert json.loads(capsys.readouterr().out)["mesh"] == str(run / "mesh_0.2.ply")
    warned = [r.getMessage() for r in caplog.records if "previous checkpoint" in r.getMessage()]
    assert warned and str(bad) in warned[0] and str(run / "checkpoint" / str(older)) in warned[0], warned


def test_resume_after_the_newest_checkpoint_is_damaged_gives_the_same_mesh(ref, tmp_path):
    run = _copy_run(ref, tmp_path / "run")
    (run / "run.json").write_text(json.dumps({"command": "map", "status": "running"}))
    _damage(run / "checkpoint" / str(_steps(run)[0]), "flipped bit")
    (run / "mesh.ply").unlink()
    assert main(["map", "--resume", str(run), "--no-progress"]) == 0
    assert (run / "mesh.ply").read_bytes() == (ref / "mesh.ply").read_bytes()


def test_no_usable_checkpoint_says_so_and_how_to_start_again(ref, tmp_path, capsys):
    run = _copy_run(ref, tmp_path / "run")
    for s in _steps(run):
        _damage(run / "checkpoint" / str(s), "truncated meta.json")
    assert main(["mesh", str(run)]) == 2
    _one_line_error(capsys, f"no usable checkpoint in {run}", "start again with --overwrite", "meta.json")
    assert main(["map", "--resume", str(run), "--no-progress"]) == 2
    _one_line_error(capsys, f"no usable checkpoint in {run}", "start again with --overwrite")


def test_a_run_that_never_checkpointed_resumes_from_frame_0(ref, tmp_path, caplog):
    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(ref / "config.yaml", run / "config.yaml")
    (run / "run.json").write_text(json.dumps({"command": "map", "status": "running"}))
    assert main(["map", "--resume", str(run), "--no-progress"]) == 0
    assert any("no checkpoint yet" in r.getMessage() and "frame 0" in r.getMessage() for r in caplog.records)
    assert (run / "mesh.ply").read_bytes() == (ref / "mesh.ply").read_bytes()


def test_mesh_of_a_run_without_checkpoint_names_it(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    assert main(["mesh", str(run)]) == 2
    _one_line_error(capsys, run, "no checkpoint yet", f"jaxmap map --resume {run}")


# ------------------------------------------------------------------------------------------------
# configs validated when loaded, before the run directory is touched
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("command,override,names", [
    ("map", "window.mode=voxl", ["window.mode", "did you mean 'voxel'"]),
    ("map", "sampling.label_mode=foo", ["sampling.label_mode", "'projective'"]),
    ("map", "mesh.resolution_m=0.15", ["mesh.resolution_m=0.15", "grid.leaf_vox_size=0.2"]),
    ("map", "train.iters=-5", ["train.iters=-5", ">= 1"]),
    ("map", "nosuch.key=1", ["unknown config section 'nosuch'", "train"]),
    ("map", "trian.iters=3", ["unknown config section 'trian'", "did you mean 'train'"]),
    ("imt", "map.interpolation=foo", ["map.interpolation", "'trilinear'"]),
    ("slam", "frontend.odometry.method=kiss", ["frontend.odometry.method", "did you mean 'kiss_icp'"]),
])
def test_a_bad_config_value_is_a_one_line_error_before_anything_runs(tmp_path, capsys, command, override, names):
    config = {"map": "configs/city.yaml", "imt": "configs/room_imt.yaml", "slam": "configs/room_slam.yaml"}[command]
    out = tmp_path / "run"
    assert main([command, config, "--out", str(out), "--no-progress", "--set", override]) == 2
    line = _one_line_error(capsys, f"--set '{override}'", *names)
    assert "checkpoint_every" not in line
    assert not out.exists()


def test_a_bad_value_in_a_config_file_names_the_file(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("window:\n  mode: voxl\n")
    assert main(["map", str(cfg), "--out", str(tmp_path / "run")]) == 2
    _one_line_error(capsys, f"{cfg}: window.mode='voxl'", "'voxel'")


def test_debug_shows_the_traceback(tmp_path):
    from jaxmap.config import ConfigError

    with pytest.raises(ConfigError, match="train.iters"):
        main(["--debug", "map", "configs/city.yaml", "--out", str(tmp_path / "r"), "--set", "train.iters=-5"])


def test_every_rule_names_a_field_of_its_config():
    import dataclasses

    import jaxmap.runs.slam  # noqa: F401  (registers the front end's rules)
    from jaxmap.config import RULES

    for schema, rules in RULES.items():
        names = {f.name for f in dataclasses.fields(schema)}
        assert set(rules) <= names, (schema.__name__, set(rules) - names)


def test_shipped_configs_pass_their_rules():
    from jaxmap.config import ImtConfig, load_config
    from jaxmap.config import SlamConfig

    load_config("configs/city.yaml")
    load_config("configs/room_imt.yaml", schema=ImtConfig)
    load_config("configs/city_slam.yaml", schema=SlamConfig)


# ------------------------------------------------------------------------------------------------
# output paths
# ------------------------------------------------------------------------------------------------


def test_out_that_is_a_file_or_under_a_file_or_read_only(city, tmp_path, capsys, read_only):
    f = tmp_path / "a_file"
    f.write_text("x")
    assert main(_map_args(city, f)) == 2
    _one_line_error(capsys, f"--out {f}", "is a file")
    assert main(_map_args(city, f / "run")) == 2
    _one_line_error(capsys, f"--out {f / 'run'}", f"{f} is a file")
    assert main(_map_args(city, read_only / "run")) == 2
    _one_line_error(capsys, f"--out {read_only / 'run'}")
    assert main(["synth", "room", "--small", "--frames", "2", "--out", str(read_only / "room")]) == 2
    _one_line_error(capsys, f"--out {read_only / 'room'}")


def test_eval_checks_json_out_first_and_writes_no_side_file(ref, city, tmp_path, capsys, read_only, monkeypatch):
    import jaxmap.finish
    import jaxmap.metrics

    calls = []
    fake = lambda *a, **k: calls.append(a) or {"f_score": 1.0}  # noqa: E731
    monkeypatch.setattr(jaxmap.metrics, "evaluate_mesh_file", fake)
    monkeypatch.setattr(jaxmap.finish, "evaluate_mesh_file", fake)  # (a run's mesh: scored as the run scored it)
    monkeypatch.setattr(jaxmap.metrics, "format_metrics", lambda *a, **k: "(table)", raising=False)
    assert main(["eval", str(ref / "mesh.ply"), "--gt", str(city), "--json-out", str(read_only / "m.json")]) == 2
    _one_line_error(capsys, f"--json-out {read_only / 'm.json'}")
    assert not calls  # refused before the metrics were computed
    out = tmp_path / "sub" / "m.json"
    assert main(["eval", str(ref / "mesh.ply"), "--gt", str(city), "--json-out", str(out)]) == 0
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(out.read_text()) == json.loads(printed) == {"f_score": 1.0}
    assert not (ref / "mesh.metrics.json").exists()


def test_mesh_resolution_mistakes_are_one_line_errors(ref, capsys):
    assert main(["mesh", str(ref), "--res", "-0.1"]) == 2
    _one_line_error(capsys, "--res -0.1", "> 0")
    assert main(["mesh", str(ref), "--res", "0.15"]) == 2
    _one_line_error(capsys, f"--res 0.15 for {ref}", "leaf_vox_size=0.2")
    assert main(["mesh", str(ref / "nope")]) == 2
    _one_line_error(capsys, ref / "nope")


# ------------------------------------------------------------------------------------------------
# data that used to be accepted silently; sequences are indexable
# ------------------------------------------------------------------------------------------------


def test_empty_and_all_zero_scans_are_reported_with_their_file(city, tmp_path, caplog):
    from jaxmap.io import open_sequence, write_poses, write_scan_bin

    seq = open_sequence(city)
    assert len(seq[EMPTY].points) == 0
    assert any("empty scan" in r.getMessage() and f"{EMPTY:06d}.bin" in r.getMessage() for r in caplog.records)
    d = tmp_path / "zeros"
    write_scan_bin(d / "velodyne" / "000000.bin", np.zeros((100, 3), np.float32))
    write_poses(d / "poses.txt", np.eye(4)[None])
    caplog.clear()
    open_sequence(d)[0]
    assert any("all 100 points at the sensor origin" in r.getMessage() and "000000.bin" in r.getMessage()
               for r in caplog.records)


def test_a_mesh_given_as_a_scan_is_read_with_a_warning(tmp_path, caplog):
    import trimesh

    from jaxmap.io import open_sequence, write_poses

    d = tmp_path / "meshes"
    (d / "velodyne").mkdir(parents=True)
    trimesh.creation.box(extents=(4, 4, 4)).export(d / "velodyne" / "000000.ply")
    write_poses(d / "poses.txt", np.eye(4)[None])
    frame = open_sequence(d)[0]
    assert len(frame.points) == 8
    assert any("triangle mesh" in r.getMessage() and "000000.ply" in r.getMessage() for r in caplog.records)


def test_a_depth_image_of_another_size_than_the_intrinsics_is_an_error(small_room, tmp_path):
    from jaxmap.errors import DataError
    from jaxmap.io import open_sequence, read_intrinsics, write_intrinsics

    d = tmp_path / "room"
    d.mkdir()
    for p in small_room.iterdir():
        if p.name != "intrinsics.txt":
            (d / p.name).symlink_to(p)
    fx, fy, cx, cy, _ = read_intrinsics(small_room / "intrinsics.txt")
    write_intrinsics(d / "intrinsics.txt", 4 * fx, 4 * fy, 4 * cx, 4 * cy)  # intrinsics of a 4x larger image
    seq = open_sequence(d)
    with pytest.raises(DataError) as e:
        seq[0]
    assert "depth" in str(e.value) and str(d / "intrinsics.txt") in str(e.value)


def test_open_sequence_is_indexable(small_city):
    from jaxmap.io import open_sequence

    seq = open_sequence(small_city, every_frame=2)
    assert seq[0].index == 0 and seq[-1].index == seq.frame(len(seq) - 1).index == 62
    np.testing.assert_array_equal(seq[1].points, seq.frame(1).points)
    with pytest.raises(IndexError):
        seq[len(seq)]
    with pytest.raises(TypeError):
        seq[0:2]


# ------------------------------------------------------------------------------------------------
# the README's Quickstart and Python snippet outside the repository (issue 43). Here, beside `ref`, because
# a run of TINY on the small city's first frames is the program `ref` compiled: the CLI below loads it
# from the compile cache and the snippet finds it in this process (a test of its own compiled it again).
# ------------------------------------------------------------------------------------------------


def _readme_python(readme: str, tiny: list[str]) -> str:
    """The README's first Python block, small: TINY's settings, 3 frames, the run's mesh resolution."""
    code = re.search(r"^Python:\n\n```python\n(.*?)^```", readme, re.S | re.M).group(1)
    small = {'load_config("city")': f'load_config("city", {tiny!r})',
             'open_sequence("data/city")': 'open_sequence("data/city", end_frame=3)',
             "mapper.mesh(res=0.1)": "mapper.mesh(res=0.2)"}
    for line, repl in small.items():
        assert line in code, f"the README's Python snippet has no {line}"
        code = code.replace(line, repl)
    return code


def test_quickstart_and_python_snippet_run_outside_the_repository(ref, small_city, tmp_path, monkeypatch, capsys):
    """From a folder outside the repository: the Quickstart's `jaxmap map city` (configs by name) on what its
    first line writes (`jaxmap synth city --small --out data/city` is the session's small_city), `jaxmap eval`
    of that partial run equal to its metrics.json to the digit with a warning that it mapped 3 of 64 frames,
    and the README's Python snippet."""
    import jaxmap

    repo = pathlib.Path(__file__).resolve().parents[1]
    readme = (repo / "README.md").read_text(encoding="utf-8")
    for line in ("jaxmap synth city --out data/city", "jaxmap synth city --small --out data/city_small",
                 "jaxmap map city --data data/city --out runs/city", "jaxmap eval runs/city "):
        assert line in readme, f"README.md has no `{line}`"
    assert os.path.relpath(tmp_path, repo).startswith(".."), tmp_path
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "city").symlink_to(small_city)
    tiny = [s for s in TINY[2::2] if not s.startswith("data.end_frame")] + ["data.end_frame=3"]
    env = dict(os.environ, PYTHONPATH=str(pathlib.Path(jaxmap.__file__).parents[1]))  # this jaxmap, as installed
    r = subprocess.run([sys.executable, "-m", "jaxmap", "map", "city", "--data", "data/city", "--out", "runs/city",
                        "--no-progress"] + [a for s in tiny for a in ("--set", s)],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]

    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["eval", "runs/city"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out.splitlines()[-1]) == json.loads((tmp_path / "runs/city/metrics.json").read_text())
    assert "mapped frames 0-2 of the 64 in data/city" in err, err

    scope = {"points_w": np.array([[0.0, 0.0, 0.5], [5.0, 2.0, 1.0]])}  # the snippet's query points
    exec(compile(_readme_python(readme, tiny), "README.md (Python)", "exec"), scope)
    assert scope["sdf"].shape == (2,) and (tmp_path / "mesh.ply").stat().st_size > 0
    assert (tmp_path / "runs/x/checkpoint").is_dir()
