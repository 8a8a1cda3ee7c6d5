"""Front end: the χ² gate that keeps lumpy wheel-odometry edges out of the graph, the a-posteriori edge
covariance, and the online calibration of the wheel noise model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from core import geometry as G
from slam.noise_scale import NoiseScaleCalibration
from slam.pipeline.config import SlamConfig
from slam.pipeline.frontend import FrontEnd, OdometryEdge


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
        fe = _front()
        assert fe._consistent(fe._innovation(edge, T @ G.xytheta_to_matrix(0.0, 0.0, delta)), Ce, Cw) is kept


def test_wheel_gate_off_keeps_every_edge():
    edge = OdometryEdge(0, 1, np.eye(4), np.eye(3) * 1e-6)
    d = _front()._innovation(edge, G.xytheta_to_matrix(0.0, 0.0, 1.0))
    assert _front(None)._consistent(d, edge.covariance, np.eye(3) * 1e-6)
    assert not _front()._consistent(d, edge.covariance, np.eye(3) * 1e-6)


def test_lumpy_wheel_odometry_edges_are_dropped_and_the_rest_kept():
    """Turning in place with wheel odometry that stalls for four scans and then reports the whole turn: the wheel
    edges over the stall and over the lump disagree with the ICP edges by tens of degrees and are left out;
    the wheel edges of the steady turn before and after are kept."""
    from slam.pipeline.odometry_source import make_odometry
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


def _keyframe_pair(odom_step: float):
    """Two keyframes 0.4 m apart along x whose wheel odometry says *odom_step* metres."""
    from types import SimpleNamespace
    prev = SimpleNamespace(id=0, frame=SimpleNamespace(odom=np.eye(4)))
    kf = SimpleNamespace(id=1, frame=SimpleNamespace(odom=G.xytheta_to_matrix(odom_step, 0.0, 0.0)))
    return prev, kf


@pytest.mark.parametrize("lumpy", [False, True])
def test_a_wheel_edge_that_fails_the_gate_is_dropped_only_where_the_wheels_were_lumpy(lumpy):
    """Registration 0.40 m, smooth wheels 0.20 m (a slide along a corridor): far outside the gate. Over smooth
    wheels the edge stays (the registration slid) but is no calibration sample; over lumpy ones it goes."""
    fe = _front()
    prev, kf = _keyframe_pair(0.2)
    edge = OdometryEdge(0, 1, G.xytheta_to_matrix(0.4, 0.0, 0.0), np.diag([1e-4, 1e-4, 1e-6]))
    fe._lumpy_since_kf = lumpy
    wheel, agree = fe._wheel_edge(prev, kf, edge, edge.covariance, edge.covariance)
    assert (wheel is None) is lumpy and not agree
    assert fe.wheel_edges_dropped == int(lumpy)
    if not lumpy:
        assert fe.wheel_calibration is not None and fe.wheel_calibration.samples == 0
        assert G.matrix_to_xytheta(wheel.measurement)[0] == pytest.approx(0.2)


def test_the_wheel_edge_carries_the_calibrated_model_once_enough_edges_agree():
    """Wheels that agree with the registration to 2 mm on 0.4 m steps (σ_model = 4.1 cm): after the calibration's
    minimum of samples the wheel covariance shrinks by the fitted scale², and the gate itself is unchanged."""
    fe = _front()
    rng = np.random.default_rng(5)
    Ce = np.diag([1e-6, 1e-6, 1e-8])
    covs = []
    for _ in range(60):
        noise = rng.normal(0.0, [0.002, 0.002, 0.0005])
        prev, kf = _keyframe_pair(0.4)
        kf.frame.odom = G.xytheta_to_matrix(0.4 + noise[0], noise[1], noise[2])
        wheel, agree = fe._wheel_edge(prev, kf, OdometryEdge(0, 1, G.xytheta_to_matrix(0.4, 0.0, 0.0), Ce), Ce, Ce)
        assert agree
        covs.append((wheel.covariance, fe._wheel_covariance(wheel.measurement)))
    assert np.allclose(*covs[0])  # before min_edges: the model as configured
    cal = fe.wheel_calibration
    assert cal.samples == 60 and cal.scale_translation < 0.1 and cal.scale_rotation < 0.2
    last, model = covs[-1]
    assert np.allclose(np.diag(last), np.diag(model) * np.array([cal.scale_translation] * 2 + [cal.scale_rotation]) ** 2)


@pytest.mark.parametrize("k_t, k_r", [(0.4, 0.1), (1.0, 1.0), (3.0, 0.5)])
def test_wheel_calibration_recovers_the_scale_the_innovations_were_drawn_with(k_t, k_r):
    """Innovations drawn from N(0, Σ_reg + diag(k_t, k_t, k_r)² Σ_model) with random registration covariances: the
    moment fit returns k_t and k_r within 8 % (2000 samples)."""
    rng = np.random.default_rng(11)
    cal = NoiseScaleCalibration(2)
    s = np.array([k_t, k_t, k_r])
    for _ in range(2000):
        L = rng.normal(size=(3, 3)) * np.array([0.01, 0.01, 0.002])[:, None]
        A = L @ L.T + np.diag([1e-6, 1e-6, 1e-8])
        d_step = rng.uniform(0.1, 0.5)
        B = np.diag([(0.1 * d_step) ** 2] * 2 + [(0.08 * d_step) ** 2])
        cal.add(rng.multivariate_normal(np.zeros(3), A + B * np.outer(s, s)), A, B)
    assert cal.scale_translation == pytest.approx(k_t, rel=0.08)
    assert cal.scale_rotation == pytest.approx(k_r, rel=0.08)


@pytest.mark.parametrize("k_t, k_r", [(0.12, 0.1), (0.25, 0.2)])
def test_wheel_calibration_measures_against_the_own_covariance_where_the_margins_hide_the_model(k_t, k_r):
    """Innovations drawn from N(0, Σ_own + diag(k_t, k_t, k_r)² Σ_model), but the trusted side states Σ_own plus
    a floor larger than the whole disagreement (a fast laser's registration with the edge floors): fitted
    against the stated covariance both scales would end at the lower bound (the wheels 2–5 × surer than they
    are); the fit falls back on Σ_own and returns k_t and k_r within 10 % (1500 samples)."""
    rng = np.random.default_rng(3)
    s = np.array([k_t, k_t, k_r])
    cal, floored_only = NoiseScaleCalibration(2), NoiseScaleCalibration(2)
    for _ in range(1500):
        own = np.diag([rng.uniform(0.5, 2.0) * 1e-6] * 2 + [rng.uniform(0.5, 2.0) * 1e-8])
        d_step = rng.uniform(0.2, 0.4)
        B = np.diag([(0.1 * d_step) ** 2] * 2 + [(0.08 * d_step) ** 2])
        floor = B * 0.5  # margins alone above the innovation's whole covariance (k² < 0.5)
        d = rng.multivariate_normal(np.zeros(3), own + B * np.outer(s, s))
        cal.add(d, own + floor, B, own)
        floored_only.add(d, own + floor, B)
    assert (floored_only.scale_translation, floored_only.scale_rotation) == (0.05, 0.05)
    assert cal.scale_translation == pytest.approx(k_t, rel=0.1)
    assert cal.scale_rotation == pytest.approx(k_r, rel=0.1)


def test_wheel_calibration_leaves_the_trusted_sides_margins_out_of_the_models_share():
    """Margins that take most, not all, of the disagreement (a registration sharper than its floors say): fitted
    against the stated covariance the model's scale comes out at 0.4 of the true one (the wheels six times surer
    than they are), above the lower bound; the calibration takes the fit against the own claim, within 10 % of
    the truth (1500 samples)."""
    rng = np.random.default_rng(7)
    k_t, k_r = 0.25, 0.2
    s = np.array([k_t, k_t, k_r])
    cal = NoiseScaleCalibration(2)
    rows = []
    for _ in range(1500):
        own = np.diag([rng.uniform(0.5, 2.0) * 1e-6] * 2 + [rng.uniform(0.5, 2.0) * 1e-8])
        d_step = rng.uniform(0.2, 0.4)
        B = np.diag([(0.1 * d_step) ** 2] * 2 + [(0.08 * d_step) ** 2])
        floor = B * np.outer(s, s) * 0.85  # 85 % of the model's true share
        d = rng.multivariate_normal(np.zeros(3), own + B * np.outer(s, s))
        cal.add(d, own + floor, B, own)
        rows.append((d, own + floor, B))
    stated = np.array([r[1] for r in rows])
    dd, BB = np.array([r[0] for r in rows]), np.array([r[2] for r in rows])
    k_stated = cal._solve(dd[:, :2], stated[:, :2, :2], BB[:, :2, :2])
    assert 0.05 < k_stated < 0.45 * k_t  # above the bound: its fallback alone would not have caught it
    assert cal.scale_translation == pytest.approx(k_t, rel=0.1)
    assert cal.scale_rotation == pytest.approx(k_r, rel=0.1)


def _heading_innovations(rng, n, k_r, bias_per_sigma=0.0):
    """*n* heading innovations: each N(μ, A + k_r² B) with A, B random per interval and a mean μ of
    *bias_per_sigma* of the interval's σ at the true scale (a wheel error that repeats)."""
    for _ in range(n):
        A = np.diag([1e-5, 1e-5, rng.uniform(0.5, 2.0) * 1e-6])
        B = np.diag([1e-4, 1e-4, rng.uniform(0.5, 2.0) * 1e-5])
        sigma = np.sqrt(A[2, 2] + k_r**2 * B[2, 2])
        d = np.r_[rng.normal(0.0, np.sqrt(A[0, 0] + B[0, 0]), 2), rng.normal(bias_per_sigma * sigma, sigma)]
        yield d, A, B


