"""Odometry (KissOdometry, IcpOdometry): one interface, real logs and simulated scans."""

from __future__ import annotations

import numpy as np
import pytest

from core import geometry as geo
from core.frame import Frame
from registration.config import IcpConfig, IcpOdometryConfig, KissOdometryConfig
from registration.odometry import IcpOdometry, OdometryStep, wheel_increment
from registration.odometry_kiss import KissOdometry
from tests.conftest import DATA, shared_path


def _intel_frames(n: int):
    from slam.logs import open_log

    out = []
    for f in open_log(DATA / "intel.clf.bz2").frames():
        out.append(f)
        if len(out) == n:
            break
    return out


@pytest.mark.parametrize("kind", ["kiss", "icp"])
def test_planar_odometry_on_intel_interface_and_shape(kind):
    """Both odometries take Frames and return steps with planar world_T_sensor, prev_T_curr that
    chains to the pose, and a symmetric positive-definite 3×3 increment covariance."""
    frames = _intel_frames(150)
    odo = KissOdometry(KissOdometryConfig.planar_default()) if kind == "kiss" else IcpOdometry()
    steps = odo.run(frames)
    assert len(steps) == 150 and all(isinstance(s, OdometryStep) for s in steps)
    assert steps[0].covariance is None and np.allclose(steps[0].world_T_sensor, np.eye(4))
    for a, b in zip(steps[:-1], steps[1:]):
        assert np.allclose(a.world_T_sensor @ b.prev_T_curr, b.world_T_sensor, atol=1e-9)
        assert b.world_T_sensor[2, 3] == 0 and np.allclose(b.world_T_sensor[2, :3], [0, 0, 1])
    covs = [s.covariance for s in steps[1:] if s.covariance is not None]
    assert len(covs) > 140
    for C in covs:
        assert C.shape == (3, 3) and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)


def test_kiss_beats_wheel_odometry_on_intel_relations():
    """On the first 2000 Intel scans, KISS-ICP (z = 0, no deskew, wheel guess) has a smaller mean
    Kümmerle relation error (translation and rotation) and a smaller median rotation error than raw
    wheel odometry (scan matching removes the heading drift)."""
    from core.trajectory import Trajectory
    from evaluation.relations import evaluate_relations, read_relations

    frames = _intel_frames(2000)
    odo = KissOdometry(KissOdometryConfig.planar_default().model_copy(update={"compute_covariance": False}))
    odo.run(frames)
    rel = read_relations(DATA / "intel.relations")
    kiss = evaluate_relations(Trajectory(odo.stamps(), odo.poses(base=True)), rel)
    wheel = evaluate_relations(Trajectory(odo.stamps(), np.array([f.odom for f in frames])), rel)
    assert kiss.n_used > 50
    assert kiss.trans_mean < wheel.trans_mean and kiss.rot_mean_deg < wheel.rot_mean_deg
    assert np.median(kiss.rot_errors_deg) < np.median(wheel.rot_errors_deg)


def test_wheel_increment_in_sensor_frame():
    """The wheel guess is the sensor motion B⁻¹·odom_a⁻¹·odom_b·B for a sensor offset B."""
    B = geo.xytheta_to_matrix(0.2, 0.0, 0.0)
    oa, ob = geo.xytheta_to_matrix(0, 0, 0), geo.xytheta_to_matrix(0, 0, np.pi / 2)
    fa = Frame(0.0, np.zeros((3, 2)), odom=oa, base_T_sensor=B)
    fb = Frame(0.1, np.zeros((3, 2)), odom=ob, base_T_sensor=B)
    inc = wheel_increment(fa, fb)
    # Turning in place by 90°: the sensor 0.2 m ahead moves to (−0.2, 0.2) in its old frame.
    assert np.allclose(geo.matrix_to_xytheta(inc), [-0.2, 0.2, np.pi / 2])


