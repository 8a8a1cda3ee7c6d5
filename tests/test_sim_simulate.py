"""Simulated logs: odometry drift, determinism, frames, MCAP output and the ``slam simulate`` CLI."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import geometry as geo
from evaluation.sim import LASER_PRESETS, load_world
from evaluation.sim.simulate import odometry_from_ground_truth, simulate
from mapping.mapserver import read_map_server
from slam.logs.simulated import map_paths, write_simulated_log
from tests.conftest import REPO

SPEC = LASER_PRESETS["fastgpom"]


@pytest.fixture(scope="module")
def sim300():
    return simulate(load_world("rooms", seed=1), n_scans=300, spec=SPEC, seed=1)


def _true_path(n=400):
    """A smooth curvy trajectory (x, y, θ) with 5 cm steps."""
    s = np.arange(n) * 0.05
    x, y = s, np.sin(s / 3.0)
    th = np.arctan2(np.gradient(y), np.gradient(x))
    return np.column_stack([x, y, th])


def test_noise_free_odometry_is_exact():
    """With α = 0 the odometry equals the true motion relative to the start pose (closed form)."""
    p = _true_path()
    odo = geo.xytheta_to_matrix(odometry_from_ground_truth(p, (0, 0, 0, 0), np.random.default_rng(0)))
    gt = geo.xytheta_to_matrix(p)
    np.testing.assert_allclose(odo, geo.relative(gt[0], gt), atol=1e-9)


def test_odometry_error_grows_with_distance():
    """Over 200 noise draws the RMS position error of the odometry grows with the distance driven
    (strictly increasing at 5, 10, 15, 20 m) and its heading error too."""
    p = _true_path(401)
    gt = geo.relative(geo.xytheta_to_matrix(p[0]), geo.xytheta_to_matrix(p))
    rng = np.random.default_rng(1)
    idx = [100, 200, 300, 400]
    errs = np.zeros((200, len(idx)))
    herr = np.zeros((200, len(idx)))
    for k in range(200):
        o = odometry_from_ground_truth(p, (0.02, 0.002, 0.01, 0.001), rng)
        errs[k] = np.hypot(o[idx, 0] - gt[idx, 0, 3], o[idx, 1] - gt[idx, 1, 3])
        herr[k] = np.abs(geo.wrap_angle(o[idx, 2] - geo.matrix_to_xytheta(gt[idx])[:, 2]))
    rms = np.sqrt((errs**2).mean(axis=0))
    hrms = np.sqrt((herr**2).mean(axis=0))
    assert np.all(np.diff(rms) > 0) and np.all(np.diff(hrms) > 0)
    assert rms[0] > 0


def test_determinism_and_independent_streams():
    """The same seed gives bit-identical logs; changing only the range noise leaves path and
    odometry unchanged; another seed changes the path."""
    world = load_world("obstacles", seed=2)
    a = simulate(world, n_scans=80, spec=SPEC, seed=3)
    b = simulate(world, n_scans=80, spec=SPEC, seed=3)
    for f in ("stamps", "ground_truth", "odometry", "ranges"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    c = simulate(world, n_scans=80, spec=SPEC, seed=3, range_noise=0.05)
    np.testing.assert_array_equal(a.ground_truth, c.ground_truth)
    np.testing.assert_array_equal(a.odometry, c.odometry)
    assert not np.array_equal(np.nan_to_num(a.ranges, posinf=0), np.nan_to_num(c.ranges, posinf=0))
    d = simulate(world, n_scans=80, spec=SPEC, seed=4)
    assert not np.array_equal(a.ground_truth, d.ground_truth)


def test_simulated_hits_and_no_returns(sim300):
    """Every hit of the 300-scan log lies within half a cell diagonal + 6σ of an occupied cell;
    every no-return beam has no occupied cell within range_max along it (fine-step march)."""
    sim, world = sim300, sim300.world
    sp = sim.sensor_poses()
    xyt = geo.matrix_to_xytheta(sp)
    th = xyt[:, 2:3] + sim.angles[None, :]
    hit = np.isfinite(sim.ranges)
    assert hit.any() and (~hit).any()
    r = np.where(hit, sim.ranges, 0.0)
    pts = np.stack([xyt[:, 0:1] + r * np.cos(th), xyt[:, 1:2] + r * np.sin(th)], -1)[hit]
    xs, ys = world.cell_centres()
    oy, ox = np.nonzero(world.occupied)
    d, _ = cKDTree(np.column_stack([xs[ox], ys[oy]])).query(pts)
    assert d.max() <= world.resolution * math.sqrt(2) / 2 + 6 * sim.range_noise
    # no-return beams: march every res/5 up to range_max
    k, b = np.nonzero(~hit)
    s = np.arange(0.0, SPEC.range_max, world.resolution / 5)
    ang = th[k, b]
    px = xyt[k, 0][:, None] + s[None, :] * np.cos(ang)[:, None]
    py = xyt[k, 1][:, None] + s[None, :] * np.sin(ang)[:, None]
    iy, ix = world.cell_of(np.stack([px, py], -1))
    h, w = world.shape
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    assert not world.occupied[iy[ok], ix[ok]].any()


def test_frames_match_log(sim300):
    """frames() yields one Frame per scan whose points are the hits in the laser frame and whose
    poses are the log's."""
    frames = list(sim300.frames())
    assert len(frames) == 300
    f = frames[17]
    r = sim300.ranges[17]
    assert f.points.shape == (np.isfinite(r).sum(), 2)
    np.testing.assert_allclose(np.hypot(f.points[:, 0], f.points[:, 1]), r[np.isfinite(r)])
    np.testing.assert_array_equal(f.ground_truth, sim300.ground_truth[17])
    np.testing.assert_array_equal(f.odom, sim300.odometry[17])
    assert f.max_range == SPEC.range_max and f.stamp == sim300.stamps[17]


