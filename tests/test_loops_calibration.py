"""The loop closer's variances widened by the run's own long closures (slam.loops.calibration)."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from core import geometry as G
from evaluation.chain_model import ChainSample
from slam.loops.calibration import WindowCalibration
from slam.loops.uncertainty import RelativeUncertainty

SIGMA = np.diag([0.01**2, 0.006**2, np.radians(0.2) ** 2])  # each step's stated covariance
CLOSURE = np.diag([0.02**2, 0.02**2, np.radians(0.3) ** 2])


def _run(rng, true_scale: float, K: int = 700, lengths=(120, 200, 320), every: int = 12):  # type: ignore[no-untyped-def]
    """A front end whose steps err with *true_scale* × their stated covariance, and closures drawn from the truth
    with their own covariance; the calibration fed as the online graph feeds it."""
    cal = WindowCalibration(drift_rad_per_m=0.0)
    truth = [np.eye(4)]
    for k in range(1, K):
        step = G.xytheta_to_matrix(0.3, 0.0, rng.normal(0, 0.08))
        truth.append(truth[-1] @ step)
        measured = step @ G.se2_exp(rng.multivariate_normal(np.zeros(3), true_scale * SIGMA))
        cal.add_step(k - 1, k, measured, SIGMA)
        if k % 2:  # a wheel edge beside half of the steps, given backwards: the same step, fused
            wheel = step @ G.se2_exp(rng.multivariate_normal(np.zeros(3), true_scale * 4 * SIGMA))
            A = G.adjoint(wheel, planar=True)  # the covariance of k_T_(k−1) whose inverse has 4 Σ
            cal.add_step(k, k - 1, G.inverse(wheel), A @ (4 * SIGMA) @ A.T)
        for L in lengths:
            if k % every == 0 and k >= L:
                Z = G.relative(truth[k - L], truth[k]) @ G.se2_exp(rng.multivariate_normal(np.zeros(3), CLOSURE))
                cal.add_closure(k - L, k, Z, CLOSURE)
    return cal


@pytest.mark.parametrize("true_scale", [4.0, 9.0])
def test_closures_of_an_overconfident_front_end_scale_the_variances_by_its_overconfidence(true_scale):
    """Long closures overlap (one loop's closures share most of their chain), so the mean of their NEES has a
    spread of tens of per cent even over 3000 keyframes (4 seeds: 0.87–1.16 × the truth)."""
    cal = _run(np.random.default_rng(3), true_scale, K=3000)
    assert cal.update() == pytest.approx(true_scale, rel=0.3)


def test_a_front_end_as_sure_as_it_says_or_less_keeps_the_stated_model():
    """The stated model is the floor: a consistent or conservative front end searches exactly as before."""
    for true_scale in (0.8, 0.25):
        assert _run(np.random.default_rng(5), true_scale, K=3000).update() == 1.0


def test_too_few_long_closures_leave_the_model_alone():
    cal = _run(np.random.default_rng(7), 9.0, K=300, lengths=(150,), every=20)
    assert 0 < len(cal._rows) < cal.min_chains  # noqa: SLF001 (the sample's size is the point of the test)
    assert cal.update() == 1.0
    # Closures shorter than a long chain are not a sample of the chain's drift at all.
    short = _run(np.random.default_rng(7), 9.0, lengths=(40, 80))
    assert short.update() == 1.0 and not short._rows  # noqa: SLF001


def test_the_scale_multiplies_every_variance_the_closer_uses():
    rng = np.random.default_rng(11)
    K = 60
    pos = np.cumsum(rng.uniform(0.2, 0.4, (K, 2)), axis=0)
    def uncertainty(scale: float) -> RelativeUncertainty:
        u = RelativeUncertainty(planar=True, limit_m2=1e4, drift_rad_per_m=np.radians(0.015))
        for k in range(1, K):
            u.add_edge(k - 1, k, SIGMA, 0.3)
        u.add_edge(5, 50, CLOSURE)
        u.scale = scale
        return u
    one, three = uncertainty(1.0).from_node(K - 1, pos), uncertainty(3.0).from_node(K - 1, pos)
    np.testing.assert_allclose(three.position_var, 3 * one.position_var, rtol=1e-12)
    np.testing.assert_allclose(three.rotation_var, 3 * one.rotation_var, rtol=1e-12)
    np.testing.assert_allclose(three.without_drift().position_var, 3 * one.without_drift().position_var, rtol=1e-12)
    assert uncertainty(3.0).chain_variance(10, 40, pos) == pytest.approx(
        tuple(3 * v for v in uncertainty(1.0).chain_variance(10, 40, pos)), rel=1e-12)


def test_the_sample_grown_at_each_refit_is_the_sample_of_every_closure():
    """The online calibration refits after every keyframe that brought long closures; its sample grows by the new
    ones (``ChainSample.joined``) instead of being rebuilt from every row, and holds exactly the same numbers."""
    rows = _run(np.random.default_rng(3), 4.0, K=1500)._rows  # noqa: SLF001 (the rows are the point of the test)
    whole = ChainSample.of(rows)
    grown = ChainSample.of([])
    for a, b in ((0, 1), (1, 40), (40, 41), (41, len(rows))):
        grown = grown.joined(ChainSample.of(rows[a:b]))
    for f in fields(whole):
        np.testing.assert_array_equal(getattr(grown, f.name), getattr(whole, f.name))
    online, once = WindowCalibration(0.0), WindowCalibration(0.0)
    once._rows = list(rows)  # noqa: SLF001
    for k in range(0, len(rows), 7):
        online._rows = rows[: k + 7]  # noqa: SLF001
        online.update()
    assert online.scale == once.update() > 1.0