def test_icp_odometry_on_simulated_path_tracks_truth():
    """IcpOdometry on simulated SICK scans (σ = 1 cm) along a straight 2 m path through the most
    open part of the 'rooms' world, no wheel odometry (constant-velocity guess): the end pose is
    within 5 cm and 1° of the truth (point-to-point ICP has a known sampling bias of a few mm and
    ~0.05° per scan; 20 scans)."""
    sim = pytest.importorskip("evaluation.sim")
    from scipy.ndimage import distance_transform_edt

    world = sim.load_world("rooms")
    spec = sim.LASER_PRESETS["sick_lms"]
    xs, ys = world.cell_centres()
    clear = distance_transform_edt(world.free) * world.resolution
    # The path x ∈ [x0, x0 + 2] at the row and start with the largest minimum clearance.
    n = int(round(2.0 / world.resolution))
    from numpy.lib.stride_tricks import sliding_window_view

    run = sliding_window_view(clear, n, axis=1).min(axis=-1)
    iy, ix0 = np.unravel_index(np.argmax(run), run.shape)
    assert run[iy, ix0] > 0.5
    poses = np.column_stack([xs[ix0] + np.arange(21) * 0.1, np.full(21, ys[iy]), np.zeros(21)])
    R = sim.cast_rays(world, poses, spec, rng=np.random.default_rng(0), range_noise=0.01)
    ang = spec.angles()
    frames = []
    for k, r in enumerate(R):
        ok = np.isfinite(r)
        frames.append(Frame(0.1 * k, np.column_stack([r[ok] * np.cos(ang[ok]), r[ok] * np.sin(ang[ok])]), index=k))
    odo = IcpOdometry()
    odo.run(frames)
    truth = geo.relative(geo.xytheta_to_matrix(poses[0]), geo.xytheta_to_matrix(poses[-1]))
    E = geo.relative(truth, odo.world_T_sensor)
    assert np.linalg.norm(E[:2, 3]) < 0.05
    assert abs(np.degrees(geo.matrix_to_xytheta(E)[2])) < 1.0


def _kitti_frames():
    from slam.logs import open_log

    return list(open_log(shared_path("kitti_odometry_00_sample", "sequences", "00")).frames())


def test_kiss_on_kitti_returns_6dof_steps():
    """KissOdometry on the 10 real KITTI frames: 6×6 PD covariances, forward motion every frame."""
    frames = _kitti_frames()
    odo = KissOdometry(KissOdometryConfig())
    steps = odo.run(frames)
    for s in steps[1:]:
        assert s.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(s.covariance) > 0)
        assert s.prev_T_curr[0, 3] > 0.5


@pytest.mark.parametrize("seq", ["00", "01"])
def test_default_3d_odometry_end_point_drift_below_one_percent(seq):
    """Acceptance (issue 25): the default 3D odometry's end-point drift over kitti_mini's 10 frames ≤ 1 % of the
    distance travelled (6.7 m on 00, 9.0 m on 01; 07 and 10 creep 1–2 m, where a percentage says little), against
    the SemanticKITTI poses (not the official ones, a placeholder over frames 0–14). KISS-ICP (``--odometry kiss``)
    drifts 1.4 % and 1.0 % here, from its first steps on an empty map (docs/ODOMETRY.md)."""
    from slam.logs import open_log
    from slam.pipeline.config import SlamConfig
    from slam.pipeline.odometry_source import make_odometry

    frames = list(open_log(shared_path("kitti_mini", "sequences", seq)).frames())
    odo = make_odometry(SlamConfig(), planar=False)
    odo.run(frames)
    gt = np.array([f.ground_truth for f in frames])
    G = geo.relative(gt[0], gt)
    dist = np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1))
    est = geo.relative(odo.steps[0].world_T_sensor, odo.world_T_sensor)
    err = np.linalg.norm(geo.relative(G[-1], est)[:3, 3])
    assert dist > 5.0 and err / dist <= 0.01


def test_default_3d_odometry_starts_a_log_that_begins_at_speed():
    """A log that begins in motion: every third kitti_mini 01 frame (3.0 m between the first two, 30 m/s at
    10 Hz) from a standing estimate. The first step runs the wide first gate and every step stays within
    5 cm of the SemanticKITTI poses; with the configured gates alone the first step ends 1.5 m short."""
    from slam.logs import open_log
    from slam.pipeline.config import SlamConfig

    frames = list(open_log(shared_path("kitti_mini", "sequences", "01")).frames())[::3]
    gt = np.array([f.ground_truth for f in frames])
    assert np.linalg.norm(geo.relative(gt[0], gt[1])[:3, 3]) > 2.9
    errors = {}
    for gate in (SlamConfig().odometry.icp_3d.first_step_gate_m, None):
        odo = IcpOdometry(SlamConfig().odometry.icp_3d.model_copy(update={"first_step_gate_m": gate}))
        P = np.array([s.world_T_sensor for s in odo.run(frames)])
        errors[gate] = max(np.linalg.norm(geo.relative(geo.relative(gt[k - 1], gt[k]), geo.relative(P[k - 1], P[k]))[:3, 3])
                           for k in range(1, len(P)))
    assert errors[SlamConfig().odometry.icp_3d.first_step_gate_m] < 0.05
    assert errors[None] > 0.5  # the case the gate is for


