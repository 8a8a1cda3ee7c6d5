"""Front end: the χ² gate that keeps wheel-odometry edges out of the graph when they contradict registration."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from registration import geometry as G
from slam.pipeline.config import SlamConfig
from slam.pipeline.frontend import FrontEnd, OdometryEdge, WheelEdge


def _front(probability: float | None = 0.999) -> FrontEnd:
    cfg = SlamConfig.model_validate({"odometry": {"wheel_gate_probability": probability}})
    fe = FrontEnd(cfg, odometry=None)  # type: ignore[arg-type]  # only the gate is exercised
    fe._dof = 3
    return fe


@pytest.mark.parametrize("scale, kept", [(0.99, True), (1.01, False)])
def test_wheel_gate_is_the_chi2_quantile_of_the_combined_covariance(scale, kept):
    """A heading disagreement δ with δ² / (σ²_edge + σ²_wheel) just below the 99.9 % χ²(3) quantile is kept,
    just above it is dropped (whatever the covariances' sizes)."""
    rng = np.random.default_rng(3)
    for _ in range(5):
        var_e, var_w = rng.uniform(1e-5, 1e-2, size=2)
        Ce, Cw = np.diag([1e-4, 1e-4, var_e]), np.diag([4e-4, 4e-4, var_w])
        delta = np.sqrt(scale * chi2.ppf(0.999, 3) * (var_e + var_w))
        T = G.xytheta_to_matrix(0.4, 0.1, 0.3)
        edge = OdometryEdge(0, 1, T, Ce)
        wheel = WheelEdge(0, 1, T @ G.xytheta_to_matrix(0.0, 0.0, delta), Cw)
        assert _front()._consistent(edge, wheel) is kept


def test_wheel_gate_off_keeps_every_edge():
    edge = OdometryEdge(0, 1, np.eye(4), np.eye(3) * 1e-6)
    wheel = WheelEdge(0, 1, G.xytheta_to_matrix(0.0, 0.0, 1.0), np.eye(3) * 1e-6)
    assert _front(None)._consistent(edge, wheel)
    assert not _front()._consistent(edge, wheel)


def test_lumpy_wheel_odometry_edges_are_dropped_and_the_rest_kept():
    """Turning in place with wheel odometry that stalls for four scans and then reports the whole turn: the wheel
    edges over the stall and over the lump disagree with the ICP edges by tens of degrees and are left out;
    the wheel edges of the steady turn before and after are kept."""
    from slam.pipeline.run import make_odometry
    from tests.test_registration_odometry import _turning_in_place

    frames, _ = _turning_in_place([8.0] * 4 + [0.0] * 4 + [40.0] + [8.0] * 6)
    cfg = SlamConfig.model_validate({"keyframes": {"distance_m": 10.0, "angle_rad": 0.1, "time_s": 100.0}})
    fe = FrontEnd(cfg, make_odometry(cfg, planar=True))
    for f in frames:
        fe.process(f)
    assert len(fe.keyframes) == len(frames)  # every scan turned 8° > 0.1 rad
    assert fe.wheel_edges_dropped == 5  # the four stalled scans and the lump
    assert len(fe.wheel_edges) == 10
    for w in fe.wheel_edges:  # every kept wheel edge is a steady 8° step
        assert np.degrees(G.matrix_to_xytheta(w.measurement)[2]) == pytest.approx(8.0, abs=1e-9)