def _calibrated(rows, chain_test: bool = True) -> NoiseScaleCalibration:
    import slam.noise_scale as ns

    runs, ns.CHAIN_MIN_RUNS = ns.CHAIN_MIN_RUNS, (ns.CHAIN_MIN_RUNS if chain_test else 10**9)
    try:
        cal = NoiseScaleCalibration(2)
        for d, A, B in rows:
            cal.add(d, A, B)
    finally:
        ns.CHAIN_MIN_RUNS = runs
    return cal


def test_white_wheel_innovations_keep_the_per_interval_rotation_scale():
    """Heading innovations that are white (independent, zero mean): the test over runs of consecutive ones
    rejects at most at its false-alarm rate (≤ 1 % per run length; 5 run lengths at 2000 samples), so in at
    least 17 of 20 logs the rotation scale is the per-interval fit's."""
    kept = 0
    for seed in range(20):
        rows = list(_heading_innovations(np.random.default_rng(100 + seed), 2000, 0.7))
        kept += _calibrated(rows).scale_rotation == _calibrated(rows, chain_test=False).scale_rotation
    assert kept >= 17


@pytest.mark.parametrize("bias", [0.3, 0.6])
def test_a_wheel_error_that_repeats_widens_the_rotation_scale_until_runs_of_intervals_agree(bias):
    """Heading innovations with a mean of 0.3 or 0.6 σ per interval: one interval's χ² hides it (the
    per-interval scale widens a little), but over runs of L intervals the mean grows L-fold against a σ
    that grows √L-fold. The calibrated scale then makes the sums over the longest runs tested (L = 64,
    31 runs) consistent — their mean NEES within [0.5, 2], the band of the NEES tables — where at the
    per-interval scale it is several times the dimension."""
    rows = list(_heading_innovations(np.random.default_rng(8), 2000, 0.7, bias))
    cal, per_interval = _calibrated(rows), _calibrated(rows, chain_test=False).scale_rotation
    d = np.array([r[0][2] for r in rows])[:1984].reshape(-1, 64).sum(1)
    a = np.array([r[1][2, 2] for r in rows])[:1984].reshape(-1, 64).sum(1)
    b = np.array([r[2][2, 2] for r in rows])[:1984].reshape(-1, 64).sum(1)
    assert np.mean(d**2 / (a + per_interval**2 * b)) > 3.0
    assert 0.5 <= np.mean(d**2 / (a + cal.scale_rotation**2 * b)) <= 2.0
    assert cal.scale_rotation > 1.5 * per_interval
    assert cal.scale_translation == _calibrated(rows, chain_test=False).scale_translation  # not tested on runs