def test_icp_odometry_keeps_the_wheel_guess_when_icp_jumps_out_of_its_basin():
    """A scan that cannot match its map (a different room) pulls ICP far from the wheel guess; with the
    deviation bound the step equals the wheel increment, without it the step follows the (wrong) ICP."""
    from registration.config import IcpConfig, IcpOdometryConfig

    ang = np.linspace(-np.pi / 2, np.pi / 2, 181)

    def frame(k, pts, odom):
        r = np.hypot(*pts.T)
        return Frame(stamp=0.1 * k, points=pts, index=k, angles=ang[: len(pts)], ranges=r, odom=odom)

    wall = np.c_[np.full(181, 3.0), np.linspace(-2.0, 2.0, 181)]  # a wall 3 m ahead
    other = np.c_[np.full(181, 2.2), np.linspace(-2.0, 2.0, 181)]  # the next scan sees it 0.8 m closer
    odo0, odo1 = np.eye(4), geo.xytheta_to_matrix(0.05, 0.0, 0.0)  # but the wheels say 5 cm
    icp_cfg = IcpConfig(gates_m=(1.0, 0.5), max_iterations=30)
    out = {}
    for bound in (None, 0.3):
        odo = IcpOdometry(IcpOdometryConfig(icp=icp_cfg, max_guess_deviation_m=bound))
        odo.update(frame(0, wall, odo0))
        step = odo.update(frame(1, other, odo1))
        out[bound] = step.prev_T_curr[0, 3]
    assert out[0.3] == pytest.approx(0.05, abs=1e-9)
    assert out[None] > 0.5


def _turning_in_place(wheel_yaw_steps):
    """Simulated scans of a robot turning in place 8° per scan in the 'rooms' world; wheel odometry
    that advances by *wheel_yaw_steps* (degrees, summing to the truth at the end) instead."""
    from evaluation import sim

    world = sim.load_world("rooms")
    spec = sim.LASER_PRESETS["sick_lms"]
    ang = spec.angles()
    n = len(wheel_yaw_steps) + 1
    truth = np.radians(8.0) * np.arange(n)
    xy = np.array([3.0, 3.0])
    iy, ix = world.cell_of(xy[None])
    assert world.free[iy[0], ix[0]]
    rng = np.random.default_rng(7)
    R = sim.cast_rays(world, np.column_stack([np.full(n, xy[0]), np.full(n, xy[1]), truth]), spec, rng=rng,
                      range_noise=0.01)
    wheel = np.radians(np.concatenate([[0.0], np.cumsum(wheel_yaw_steps)]))
    frames = []
    for k in range(n):
        ok = np.isfinite(R[k])
        pts = np.column_stack([R[k][ok] * np.cos(ang[ok]), R[k][ok] * np.sin(ang[ok])])
        frames.append(Frame(stamp=0.1 * k, points=pts, index=k, angles=ang, ranges=R[k],
                            odom=geo.xytheta_to_matrix(0.0, 0.0, wheel[k])))
    return frames, truth


