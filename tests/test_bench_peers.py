"""benchmarks/peers.py and its KISS-SLAM adapter (evaluation/peers.py).

KISS-SLAM is an optional extra (``make peers``): the one test that runs it is skipped when it is
not importable; everything else runs without it.
"""

from __future__ import annotations

import importlib.util
import itertools
import json
import math
import sys

import numpy as np
import pytest

from core import geometry as geo
from core.trajectory import Trajectory
from evaluation import peers
from evaluation.published import PUBLISHED
from evaluation.relations import evaluate_relations, read_relations
from slam.logs import open_log
from tests.conftest import DATA, REPO

INTEL = DATA / "intel.clf.bz2"
INTEL_REL = DATA / "intel.relations"
SUMMARY_KEYS = {"ours_translation_mean_m", "ours_rotation_mean_deg", "ours_wall_s",
                "kiss_slam_translation_mean_m", "kiss_slam_rotation_mean_deg", "kiss_slam_wall_s",
                "ratio_wall_ours_vs_kiss_slam", "cartographer_translation_mean_m"}


def _bench():
    spec = importlib.util.spec_from_file_location("bench_peers", REPO / "benchmarks" / "peers.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_sensor_to_base_recovers_base_motion(rng):
    """A sensor mounted at base_T_sensor and tracked from its first pose gives back the base's motion
    from its first pose: base_T_sensor · (S0⁻¹ S) · base_T_sensor⁻¹ = B0⁻¹ B with S = B · base_T_sensor."""
    B = geo.se3_exp(rng.normal(size=(20, 6)))
    bTs = geo.se3_exp(rng.normal(size=6))
    S = B @ bTs
    out = peers.sensor_to_base(geo.relative(S[0], S), bTs)
    np.testing.assert_allclose(out, geo.relative(B[0], B), atol=1e-12)


def test_singular_closure_check_is_a_rejection():
    """Open3D's 'Singular 6x6' failure of the closure ICP (z = 0 clouds) rejects the candidate and is
    counted; any other error still propagates."""

    class Closer:
        def __init__(self, exc):
            self.exc = exc

        def validate_closure(self, source, target, guess):
            raise self.exc

    c = Closer(RuntimeError("[Open3D Error] DecodeAndSolve6x6: Singular 6x6 linear system detected"))
    count = peers._guard_singular_closure_icp(c)
    ok, pose = c.validate_closure(None, None, np.eye(4))
    assert ok is False and np.array_equal(pose, np.eye(4)) and count == [1]
    other = Closer(RuntimeError("out of memory"))
    peers._guard_singular_closure_icp(other)
    with pytest.raises(RuntimeError, match="out of memory"):
        other.validate_closure(None, None, np.eye(4))


def test_missing_peer_is_one_line_error(monkeypatch, capsys):
    """Without kiss_slam the benchmark stops at once with exit 2 and one stderr line saying how to install
    the extra (or to skip the peer); stdout stays empty."""
    monkeypatch.setitem(sys.modules, "kiss_slam", None)
    monkeypatch.setitem(sys.modules, "kiss_slam.slam", None)
    assert not peers.kiss_slam_available()
    assert _bench().main(["--max-scans", "5"]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert "make peers" in lines[0] and "--skip-peer" in lines[0]


def test_bad_peer_param_is_one_line_error(capsys):
    """An unknown --peer-param field is reported as one error line naming it (exit 2), before any run."""
    assert _bench().main(["--peer-param", "no_such_field=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_such_field" in err[0]


@pytest.mark.xdist_group("pipeline")
def test_json_shape_without_peer(capsys):
    """--skip-peer on the first 300 Intel scans prints one strict-JSON object: exactly the issue's summary keys,
    null for the skipped peer, Cartographer's published Intel mean, and our relation error over the same
    relations the wheel odometry of those scans is scored on."""
    assert _bench().main(["--skip-peer", "--max-scans", "300"]) == 0
    out = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    s, d = out["summary"], out["details"]
    assert set(s) == SUMMARY_KEYS
    assert s["kiss_slam_translation_mean_m"] is None and s["kiss_slam_wall_s"] is None
    assert s["ratio_wall_ours_vs_kiss_slam"] is None and d["kiss_slam"] is None
    assert s["cartographer_translation_mean_m"] == PUBLISHED["intel"]["cartographer"]["trans"][0]
    assert all(math.isfinite(s[k]) and s[k] >= 0 for k in ("ours_translation_mean_m", "ours_rotation_mean_deg"))
    assert s["ours_wall_s"] > 0 and d["ours"]["run"]["scans"] == 300 and d["wheel_odometry"]["scans"] == 300
    used = d["ours"]["relations"]["n_used"]
    assert used > 0 and used == d["wheel_odometry"]["relations"]["n_used"]
    assert used + d["ours"]["relations"]["n_missing"] == d["relations_total"] == len(read_relations(INTEL_REL))


def test_kiss_slam_on_300_intel_scans(capfd):
    """KISS-SLAM on 300 moving Intel scans (250–549; the first ~240 stand still) as z = 0 clouds: one finite
    rigid pose per scan at the scan stamps, nothing on stdout, and a heading error of the relations below the
    raw wheel odometry's (whose yaw drift is its dominant error on Intel). Over so short a stretch the wheel
    odometry's translation error is itself ~1 cm, so for translation only centimetre level is required."""
    if not peers.kiss_slam_available():
        pytest.skip("kiss-slam (optional extra `peers`) is not installed")
    frames = list(itertools.islice(open_log(INTEL).frames(), 250, 550))
    run = peers.run_kiss_slam(iter(frames), max_scans=300)
    assert capfd.readouterr().out == ""
    X = run.trajectory.poses
    assert X.shape == (300, 4, 4) and np.all(np.isfinite(X))
    assert all(geo.is_pose(T) for T in X)
    np.testing.assert_array_equal(run.trajectory.stamps, [f.stamp for f in frames])
    rel = read_relations(INTEL_REL)
    kiss = evaluate_relations(run.trajectory, rel)
    wheel = evaluate_relations(Trajectory(run.trajectory.stamps, np.array([f.odom for f in frames])), rel)
    assert kiss.n_used == wheel.n_used > 20
    assert kiss.rot_mean_deg < wheel.rot_mean_deg
    assert kiss.trans_mean < 0.05
