"""End-to-end pipeline on a simulated log with ground truth: SLAM beats its odometry, closures are true,
outputs are complete and readable, and a failing run leaves nothing behind."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core import geometry as G
from core.trajectory import read_tum
from evaluation.sim import LASER_PRESETS, load_world, simulate
from slam.cli import main
from slam.logs import open_log
from slam.logs.simulated import write_simulated_log
from slam.pipeline.config import SlamConfig
from slam.pipeline.run import run_slam

pytestmark = pytest.mark.xdist_group("pipeline")


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    """900 scans in the built-in corridor world (two loops), Fast-GPOM laser, drifting odometry."""
    d = tmp_path_factory.mktemp("sim")
    sim = simulate(load_world("corridor"), n_scans=900, spec=LASER_PRESETS["hokuyo_utm30"], seed=7)
    path = d / "corridor.mcap"
    write_simulated_log(sim, path)
    return path, sim


def _ate(poses, gt):
    """RMS position error after the best rigid alignment of the first pose (both start at the origin frame)."""
    A = gt[0] @ G.inverse(poses[0])
    d = (A @ poses)[:, :2, 3] - gt[:, :2, 3]
    return float(np.sqrt((d**2).sum(axis=1).mean()))


@pytest.fixture(scope="module")
def result(sim_log):
    path, _ = sim_log
    cfg = SlamConfig.model_validate({"mapping": {"enabled": False}})
    return run_slam(open_log(path).frames(), cfg)


def test_slam_is_accurate_and_does_not_degrade_odometry(result, sim_log):
    """The SLAM trajectory is within 3 cm RMS of ground truth, at least twice better than the wheels, and
    never worse than its own front end by more than 5 mm (closures may not distort a good odometry)."""
    _, sim = sim_log
    gt = sim.ground_truth
    assert len(result.poses) == len(gt)
    slam_err = _ate(result.poses, gt)
    odo_err = _ate(result.odometry, gt)
    wheel_err = _ate(result.wheel, gt)
    assert slam_err < 0.03, (slam_err, odo_err, wheel_err)
    assert slam_err < wheel_err / 2 and slam_err < odo_err + 0.005, (slam_err, odo_err, wheel_err)


def test_accepted_loop_closures_agree_with_ground_truth(result, sim_log):
    """Every accepted closure's measurement matches the true relative pose within 10 cm and 1°."""
    _, sim = sim_log
    assert len(result.loops) > 0
    kf_gt = sim.ground_truth[[kf.scan_index for kf in result.keyframes]]
    for lc in result.loops:
        err = G.relative(lc.measurement, G.relative(kf_gt[lc.i], kf_gt[lc.j]))
        assert np.linalg.norm(err[:2, 3]) < 0.10
        assert abs(np.degrees(G.matrix_to_xytheta(err)[2])) < 1.0


def test_slam_run_cli_writes_every_output(tmp_path, sim_log, capsys):
    """`slam run` writes all outputs; trajectory.tum has one pose per scan; summary counts match."""
    path, sim = sim_log
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:  # typer exits 0 on success
        main(["run", str(path), "--out", str(out), "--odometry", "icp", "--quiet", "--max-scans", "400"])
    assert exc.value.code in (0, None)
    printed = capsys.readouterr().out
    for name in ("trajectory.tum", "odometry.tum", "graph.g2o", "map.pgm", "map.yaml", "map.png", "variance.png",
                 "map.npz", "result.mcap", "summary.json", "config.yaml", "node_stamps.txt"):
        assert (out / name).stat().st_size > 0, name
    tr = read_tum(out / "trajectory.tum")
    assert len(tr) == 400
    np.testing.assert_allclose(tr.stamps, sim.stamps[:400])
    s = json.loads((out / "summary.json").read_text())
    assert s["scans"] == 400 and f"scans: {s['scans']}" in printed
    assert SlamConfig.from_yaml(out / "config.yaml").odometry.method == "icp"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def _run_with_config(tmp_path, log, name: str, text: str):
    """`slam run LOG --config NAME` (NAME holding *text*) into ``tmp_path / "run"``: (exit code, that folder)."""
    cfg = tmp_path / name
    cfg.write_text(text)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        main(["run", str(log), "--out", str(out), "--config", str(cfg), "--quiet"])
    return exc.value.code, out