def test_icp_odometry_survives_wheel_odometry_logged_in_lumps():
    """Wheel odometry that reports no turn for four scans and then the whole 40° at once (as the MIT CSAIL
    log does) is a wrong guess twice. With the constant-velocity alternative start the ICP heading stays
    within 0.5° of the truth over the whole turn. Without it the lump's guess is 32° off: ICP from it finds
    the right turn, but so far from the guess that the deviation bound keeps the wrong guess."""
    from registration.config import IcpConfig, IcpOdometryConfig

    steps = [8.0, 8.0, 0.0, 0.0, 0.0, 0.0, 40.0, 8.0, 8.0]
    frames, truth = _turning_in_place(steps)
    assert np.isclose(np.sum(steps), np.degrees(truth[-1]))
    icp_cfg = IcpConfig(gates_m=(0.3,), max_iterations=30, robust="cauchy", robust_scale_m=0.05, workers=1)
    final = {}
    for alt in (None, 0.05):
        odo = IcpOdometry(IcpOdometryConfig(icp=icp_cfg, point_to_plane=True, map_voxel_m=0.03,
                                            max_guess_deviation_m=0.3, max_guess_deviation_rad=0.35,
                                            alternative_start_m=alt, alternative_start_rad=alt))
        odo.run(frames)
        poses = odo.poses()
        yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
        final[alt] = np.degrees(np.abs(np.angle(np.exp(1j * (yaw - truth)))))
        # The 4 stale scans (no wheel motion: lumpy even when steady), the lump and the one after.
        assert odo.alternative_starts == (0 if alt is None else 6)
    assert final[0.05].max() < 0.5
    assert final[None].max() > 10.0



def test_wheels_lag_the_scans_only_where_they_report_at_most_half_the_scans_motion():
    """The lag test behind the constant-velocity start: the wheels lag the scans' last increment when, in a part
    where the two disagree beyond its bound, the wheels report at most half the scans' motion. A steady 4 cm a
    scan beside a registration that stopped or stepped back is the registration's slide, not a lag (below
    0.5 m/s at 10 Hz every wheel increment is under the 5 cm bound, so "under the bound" alone called every
    slow robot's wheels stale)."""
    from registration.wheel_lag import wheels_lag

    X = lambda x, y=0.0, th=0.0: geo.xytheta_to_matrix(x, y, th)  # noqa: E731
    b_m, b_rad = 0.05, 0.05
    assert wheels_lag(X(0.0), X(0.2), b_m, b_rad)  # no motion at all while the scans moved on (a gap)
    assert wheels_lag(X(0.04), X(0.2), b_m, b_rad)  # a fifth of it
    assert wheels_lag(X(0.04, th=0.0), X(0.04, th=0.3), b_m, b_rad)  # no turn while the scans turned (a lump)
    assert not wheels_lag(X(0.04), X(-0.02), b_m, b_rad)  # the registration stepped back: it slid
    assert not wheels_lag(X(0.04, 0.0, 0.03), X(0.04, 0.0, -0.03), b_m, b_rad)  # turned the other way
    assert not wheels_lag(X(0.04), X(0.06), b_m, b_rad)  # within the bound: no disagreement
    assert not wheels_lag(X(0.2), X(0.5), b_m, b_rad)  # the wheels move beyond the bound: the other test's case
    assert not wheels_lag(X(0.0), X(0.2), None, b_rad)  # translation left out of the test


def test_wheels_lag_only_where_they_also_drop_below_half_their_own_typical_increment():
    """With the wheels' own typical increment over the last scans known, a lag is also a drop to at most half of
    it. Steady slow wheels (4 cm a scan) beside a registration that slid 25 cm forward along a corridor report
    what they always do: the slide is the registration's (before, 4 cm against 25 cm was a lag, and the
    constant-velocity start carried the slide on). Wheels that used to report 12 cm and now 4 cm lag; a lumpy
    odometry whose typical step or turn is nil still lags where it reports no motion at all."""
    from registration.wheel_lag import wheels_lag

    X = lambda x, y=0.0, th=0.0: geo.xytheta_to_matrix(x, y, th)  # noqa: E731
    b_m, b_rad = 0.05, 0.05
    assert wheels_lag(X(0.04), X(0.25), b_m, b_rad)  # nothing known of the wheels' history: as before
    assert not wheels_lag(X(0.04), X(0.25), b_m, b_rad, typical=(0.04, 0.0))  # steady wheels, a slid registration
    assert not wheels_lag(X(0.04), X(0.25), b_m, b_rad, typical=(0.05, 0.0))  # within twice the step: still steady
    assert wheels_lag(X(0.04), X(0.25), b_m, b_rad, typical=(0.12, 0.0))  # the wheels dropped to a third
    assert wheels_lag(X(0.0), X(0.25), b_m, b_rad, typical=(0.0, 0.0))  # no motion at all is a lag whatever the history
    assert wheels_lag(X(0.04, th=0.0), X(0.04, th=0.3), b_m, b_rad, typical=(0.04, 0.0))  # no turn, turns typically nil
    assert not wheels_lag(X(0.04, th=0.02), X(0.04, th=0.3), b_m, b_rad, typical=(0.04, 0.02))  # a steady turn
    assert not wheels_lag(X(0.04), X(-0.02), b_m, b_rad, typical=(0.12, 0.0))  # the registration stepped back


