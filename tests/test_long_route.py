"""The long drive with --length-km (issue 39): an X km route through the same long city that passes its
intersections again (loops over streets already driven, no U-turns, always on a street), the default
serpentine unchanged, the options' errors; and `jaxmap bench n3 --long`'s tables (`long_table`,
`late_ratio`) on synthetic per-frame records. Poses only: no city is built or ray cast here."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from jaxmap.cli import main
from jaxmap.synth.city import (LONG, _blocks, _snake_waypoints, generate_city, long_drive, long_route,
                               long_waypoints, route_revisits)


@pytest.fixture(scope="module")
def drive_3_7():
    return long_drive(length_km=3.7)


def _passes(xy: np.ndarray, centre, radius: float) -> int:
    """Separate runs of consecutive points within radius of centre: how often a drive passes there."""
    near = np.flatnonzero(np.hypot(*(xy - np.asarray(centre)).T) < radius)
    return 0 if len(near) == 0 else 1 + int(np.count_nonzero(np.diff(near) > 1))


def test_default_long_route_unchanged():
    """Without a length the long drive is the serpentine of before: its waypoints, 1114.8 m, 1025 frames
    1.0887 m apart (the files of `jaxmap synth city --long` were checked byte for byte against it)."""
    route, T, spacing = long_drive()
    expected = [(-100, -72), (100, -72), (100, -36), (-100, -36), (-100, 0), (100, 0), (100, 36), (-100, 36),
                (-100, 72), (100, 72)]
    assert np.array_equal(long_waypoints(), np.array(expected, float))
    assert np.array_equal(route.waypoints, _snake_waypoints(LONG)) and np.array_equal(long_route().waypoints,
                                                                                       route.waypoints)
    assert route.length == pytest.approx(1114.814150222053, abs=1e-9) and len(T) == LONG.frames == 1025
    assert spacing == pytest.approx(1.0886856935762237, abs=1e-12)
    assert np.allclose(T[0, :3, 3], (-100.0, -72.5, 1.73)) and np.allclose(T[512, :3, 3], (0.0, -0.5, 1.73))
    assert np.allclose(T[-1, :3, 3], (100.0, 71.5, 1.73))


def test_length_km_route_length_and_frames(drive_3_7):
    """3.7 km within 5 % (the route is cut to a whole number of frames), at the serpentine's frame spacing,
    whose frames it starts with; fewer frames stop early, more spread over the route."""
    route, T, spacing = drive_3_7
    _, T0, spacing0 = long_drive()
    assert route.length == pytest.approx(3700.0, rel=0.05) and abs(route.length - 3700.0) < 2.0
    assert spacing == spacing0 and len(T) == 3400 and spacing * (len(T) - 1) == pytest.approx(route.length)
    steps = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    assert np.all(steps <= spacing + 1e-6) and np.all(steps > 0.99 * spacing)
    assert sum(steps) == pytest.approx(3700.0, rel=0.05)
    assert np.array_equal(T[:1000], T0[:1000])  # the serpentine first, then the loops
    _, T5, sp5 = long_drive(5, length_km=3.7)
    assert sp5 == spacing and np.array_equal(T5, T[:5])
    _, T2, sp2 = long_drive(4000, length_km=3.7)
    assert sp2 < spacing and np.allclose(T2[-1], T[-1]) and np.allclose(T2[0], T[0])
    for km in (0.3, 1.0, 2.345, 6.0):  # any length: within a few metres (the frame spacing, a corner)
        assert long_route(length_m=km * 1000).length == pytest.approx(km * 1000, abs=6.0)


def test_length_km_revisits_intersections(drive_3_7):
    """Like KITTI's sequence 00 the drive comes back: at least 3 (here: every) intersections are passed
    twice or more, and a good share of the metres run over streets already driven; the serpentine alone
    passes none twice."""
    route, T, _ = drive_3_7
    xs, ys = LONG.street_lines()
    radius = LONG.road_width / 2 + 1.0
    passes = np.array([_passes(T[:, :2, 3], (x, y), radius) for x in xs for y in ys])
    assert (passes >= 2).sum() >= 3 and (passes >= 2).sum() == 30 and passes.min() >= 1
    rv = route_revisits(route)
    assert rv["intersections_passed_again"] == (passes >= 2).sum() and rv["max_passes"] == passes.max()
    assert rv["revisited_m"] > 1000.0
    _, T0, _ = long_drive()
    assert max(_passes(T0[:, :2, 3], (x, y), radius) for x in xs for y in ys) == 1
    assert route_revisits(long_route())["intersections_passed_again"] == 0


def test_length_km_no_u_turns(drive_3_7):
    """Every corner turns by 90 degrees (never back the way it came), the heading changes a car's few
    degrees a frame and never by more than a corner's worth within 25 m of road."""
    route, T, spacing = drive_3_7
    legs = np.diff(route.waypoints, axis=0)
    legs /= np.linalg.norm(legs, axis=1, keepdims=True)
    assert np.allclose(np.einsum("ij,ij->i", legs[:-1], legs[1:]), 0.0, atol=1e-12)
    yaw = np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    assert np.abs(np.diff(yaw)).max() < np.deg2rad(8)
    w = int(25.0 / spacing)
    assert np.abs(yaw[w:] - yaw[:-w]).max() < np.deg2rad(100)
    P = T[:, :3, 3]
    motion = np.diff(P[:, :2], axis=0) / np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", motion, T[:-1, :2, 0]).min() > 0.99  # forwards all along