def test_summary_lists_the_closures_the_final_solve_pruned(tmp_path, sim_log):
    """summary.json names every closure the final solve dropped: as many as loop_stats counts, none of them in
    graph.g2o, each with its keyframes' stamps (node_stamps.txt) and a violation beyond the pruning thresholds.
    The thresholds are set below the closures' own noise (2 mm / 0.02°) so that this run prunes some."""
    from slam.graph.g2o import read_g2o

    code, out = _run_with_config(tmp_path, sim_log[0], "tight.yaml", "loops:\n  prune_translation_m: 0.002\n  "
                                 "prune_rotation_deg: 0.02\n  prune_rounds: 1\nmapping:\n  enabled: false\n")
    assert code in (0, None)
    s = json.loads((out / "summary.json").read_text())
    pruned = s["pruned_closures"]
    assert len(pruned) == s["loop_stats"]["pruned"] > 0
    stamps = dict(np.loadtxt(out / "node_stamps.txt", ndmin=2))
    g = read_g2o(out / "graph.g2o")
    kept = {(e.i, e.j) for e in g.edges() if e.kind == "loop"}
    for p in pruned:
        assert (p["i"], p["j"]) not in kept
        assert p["stamp_i"] == pytest.approx(stamps[p["i"]]) and p["stamp_j"] == pytest.approx(stamps[p["j"]])
        assert p["translation_m"] > 0.002 or p["rotation_deg"] > 0.02
        assert p["round"] == 1


def test_summary_tests_the_chains_against_the_runs_own_closures(tmp_path, sim_log):
    """summary.json's closure_nees is `slam eval nees RUN` on the run's own outputs: the same bins, one chain per
    kept closure of graph.g2o."""
    from slam.graph.g2o import read_g2o

    code, out = _run_with_config(tmp_path, sim_log[0], "plain.yaml", "mapping:\n  enabled: false\n")
    assert code in (0, None)
    bins = json.loads((out / "summary.json").read_text())["closure_nees"]
    loops = sum(e.kind == "loop" for e in read_g2o(out / "graph.g2o").edges())
    assert bins and sum(b["n"] for b in bins) == loops > 0
    with pytest.raises(SystemExit) as exc:
        main(["eval", "nees", str(out), "--walk", "1", "--jitter", "0", "--heading-drift",
              str(SlamConfig().loops.heading_drift_deg_per_m), "--json", str(tmp_path / "nees.json")])
    assert exc.value.code in (0, None)
    cli = json.loads((tmp_path / "nees.json").read_text())["bins"]
    assert [b["lo"] for b in cli] == [b["lo"] for b in bins]
    for a, b in zip(cli, bins):
        assert a["n"] == b["n"] and a["nees_mean"] == pytest.approx(b["nees_mean"], rel=1e-9)


def test_variance_components_scale_the_graph_the_run_writes(tmp_path):
    """With backend.variance_components, summary.json holds the scales of every edge group, each component's
    share of the χ² matches its share of the redundancy (the estimate's fixed point), and graph.g2o is the graph
    the final solution came from: plain least squares on it, from its own vertices, stays there. The corridor
    world driven round five times: enough closures for the estimate to run."""
    from slam.backends.gtsam_backend import optimize
    from slam.backends.variance_components import MIN_REDUNDANCY
    from slam.graph.g2o import read_g2o

    log = tmp_path / "corridor.mcap"
    write_simulated_log(simulate(load_world("corridor"), n_scans=2400, spec=LASER_PRESETS["hokuyo_utm30"], seed=7), log)
    code, out = _run_with_config(tmp_path, log, "vce.yaml",
                                 "backend:\n  variance_components: true\nmapping:\n  enabled: false\n")
    assert code in (0, None)
    vc = json.loads((out / "summary.json").read_text())["variance_components"]
    assert vc is not None and vc["converged"]
    assert set(vc["groups"]) == {"registration", "wheel", "loop"}
    assert min(b["redundancy"] for b in vc["groups"]["loop"].values()) >= MIN_REDUNDANCY
    for blocks in vc["groups"].values():
        for b in blocks.values():
            assert b["scale"] > 0
            if b["redundancy"] >= MIN_REDUNDANCY:  # a component below it keeps the scale it had
                assert b["chi2"] == pytest.approx(b["redundancy"], rel=0.03)
    g = read_g2o(out / "graph.g2o")
    assert all(e.kernel is None for e in g.edges())
    P = optimize(g, g.poses, method="lm", use_kernels=False).poses
    assert np.abs(G.relative(g.poses, P)[:, :3, 3]).max() < 1e-4