def test_wheel_calibration_waits_for_its_samples_and_stays_within_its_bounds():
    cal = NoiseScaleCalibration(2, min_samples=10, bounds=(0.05, 10.0))
    A, B = np.eye(3) * 1e-4, np.eye(3) * 1e-4
    for _ in range(9):
        cal.add(np.zeros(3), A, B)
    assert (cal.scale_translation, cal.scale_rotation) == (1.0, 1.0)
    cal.add(np.zeros(3), A, B)  # perfect agreement: the registration explains everything
    assert (cal.scale_translation, cal.scale_rotation) == (0.05, 0.05)
    cal = NoiseScaleCalibration(2, min_samples=10, bounds=(0.05, 10.0))
    for _ in range(10):
        cal.add(np.full(3, 10.0), A, B)  # 1000 σ apart: capped
    assert (cal.scale_translation, cal.scale_rotation) == (10.0, 10.0)
    assert np.allclose(cal.calibrated(B), B * 100.0)


@pytest.mark.parametrize("noise", [0.005, 0.07])
def test_edge_covariance_grows_with_the_scans_own_residuals(noise):
    """Keyframe edge of a scan against itself plus range noise σ_n: at σ_n below the a-priori σ (2 cm) the
    covariance is the a-priori one; at 7 cm (the Freiburg hospital's median) it is scaled by σ̂²/σ² ≈ (7/2)²."""
    from types import SimpleNamespace
    rng = np.random.default_rng(2)
    ang = np.linspace(-1.5, 1.5, 400)
    room = np.c_[4.0 * np.cos(ang), 3.0 * np.sin(ang) + 0.5 * np.cos(3 * ang)]  # a curved wall, well conditioned
    prev = SimpleNamespace(id=0, points=room, base_T_sensor=np.eye(4))
    kf = SimpleNamespace(id=1, points=room + rng.normal(0.0, noise, room.shape), base_T_sensor=np.eye(4))
    fe = _front()
    posterior, prior = fe._edge_covariance(prev, kf, np.eye(4))
    ratio = float(np.trace(posterior) / np.trace(prior))
    if noise < 0.02:
        assert ratio == 1.0
    else:
        assert 0.6 * (noise / 0.02) ** 2 < ratio < 1.4 * (noise / 0.02) ** 2