def test_length_km_on_the_streets(drive_3_7):
    """Every leg lies on a street of the city's grid: waypoints on the street lines inside the grid, every
    frame within its street (never on a block, where the buildings stand)."""
    route, T, _ = drive_3_7
    xs, ys = LONG.street_lines()
    W = route.waypoints
    assert all(np.isclose(x, xs).any() or np.isclose(y, ys).any() for x, y in W)
    assert np.all((W[:, 0] >= xs[0]) & (W[:, 0] <= xs[-1]) & (W[:, 1] >= ys[0]) & (W[:, 1] <= ys[-1]))
    for a, b in zip(W[:-1], W[1:]):  # axis-aligned legs along a street line
        assert (a[0] == b[0] and np.isclose(a[0], xs).any()) or (a[1] == b[1] and np.isclose(a[1], ys).any())
    P = T[:, :3, 3]
    to_centre = np.minimum(np.abs(P[:, :1] - np.array(xs)).min(1), np.abs(P[:, 1:2] - np.array(ys)).min(1))
    assert to_centre.max() < LONG.road_width / 2 - 1.0
    for x0, x1, y0, y1, _, _ in _blocks(LONG):
        assert not np.any((P[:, 0] > x0 - 1) & (P[:, 0] < x1 + 1) & (P[:, 1] > y0 - 1) & (P[:, 1] < y1 + 1))


def test_length_km_errors(tmp_path, capsys):
    """--length-km needs --long and a positive number: argparse errors (exit status 2) naming the fix."""
    for argv, says in ((["--length-km", "3"], "use it with --long"),
                       (["--long", "--length-km", "0"], "must be a positive number of km"),
                       (["--long", "--length-km", "-2"], "must be a positive number of km"),
                       (["--long", "--length-km", "x"], "not a number of km")):
        with pytest.raises(SystemExit) as e:
            main(["synth", "city", "--out", str(tmp_path / "c"), *argv])
        assert e.value.code == 2 and says in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["bench", "n3", "--length-km", "3"])
    assert e.value.code == 2 and "use it with --long" in capsys.readouterr().err
    with pytest.raises(ValueError, match="needs long"):
        generate_city(tmp_path / "c", length_km=1.0)
    with pytest.raises(ValueError, match="positive"):
        generate_city(tmp_path / "c", long=True, length_km=-1.0)
    assert not os.path.exists(tmp_path / "c")


# ------------------------------------------------------------------------------------------------
# jaxmap bench n3 --long: the tables of its per-frame records
# ------------------------------------------------------------------------------------------------


def _records(n: int, times, **extra) -> list:
    """n per-frame records like timing.json's: total_s from times(i), RSS rising 1 MB a frame."""
    out = []
    for i in range(n):
        r = {"frame": i, "total_s": float(times(i)), "rss_mb": 1000.0 + i, "peak_rss_mb": 1100.0 + i}
        r.update({k: f(i) for k, f in extra.items() if f(i) is not None})
        out.append(r)
    return out