def _rooms_odometry(cast_x: np.ndarray, wheel_step_m: float) -> IcpOdometry:
    """Our ICP odometry run over scans cast in the simulator's rooms at x = *cast_x* (y 3 m, heading 0, a scan
    every 0.1 s), with wheel odometry advancing *wheel_step_m* a scan; constant-velocity start bounds 5 cm / 0.05 rad."""
    from evaluation import sim
    from registration.config import IcpConfig, IcpOdometryConfig

    world = sim.load_world("rooms")
    spec = sim.LASER_PRESETS["sick_lms"]
    ang = spec.angles()
    n = len(cast_x)
    truth = np.column_stack([cast_x, np.full(n, 3.0), np.zeros(n)])
    iy, ix = world.cell_of(truth[:, :2])
    assert world.free[iy, ix].all()
    R = sim.cast_rays(world, truth, spec, rng=np.random.default_rng(3), range_noise=0.01)
    frames = []
    for k in range(n):
        ok = np.isfinite(R[k])
        pts = np.column_stack([R[k][ok] * np.cos(ang[ok]), R[k][ok] * np.sin(ang[ok])])
        frames.append(Frame(stamp=0.1 * k, points=pts, index=k, angles=ang, ranges=R[k],
                            odom=geo.xytheta_to_matrix(wheel_step_m * k, 0.0, 0.0)))
    icp_cfg = IcpConfig(gates_m=(0.3,), max_iterations=30, robust="cauchy", robust_scale_m=0.05, workers=1)
    odo = IcpOdometry(IcpOdometryConfig(icp=icp_cfg, point_to_plane=True, map_voxel_m=0.03,
                                        max_guess_deviation_m=0.3, max_guess_deviation_rad=0.35,
                                        alternative_start_m=0.05, alternative_start_rad=0.05))
    odo.run(frames)
    return odo


def test_a_registration_jump_beside_steady_slow_wheels_takes_no_constant_velocity_start():
    """Slow wheel odometry, right and steady at 4 cm a scan (under the 5 cm bound of the constant-velocity start),
    and one scan taken 21 cm ahead of where the wheels put it, so that the registration jumps 25 cm there. The
    next scan's constant-velocity increment (the jump) disagrees with the wheels; the wheels report what they
    have been reporting all along, so they are not lumpy and ICP starts from them alone: no constant-velocity
    start in the whole run (there were two after the jump, which carried it on)."""
    n, jump = 14, 8
    x = 4.5 + 0.04 * np.arange(n)
    odo = _rooms_odometry(x + np.where(np.arange(n) == jump, 0.21, 0.0), 0.04)
    travelled = odo.poses()[:, 0, 3]
    assert travelled[jump] - travelled[jump - 1] > 0.2  # the registration did jump
    assert odo.alternative_starts == 0


def test_steady_wheel_odometry_is_not_second_guessed():
    """Wheel odometry that is wrong by a steady 40 % (0.12 m per scan where the robot moves 0.2 m) is
    not lumpy: ICP starts from it (0.08 m off, inside its basin), not from the constant-velocity
    increment, which after a corridor slide would carry the slide into the next scan (Freiburg
    hospital). The trajectory still follows the truth, not the wheels."""
    x = 4.5 + 0.2 * np.arange(12)
    odo = _rooms_odometry(x, 0.12)
    assert odo.alternative_starts == 1  # the first step only: no earlier wheel increment to compare with
    travelled = odo.poses()[:, 0, 3]
    np.testing.assert_allclose(travelled, x - x[0], atol=0.03)


