"""The 2D odometry's local map: scans spaced along the path with wheels, the last scans without.

Compared with the map of the last ten scans (every scan joined it; the default before 2026-11-26), on real
logs: the odometry alone drifts less in heading over long stretches, and the pipeline draws the cluttered labs
of the development set squarer. Without wheel odometry nothing changes.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.trajectory import Trajectory
from evaluation.relations import errors_by_path, read_relations
from mapping.shape import square_share
from registration.odometry import IcpOdometry
from slam.logs import open_log
from slam.pipeline.config import PLANAR_ICP, SlamConfig
from tests.conftest import DATA, shared_path

LAST_TEN_SCANS = PLANAR_ICP.model_copy(update={"map_scans": 10, "unguided_map_scans": None, "map_step_m": 0.0,
                                               "map_step_rad": 0.1})


def _odometry(frames, config, use_wheel_odometry: bool = True) -> IcpOdometry:
    odo = IcpOdometry(config, use_wheel_odometry=use_wheel_odometry)
    odo.run(frames)
    return odo


def test_without_wheels_every_scan_joins_and_the_map_is_the_last_ten():
    """Scan-only registration (the correlative placement needs the densest recent overlap) runs exactly as with
    the map of the last ten scans, whatever the spacing says for scans registered with the wheel guess."""
    frames = []
    for f in open_log(DATA / "intel.clf.bz2").frames():
        frames.append(f)
        if len(frames) == 300:
            break
    a = _odometry(frames, PLANAR_ICP, use_wheel_odometry=False).poses()
    b = _odometry(frames, LAST_TEN_SCANS, use_wheel_odometry=False).poses()
    assert np.array_equal(a, b)
    # with the wheels the two maps differ (so the comparison above is not vacuous)
    c = _odometry(frames, PLANAR_ICP).poses()
    d = _odometry(frames, LAST_TEN_SCANS).poses()
    assert not np.array_equal(c, d)


@pytest.mark.parametrize("log", ["intel", "mit-csail"])
def test_the_spaced_map_drifts_less_in_heading_over_long_stretches(log):
    """Odometry alone against the Kümmerle relations: over ≥ 200 m of path the median heading error is smaller
    with the default map than with the last ten scans, and over < 2 m it stays within 0.05° of it (every
    registration still matches a map that overlaps its scan)."""
    frames = list(open_log(DATA / f"{log}.clf.bz2").frames())
    relations = read_relations(DATA / f"{log}.relations")
    out = {}
    for name, config in (("default", PLANAR_ICP), ("last_ten", LAST_TEN_SCANS)):
        odo = _odometry(frames, config)
        out[name] = errors_by_path(Trajectory(odo.stamps(), odo.poses(base=True)), relations)
    far = {k: np.median(deg[path >= 200.0]) for k, (path, _, deg) in out.items()}
    near = {k: np.median(deg[path < 2.0]) for k, (path, _, deg) in out.items()}
    assert (out["default"][0] >= 200.0).sum() >= 50
    assert far["default"] < far["last_ten"]
    assert near["default"] <= near["last_ten"] + 0.05


MINES = "slam2d_devset/mines-paristech"


@pytest.mark.parametrize("log", [f"{MINES}/exp1.clf", f"{MINES}/exp2.clf", f"{MINES}/exp3.clf", f"{MINES}/test_lab.clf",
                                 "slam2d_devset/brenner-robot4/robot4.clf"])
def test_the_spaced_map_draws_cluttered_labs_squarer(log):
    """The whole pipeline on the cluttered lab logs (a 240° Hokuyo among desks, a LEGO robot's arena): the share
    of wall cells along the map's two dominant perpendicular directions (mapping.shape) is larger with the
    default local map than with the last ten scans — rooms no longer drawn at an angle to each other."""
    from slam.pipeline.run import run_slam

    path = shared_path(*log.split("/"))
    share = {}
    for name, icp in (("default", PLANAR_ICP), ("last_ten", LAST_TEN_SCANS)):
        config = SlamConfig().model_copy(deep=True)
        config = config.model_copy(update={"odometry": config.odometry.model_copy(update={"icp_2d": icp})})
        m = run_slam(open_log(path).frames(), config).occupancy_map
        share[name] = square_share(m.probability, m.observed, m.geometry.resolution)
    assert share["default"] > share["last_ten"]


def test_a_log_whose_wheel_odometry_drops_out_now_and_then_runs_on_both_maps():
    """Scans without wheel odometry among scans with it (a dropped odometry message) switch between the spaced map
    and the last scans without losing track: with every fourth scan's odom gone, the Kümmerle relation error over
    the first 1000 Intel scans stays within 1 cm and 0.2° of the run with every scan's odom."""
    import dataclasses

    from evaluation.relations import evaluate_relations

    frames = []
    for f in open_log(DATA / "intel.clf.bz2").frames():
        frames.append(f)
        if len(frames) == 1000:
            break
    holes = [dataclasses.replace(f, odom=None) if k % 4 == 3 else f for k, f in enumerate(frames)]
    relations = read_relations(DATA / "intel.relations")
    result = {}
    for name, fr in (("full", frames), ("holes", holes)):
        odo = _odometry(fr, PLANAR_ICP)
        assert np.all(np.isfinite(odo.poses()))
        result[name] = evaluate_relations(Trajectory(odo.stamps(), odo.poses(base=True)), relations)
    assert result["holes"].n_used == result["full"].n_used > 30
    assert result["holes"].trans_mean < result["full"].trans_mean + 0.01
    assert result["holes"].rot_mean_deg < result["full"].rot_mean_deg + 0.2