def test_mcap_round_trip_and_map(tmp_path, sim300):
    """The written MCAP reads back (slam.logs reader) with equal float32 ranges, stamps, odometry,
    ground truth and laser mounting; the ground-truth map reads back with the world's classes."""
    from slam.logs import open_log

    out = tmp_path / "s.mcap"
    write_simulated_log(sim300, out)
    yaml_path, pgm_path = map_paths(out)
    assert yaml_path.exists() and pgm_path.exists()
    m = read_map_server(yaml_path)
    np.testing.assert_array_equal(m.classes, sim300.world.classes())
    assert np.allclose(m.origin[:2], sim300.world.origin_xy) and m.resolution == sim300.world.resolution
    frames = list(open_log(out).frames())
    assert len(frames) == 300
    for i in (0, 150, 299):
        f = frames[i]
        np.testing.assert_array_equal(f.ranges, sim300.ranges[i].astype(np.float32).astype(np.float64))
        assert f.stamp == pytest.approx(sim300.stamps[i], abs=1e-9)
        np.testing.assert_allclose(f.odom, sim300.odometry[i], atol=1e-9)
        np.testing.assert_allclose(f.ground_truth, sim300.ground_truth[i], atol=1e-9)
        np.testing.assert_allclose(f.base_T_sensor, sim300.base_T_sensor, atol=1e-12)