def test_a_gap_in_the_log_that_the_wheels_lost_is_bridged_by_the_scaled_constant_velocity():
    """Scans every 0.1 s at 1 m/s, then a 0.5 s gap in the log (UAL Almería has ten of them) across which
    the wheel odometry advanced 2 cm instead of 0.5 m, as if it had stopped integrating. The constant-
    velocity start scaled to the gap (0.5 m, not one scan's 0.1 m) lets ICP follow the scans there; the
    wheel guess is 0.48 m off and the unscaled start 0.4 m, both beyond the deviation bound, which kept
    the wheels' 2 cm. The scan after the gap is one interval away again: its start is scaled back."""
    from evaluation import sim
    from registration.config import IcpConfig, IcpOdometryConfig

    world = sim.load_world("rooms")
    spec = sim.LASER_PRESETS["sick_lms"]
    ang = spec.angles()
    stamps = np.r_[0.1 * np.arange(8), 0.7 + 0.5 + 0.1 * np.arange(4)]
    x = 4.5 + stamps  # 1 m/s
    wheel_x = np.where(stamps > 1.0, x - 0.48, x)  # the gap's motion lost but 2 cm
    truth = np.column_stack([x, np.full(len(x), 3.0), np.zeros(len(x))])
    iy, ix = world.cell_of(truth[:, :2])
    assert world.free[iy, ix].all()
    R = sim.cast_rays(world, truth, spec, rng=np.random.default_rng(5), range_noise=0.01)
    frames = []
    for k in range(len(x)):
        ok = np.isfinite(R[k])
        pts = np.column_stack([R[k][ok] * np.cos(ang[ok]), R[k][ok] * np.sin(ang[ok])])
        frames.append(Frame(stamp=float(stamps[k]), points=pts, index=k, angles=ang, ranges=R[k],
                            odom=geo.xytheta_to_matrix(wheel_x[k], 0.0, 0.0)))
    icp_cfg = IcpConfig(gates_m=(0.3,), max_iterations=30, robust="cauchy", robust_scale_m=0.05, workers=1)
    odo = IcpOdometry(IcpOdometryConfig(icp=icp_cfg, point_to_plane=True, map_voxel_m=0.03,
                                        max_guess_deviation_m=0.3, max_guess_deviation_rad=0.35,
                                        alternative_start_m=0.05, alternative_start_rad=0.05))
    odo.run(frames)
    travelled = odo.poses()[:, 0, 3]
    np.testing.assert_allclose(travelled, x - x[0], atol=0.03)
    # The first step (no earlier wheel increment) and the gap; not the steps after it.
    assert odo.alternative_starts == 2


def _straight_corridor(n: int, step: float, seed: int) -> list[Frame]:
    """A 180° laser (1 cm range noise, 8 m range) driving down the middle of an endless 2 m corridor at
    *step* m per scan, with exact wheel odometry: the walls say nothing about the forward motion."""
    rng = np.random.default_rng(seed)
    ang = np.radians(np.linspace(-90.0, 90.0, 361))
    s = np.sin(ang)
    with np.errstate(divide="ignore"):
        r = np.where(np.abs(s) < 1e-9, np.inf, 1.0 / np.abs(s))
    frames = []
    for k in range(n):
        rk = r + rng.normal(0.0, 0.01, r.shape)
        rk[~(rk <= 8.0)] = np.nan
        ok = np.isfinite(rk)
        pts = np.column_stack([rk[ok] * np.cos(ang[ok]), rk[ok] * np.sin(ang[ok])])
        frames.append(Frame(stamp=0.1 * k, points=pts, index=k, angles=ang, ranges=rk,
                            odom=geo.xytheta_to_matrix(step * k, 0.0, 0.0)))
    return frames


def test_wheel_prior_holds_icp_odometry_in_a_featureless_corridor():
    """In a corridor with nothing along it, range noise alone makes point-to-plane ICP slide forward and
    back by centimetres per scan; with the wheel prediction as a prior in each ICP step
    (``prior_point_sigma``) the per-scan increments follow the (here exact) wheels to a millimetre.
    The first step is left out: with no earlier wheel increment it is judged lumpy and has no prior."""
    from registration.config import IcpConfig, IcpOdometryConfig

    icp_cfg = IcpConfig(gates_m=(0.3,), max_iterations=30, robust="cauchy", robust_scale_m=0.05, workers=1)
    worst = {}
    for prior in (None, 0.5):
        odo = IcpOdometry(IcpOdometryConfig(icp=icp_cfg, point_to_plane=True, map_voxel_m=0.03,
                                            max_guess_deviation_m=0.3, max_guess_deviation_rad=0.35,
                                            alternative_start_m=0.05, alternative_start_rad=0.05,
                                            prior_point_sigma_m=prior))
        odo.run(_straight_corridor(30, 0.2, seed=1))
        worst[prior] = np.abs(np.diff(odo.poses()[:, 0, 3])[1:] - 0.2).max()
    assert worst[0.5] < 1e-3
    assert worst[None] > 0.01