def test_long_table_rows():
    from jaxmap.bench.n3 import long_table

    recs = _records(1025, lambda i: 1.0 + (i % 100) / 1000, device_mb=lambda i: 2000.0 + i if i % 7 == 0 else None)
    rows = long_table(recs, 500)
    assert [r["frames"] for r in rows] == [[0, 499], [500, 999], [1000, 1024]]
    assert rows[0]["median_s"] == pytest.approx(np.median(1.0 + (np.arange(500) % 100) / 1000))
    assert rows[0]["p95_s"] == pytest.approx(np.percentile(1.0 + (np.arange(500) % 100) / 1000, 95))
    assert [r["rss_mb"] for r in rows] == [1499.0, 1999.0, 2024.0]
    assert [r["peak_rss_mb"] for r in rows] == [1599.0, 2099.0, 2124.0]
    assert [r["device_mb"] for r in rows] == [2000.0 + 497, 2000.0 + 994, 2000.0 + 1022]  # the last that has it
    assert all(r["submaps_resident"] is None and r["submaps_on_disk"] is None for r in rows)
    fine = long_table(recs, 100)
    assert len(fine) == 11 and fine[-1]["frames"] == [1000, 1024] and fine[3]["frames"] == [300, 399]
    # the peak so far never falls, whatever a record says
    recs[600]["peak_rss_mb"] = 9999.0
    assert [r["peak_rss_mb"] for r in long_table(recs, 500)] == [1599.0, 9999.0, 9999.0]
    sub = _records(300, lambda i: 0.5, submaps_resident=lambda i: 3 + i // 100, submaps_on_disk=lambda i: i // 50)
    rows = long_table(sub, 100)
    assert [(r["submaps_resident"], r["submaps_on_disk"], r["device_mb"]) for r in rows] == \
        [(3, 1, None), (4, 3, None), (5, 5, None)]
    assert long_table([], 500) == []


def test_late_ratio_and_printed_table(capsys):
    from jaxmap.bench.n3 import late_ratio, long_table, print_long_table

    assert late_ratio(_records(999, lambda i: 1.0)) is None
    slow = _records(2000, lambda i: 2.0 if i < 500 else 1.0 if i < 1000 else 1.05 if i < 1500 else 1.2)
    r = late_ratio(slow)
    assert r["late"] == [1500, 1999] and r["median_500_1000_s"] == 1.0 and r["median_late_s"] == 1.2
    assert r["ratio"] == pytest.approx(1.2) and r["within_10pct"] is False
    ok = late_ratio(_records(1800, lambda i: 1.0 if i < 1000 else 1.08))
    assert ok["ratio"] == pytest.approx(1.08) and ok["within_10pct"] is True and ok["late"] == [1300, 1799]
    print_long_table(long_table(slow, 500), "every 500 frames:")
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "every 500 frames:" and "device MB" in out[1] and "submaps res" in out[1]
    assert len(out) == 3 + 4 and out[3].split() == ["0-499", "2.000", "2.000", "1499", "1599", "n/a", "-", "-"]


def test_bench_long_length_km(tmp_path, monkeypatch, capsys):
    """`jaxmap bench n3 --long --length-km X --set K=V`: the mapping run gets the overrides, the tables go
    to OUT/long.json (the run itself is faked: its summary and per-frame records)."""
    import jaxmap.bench.n3 as n3

    data, out = tmp_path / "city_long_2.5km", tmp_path / "out"
    data.mkdir()
    (data / "poses.txt").write_text("")
    (data / "meta.json").write_text(json.dumps({"trajectory": {"length_km": 2.5}}))
    calls = []
    keys = ("store_pairs", "store_bytes", "window_voxels", "leaf_voxels", "feature_rows", "feature_capacity")

    def fake_map(d, o, cache, overrides, evaluate=True):
        calls.append((d, overrides, evaluate))
        frames = _records(1200, lambda i: 1.0, submaps_resident=lambda i: 4, submaps_on_disk=lambda i: i // 100)
        for r in frames:
            r.update({k: 1 for k in keys})
        return {"wall_s": 1200.0, "wall_s_per_frame": 1.0, "compile_s": 5.0, "compiles": 2,
                "peak_rss_mapping_mb": 2300.0, "frames": frames}

    monkeypatch.setattr(n3, "map_in_subprocess", fake_map)
    assert main(["bench", "n3", "--long", "--length-km", "2.5", "--data", str(data), "--out", str(out),
                 "--set", "train.iters=3", "--set", "map.x=1"]) == 0
    (d, overrides, evaluate), = calls
    assert d == str(data) and not evaluate
    assert overrides[:2] == ["train.iters=3", "map.x=1"] and "checkpoint_every=100000" in overrides
    text = capsys.readouterr().out
    assert "every 500 frames:" in text and "every 100 frames:" in text and "ratio 1.000" in text
    assert "peak RSS of the mapping process" in text
    res = json.loads((out / "long.json").read_text())
    assert res["length_km"] == 2.5 and res["overrides"] == ["train.iters=3", "map.x=1"]
    assert [r["frames"] for r in res["tables"]["every_500"]] == [[0, 499], [500, 999], [1000, 1199]]
    assert len(res["tables"]["every_100"]) == 12 and res["tables"]["every_500"][-1]["submaps_on_disk"] == 11
    assert res["late_ratio"]["ratio"] == 1.0 and res["late_ratio"]["within_10pct"] is True
    assert "process_peak_rss_mb" in res and "median_100_200" in res  # (the outputs of before stay)
    # a sequence of another length is not taken for this one
    with pytest.raises(SystemExit, match="not 3 km"):
        main(["bench", "n3", "--long", "--length-km", "3", "--data", str(data), "--out", str(out)])
    args = type("A", (), {"data": "data/city_bench", "length_km": 3.7})()
    assert n3.long_data_dir(args) == "data/city_long_3.7km"
    args.length_km = None
    assert n3.long_data_dir(args) == "data/city_long"