def test_failed_write_leaves_nothing(tmp_path, sim300, monkeypatch):
    """If writing the MCAP fails mid-way, neither the log nor the map files exist afterwards."""
    import slam.logs.mcap_writer as mw

    calls = {"n": 0}
    orig = mw.McapLogWriter.write_scan

    def boom(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 50:
            raise RuntimeError("disk full")
        return orig(self, *a, **k)

    monkeypatch.setattr(mw.McapLogWriter, "write_scan", boom)
    with pytest.raises(RuntimeError):
        write_simulated_log(sim300, tmp_path / "x.mcap")
    assert list(tmp_path.iterdir()) == []


def _slam(*args, cwd):
    return subprocess.run([sys.executable, "-m", "slam", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_cli_simulate_then_info(tmp_path):
    """`slam simulate rooms --out sim.mcap --scans 300 --seed 1` then `slam info sim.mcap` prints
    a line exactly `scans: 300`, and the map files exist beside the log."""
    r = _slam("simulate", "rooms", "--out", "sim.mcap", "--scans", "300", "--seed", "1", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "sim_map.yaml").exists() and (tmp_path / "sim_map.pgm").exists()
    info = _slam("info", "sim.mcap", cwd=tmp_path)
    assert info.returncode == 0, info.stderr
    assert "scans: 300" in info.stdout.splitlines()


@pytest.mark.parametrize("args,what", [
    (["nowhere", "--out", "a.mcap"], "unknown world"),
    (["rooms", "--out", "a.mcap", "--sensor", "lidar9000"], "--sensor"),
    (["rooms", "--out", "a.mcap", "--odom-noise", "0.1,0.2"], "--odom-noise"),
    (["rooms", "--out", "a.mcap", "--scans", "0"], "--scans"),
    (["rooms", "--out", "a.mcap", "--scans", "many"], "--scans"),
    (["rooms", "--out", "a.mcap", "--laps", "0"], "--laps"),
    (["rooms", "--out", "a.mcap", "--scans", "300", "--laps", "2"], "--laps"),
    (["rooms", "--out", "a.mcap", "--robot-radius", "0"], "--robot-radius"),
    (["rooms", "--out", "a.mcap", "--robot-radius", "nan"], "--robot-radius"),
    (["rooms", "--out", "a.mcap", "--robot-radius", "5"], "radius 5.00 m"),
])
def test_cli_bad_arguments(tmp_path, args, what, monkeypatch, capsys):
    """Bad arguments give one `error:` line naming the problem, exit status 2 and no output file."""
    from slam.cli import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as ex:
        main(["simulate", *args])
    assert ex.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and what in err[0]
    assert list(tmp_path.iterdir()) == []


def test_repo_has_no_stdr_maps():
    """GPL STDR maps are read from ../shared only, never copied into the project."""
    names = {"simple_rooms.png", "sparse_obstacles.png", "robocup.png", "mines.png"}
    assert not any(p.name in names for p in REPO.rglob("*.png") if ".venv" not in p.parts)


def test_cli_bad_map_yaml(tmp_path, monkeypatch, capsys):
    """A malformed map_server world gives one `error:` line naming the yaml, exit 2, no log written."""
    from slam.cli import main

    (tmp_path / "w.yaml").write_text("image: w.pgm\nresolution: -1\norigin: [0, 0, 0]\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as ex:
        main(["simulate", "w.yaml", "--out", "o.mcap"])
    assert ex.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "w.yaml" in err[0] and "resolution" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.yaml"]


def test_a_sweeping_laser_is_skewed_and_deskewing_undoes_it(tmp_path):
    """A laser with a revolution time (the URG-04LX preset) takes each beam from the pose of its own
    time: its log records that time (``time_increment``), read back as each frame's ``beam_times``; a
    scan taken while turning, deskewed with the true twist, lies on the world's walls seen from the
    pose at mid-sweep, and the same scan read as if taken at once from there does not."""
    from registration.deskew import deskew_planar, planar_twist
    from slam.logs import open_log

    spec = LASER_PRESETS["hokuyo_urg04lx"]
    sim = simulate(load_world("rooms", seed=1), n_scans=300, spec=spec, seed=1, range_noise=0.0)
    out = tmp_path / "urg.mcap"
    write_simulated_log(sim, out)
    frames = list(open_log(out).frames())
    np.testing.assert_allclose(frames[5].beam_times, spec.beam_times(), rtol=1e-6)
    world = sim.world
    iy, ix = np.nonzero(world.occupied)
    cx, cy = world.cell_centres()
    walls = cKDTree(np.column_stack([cx[ix], cy[iy]]))
    sensor = sim.sensor_poses()
    mid = 0.5 * spec.beam_times()[-1]
    turns = [k for k in range(len(sim) - 1)
             if abs(geo.matrix_to_xytheta(geo.relative(sensor[k], sensor[k + 1]))[2]) / spec.period > 0.6]
    assert len(turns) >= 10
    raw_d, fixed_d = [], []
    for k in turns[:20]:
        twist = planar_twist(geo.relative(sensor[k], sensor[k + 1]), spec.period)
        at_mid = sensor[k] @ geo.se3_exp(np.array([twist[0] * mid, twist[1] * mid, 0, 0, 0, twist[2] * mid]))
        for pts, bucket in ((frames[k].points, raw_d), (deskew_planar(frames[k], twist).points, fixed_d)):
            w = geo.transform_points(at_mid, np.column_stack([pts, np.zeros(len(pts))]))[:, :2]
            _, near = walls.query(w, k=4)  # distance to the nearest occupied cell's square (0 on its edge)
            gap = np.maximum(np.abs(w[:, None, :] - walls.data[near]) - 0.5 * world.resolution, 0.0)
            bucket.append(np.percentile(np.linalg.norm(gap, axis=2).min(axis=1), 90))
    assert np.median(fixed_d) < 0.002
    assert np.median(raw_d) > 0.01


def test_a_sweep_longer_than_the_scan_period_is_refused():
    from evaluation.sim import LaserSpec

    with pytest.raises(ValueError, match="sweep"):
        LaserSpec("slow", 100, -np.pi, np.pi * 0.99, 0.1, 5.0, 10.0, 0.01, revolution_s=0.2)