def test_on_a_simulated_log_the_calibration_scales_follow_the_wheel_noise(tmp_path):
    """Two simulated runs of the same path, wheel odometry from the motion model with α = 0.002 and with α = 0.05
    (σ ratio √25 = 5): the calibration fitted against the registration trusts the quiet wheels more in both blocks.
    In heading the ratio of the fitted scales is the noise ratio (3–8×; measured 5.0); in translation the quiet
    wheels sit below the registration's own noise and the scale goes to its lower bound (> 2×; measured 9.5)."""
    from evaluation.sim import LASER_PRESETS, load_world, simulate
    from slam.logs import open_log
    from slam.logs.simulated import write_simulated_log
    from slam.pipeline.odometry_source import make_odometry

    scales = {}
    for alpha in (0.002, 0.05):
        sim = simulate(load_world("rooms"), n_scans=300, spec=LASER_PRESETS["sick_lms"], seed=3, odom_noise=(alpha,) * 4)
        path = tmp_path / f"rooms_{alpha}.mcap"
        write_simulated_log(sim, path)
        cfg = SlamConfig()
        fe = FrontEnd(cfg, make_odometry(cfg, planar=True))
        for frame in open_log(path).frames():
            fe.process(frame)
        cal = fe.wheel_calibration
        assert cal is not None and cal.samples >= cal.min_samples
        scales[alpha] = (cal.scale_translation, cal.scale_rotation)
    (t_lo, r_lo), (t_hi, r_hi) = scales[0.002], scales[0.05]
    assert t_hi > 2 * t_lo and 3 < r_hi / r_lo < 8, scales


class _Scripted:
    """An odometry source that reports given sensor poses (the front end's bookkeeping is what is tested)."""

    def __init__(self, poses: list[np.ndarray], lumpy: bool = False) -> None:
        self.poses, self.n, self.lumpy, self.alternative_starts = poses, 0, lumpy, 0

    def update(self, frame):
        from registration.odometry import OdometryStep
        pose, self.n = self.poses[self.n], self.n + 1
        self.alternative_starts += int(self.lumpy and self.n > 1)  # took its constant-velocity start
        return OdometryStep(frame.stamp, frame.index, pose, pose @ G.inverse(frame.base_T_sensor), np.eye(4), None)