def test_without_wheels_a_correlative_search_places_scans_the_constant_velocity_guess_misses():
    """Scans of a path that stops, turns 25° and starts again (as in logs that kept only some scans): the
    constant-velocity guess is 0.4 m / 25° off at the stop and the turn, beyond ICP's 0.3 m gate, and
    ICP alone ends far from the truth; with the correlative search of ±1 m / ±30° first it ends within
    5 cm and 1° (Olson 2009's scan-to-map matching without odometry)."""
    from tests.loop_scenes import keyframes, room

    xyt = [(2.0 + 0.4 * k, 3.0, 0.0) for k in range(6)] + [(4.0, 3.0, np.radians(25.0))]
    xyt += [(4.0 + 0.4 * k * np.cos(np.radians(25.0)), 3.0 + 0.4 * k * np.sin(np.radians(25.0)), np.radians(25.0))
            for k in range(1, 8)]
    frames = [kf.frame for kf in keyframes(room(), xyt, seed=4)]
    truth = geo.relative(geo.xytheta_to_matrix(*xyt[0]), geo.xytheta_to_matrix(*xyt[-1]))
    errors = {}
    for window in (None, 1.0):
        odo = IcpOdometry(IcpOdometryConfig(icp=IcpConfig(gates_m=(0.3,), max_iterations=30, robust="cauchy", robust_scale_m=0.05),
                                            point_to_plane=True, map_voxel_m=0.03,
                                            unguided_window_m=window, unguided_window_rad=np.radians(30.0)),
                          use_wheel_odometry=False)
        odo.run(frames)
        E = geo.relative(truth, odo.world_T_sensor)
        errors[window] = (np.linalg.norm(E[:2, 3]), abs(np.degrees(geo.matrix_to_xytheta(E)[2])))
    assert errors[1.0][0] < 0.05 and errors[1.0][1] < 1.0
    assert errors[None][0] > 0.3 or errors[None][1] > 5.0


def test_without_wheels_a_turn_beyond_the_window_is_found_by_the_escalated_search():
    """Kept scans of a path that turns 70° in place between two of them (as GMapping keeps a scan per
    0.5 rad turned, and a log may skip more): beyond the ±30° window the best pose scores poorly, below
    0.8 of the recent scans' median, so the search is repeated at every heading over ±2 m and the path
    ends within 5 cm and 1°; without the escalation it does not."""
    from tests.loop_scenes import keyframes, room

    turn = np.radians(70.0)
    xyt = [(2.0 + 0.3 * k, 3.0, 0.0) for k in range(8)] + [(4.1, 3.0, turn)]
    xyt += [(4.1 + 0.3 * k * np.cos(turn), 3.0 + 0.3 * k * np.sin(turn), turn) for k in range(1, 6)]
    frames = [kf.frame for kf in keyframes(room(), xyt, seed=5)]
    truth = geo.relative(geo.xytheta_to_matrix(*xyt[0]), geo.xytheta_to_matrix(*xyt[-1]))
    errors, escalations = {}, {}
    for escalation in (None, 0.8):
        odo = IcpOdometry(IcpOdometryConfig(icp=IcpConfig(gates_m=(0.3,), max_iterations=30, robust="cauchy", robust_scale_m=0.05),
                                            point_to_plane=True, map_voxel_m=0.03,
                                            unguided_window_m=1.0, unguided_window_rad=np.radians(30.0),
                                            unguided_escalation=escalation), use_wheel_odometry=False)
        odo.run(frames)
        E = geo.relative(truth, odo.world_T_sensor)
        errors[escalation] = (np.linalg.norm(E[:2, 3]), abs(np.degrees(geo.matrix_to_xytheta(E)[2])))
        escalations[escalation] = odo.unguided_escalations
    assert errors[0.8][0] < 0.05 and errors[0.8][1] < 1.0, errors
    assert escalations[0.8] >= 1 and escalations[None] == 0
    assert errors[None][0] > 0.3 or errors[None][1] > 5.0, errors