def test_failed_run_leaves_no_output(tmp_path, sim_log, capsys):
    """A bad configuration value stops the run with exit 2 before anything is written."""
    code, out = _run_with_config(tmp_path, sim_log[0], "bad.yaml", "keyframes:\n  distance_m: -1\n")
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.yaml" in err[0]
    assert not out.exists()


def test_slam_run_on_the_kitti_sample_writes_the_3d_outputs(tmp_path, capsys):
    """The 10-scan KITTI sample runs end to end: one pose per scan, steps of a car at ~30 km/h
    (0.6–1.0 m per 0.1 s frame, as both registrations measure it), a 2D map of the height band with
    occupied and free cells, and a voxel point map in PLY."""
    from tests.conftest import shared_path

    seq = shared_path("kitti_odometry_00_sample", "sequences", "00")
    out = tmp_path / "kitti"
    with pytest.raises(SystemExit) as exc:
        main(["run", str(seq), "--out", str(out), "--quiet"])
    assert exc.value.code in (0, None)
    tr = read_tum(out / "trajectory.tum")
    assert len(tr) == 10
    steps = np.linalg.norm(np.diff(tr.poses[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.6) & (steps < 1.0)), steps
    s = json.loads((out / "summary.json").read_text())
    assert s["dimension"] == 3 and s["scans"] == 10
    m = np.load(out / "map.npz")
    p, seen = m["probability"], m["observed"]
    assert (p[seen] > 0.65).sum() > 100 and (p[seen] < 0.35).sum() > 1000
    header = (out / "points.ply").read_bytes()[:400].decode("ascii", "replace")
    n_vertices = int(header.split("element vertex ")[1].split()[0])
    assert n_vertices > 1000


@pytest.mark.parametrize("method", ["fastgpom", "logodds"])
def test_3d_keyframes_drop_their_clouds_and_no_output_changes(method, monkeypatch):
    """A 3D keyframe's full cloud (a KITTI scan: ~120,000 points, 3 MB) is read by the place descriptor and
    the mapping stage's planar slice when the keyframe arrives, then dropped: a long drive would otherwise
    hold all of them. The result's keyframes keep their ICP points and no cloud, and dropping changes no
    output — the same trajectory, closures and map (online Fast-GPOM and a baseline mapped at the final
    poses from the slices kept) as a run that keeps every cloud. Inline stages, so the no-op reaches them;
    equal to 1e-9, not bit for bit: KISS-ICP's threaded sums make two runs of one log differ by ~1e-15 m."""
    from slam.keyframes import Keyframe
    from tests.conftest import shared_path

    frames = list(open_log(shared_path("kitti_mini", "sequences", "00")).frames())
    cfg = SlamConfig.model_validate({"stage_processes": False, "mapping": {"params": {"method": method}}})
    dropped = run_slam(iter(frames), cfg)
    monkeypatch.setattr(Keyframe, "drop_cloud", lambda self: None)
    kept = run_slam(iter(frames), cfg)
    assert len(dropped.keyframes) == len(kept.keyframes) == 10
    for a, b in zip(dropped.keyframes, kept.keyframes):
        assert a.frame.points.shape == (0, 3) and len(b.frame.points) > 50_000
        assert np.array_equal(a.points, b.points) and a.frame.stamp == b.frame.stamp
    assert np.allclose(dropped.poses, kept.poses, rtol=0, atol=1e-9)
    assert [(lc.i, lc.j) for lc in dropped.loops] == [(lc.i, lc.j) for lc in kept.loops]
    assert dropped.map_scans_fused == kept.map_scans_fused == 10
    a, b = dropped.occupancy_map, kept.occupancy_map
    assert a.probability.shape == b.probability.shape and np.array_equal(a.observed, b.observed)
    assert np.allclose(a.probability, b.probability, rtol=0, atol=1e-9)