@pytest.mark.parametrize("mount_deg", [0.0, 90.0, 30.0])
@pytest.mark.parametrize("wheels", ["none", "smooth", "lumpy", "held"])
def test_an_edge_in_a_corridor_without_agreeing_wheels_is_uncertain_along_it(mount_deg, wheels):
    """Two keyframes 0.5 m apart in a 2 m wide corridor: the registration pins the step across the corridor, the
    score surface lets it slide ±1 m along it. Without a wheel edge beside it (no wheel odometry, or wheels that
    said 0.2 m while lumpy, whose edge the gate leaves out) the edge covariance (base frame) is then largest
    along the corridor, at about the uniform spread's (1 m)²/3 (the mounting turns the sensor's corridor axis
    into the base's), and stays the registration's across it. So it is beside smooth wheels that fail the gate's
    test ("held": the registration held at 0.3 m where the robot and its wheels moved 1.5 m): their edge stays
    and, against a registration edge that now admits the slide, holds the step. With smooth wheels that agree the
    registration edge keeps its own covariance."""
    from core.frame import Frame
    rng = np.random.default_rng(5)

    def walls(n: int = 3000) -> np.ndarray:  # along the sensor's x at keyframe 0, 2 cm apart on each wall
        x = rng.uniform(-15, 15, n)
        jamb = np.c_[np.full(n // 50, 3.0), rng.uniform(0.8, 1.0, n // 50)]  # a door jamb: 2 % of the points fix x, barely
        return np.vstack([np.c_[x, np.where(rng.random(n) < 0.5, -1.0, 1.0)], jamb]) + 0.0137

    mount = G.xytheta_to_matrix(0.3, 0.1, np.radians(mount_deg))
    step = G.xytheta_to_matrix(1.5 if wheels == "held" else 0.5, 0.0, 0.0)  # sensor frame, along the corridor
    in_view = lambda p: p[np.abs(p[:, 0]) < 8]  # noqa: E731  (each scan sees 16 m of the corridor)
    scans = [in_view(walls()), in_view(G.transform_points(G.inverse(step), walls()))]
    base_poses = [np.eye(4), mount @ step @ G.inverse(mount)]
    odom = {"none": [None, None], "smooth": base_poses, "held": base_poses,
            "lumpy": [np.eye(4), mount @ G.xytheta_to_matrix(0.2, 0.0, 0.0) @ G.inverse(mount)]}[wheels]
    frames = [Frame(stamp=float(k), points=scans[k], index=k, base_T_sensor=mount, odom=odom[k]) for k in range(2)]
    registered = base_poses if wheels != "held" else [np.eye(4), mount @ G.xytheta_to_matrix(0.3, 0.0, 0.0) @ G.inverse(mount)]
    fe = FrontEnd(SlamConfig(), _Scripted([b @ mount for b in registered], lumpy=wheels == "lumpy"))  # type: ignore[arg-type]
    edges = [fe.process(f)[1] for f in frames]
    cov = edges[1].covariance
    axis = mount[:2, 0]  # the corridor (sensor x) in the base frame
    normal = np.array([-axis[1], axis[0]])
    along, across = float(axis @ cov[:2, :2] @ axis), float(normal @ cov[:2, :2] @ normal)
    assert across < 0.02**2
    assert len(fe.wheel_edges) == (wheels in ("smooth", "held"))
    if wheels == "smooth":
        assert along < 0.05**2 and fe.slid_edges == 0
    elif wheels == "held":  # the surface round 0.3 m is less flat (the jamb is 1.2 m nearer): a wide slide, not the exact spread
        wheel_along = float(axis @ fe.wheel_edges[0].covariance[:2, :2] @ axis)
        assert fe.slid_edges == 1 and along > 0.2 and wheel_along < along / 10  # the wheel edge holds the step
    else:
        assert along == pytest.approx(1.0 / 3.0, rel=0.2)
        assert fe.slid_edges == 1 and fe.max_slide_m == pytest.approx(np.sqrt(1.0 / 3.0), rel=0.1)
