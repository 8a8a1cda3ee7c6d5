"""Deskewing a planar scan (registration.deskew) and the front end that uses it.

Properties: a scan cast while the sensor moves, corrected with the true twist, lies on the world's walls
as seen from the pose at the middle of its sweep (without the correction it does not); the sweep check
reads from the scans which way their beams were taken; the twist of an increment is its
logarithm over the interval (round trip through the exponential); a front end turning in place with
a slow laser is short of the turn by the closed-form fraction ω·s / (1 + ω·s) without deskewing, and
within a small fraction of it with; and the poses it reports are the sensor's at the scans' stamps, not
half a sweep later where it registers them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core import geometry as geo
from core.frame import Frame
from registration.deskew import deskew_planar, middle_T_stamp, planar_twist, seen_from, sweep_middle_s, sweep_times
from registration.sweep_check import SweepCheck
from slam.pipeline.config import SlamConfig
from slam.pipeline.frontend import FrontEnd
from slam.pipeline.odometry_source import make_odometry

# A 9 m × 7 m room with a pillar and a cabinet: wall segments (x0, y0, x1, y1).
_WALLS = np.array([
    (-4.5, -3.5, 4.5, -3.5), (4.5, -3.5, 4.5, 3.5), (4.5, 3.5, -4.5, 3.5), (-4.5, 3.5, -4.5, -3.5),
    (1.0, 1.0, 1.6, 1.0), (1.6, 1.0, 1.6, 1.6), (1.6, 1.6, 1.0, 1.6), (1.0, 1.6, 1.0, 1.0),
    (-3.0, -2.0, -1.0, -2.6), (-1.0, -2.6, -0.8, -2.0), (2.5, -1.0, 3.6, 0.4),
])
_FOV = np.radians(240.0)
_REVOLUTION_S = 0.1  # a Hokuyo URG-04LX


def _cast(origins: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """Range of each ray (origin (N, 2), world heading (N,)) to the nearest wall."""
    d = np.column_stack([np.cos(headings), np.sin(headings)])[:, None, :]
    a, b = _WALLS[None, :, :2], _WALLS[None, :, 2:]
    e = b - a
    o = origins[:, None, :]
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    w = a - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / den
        u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / den
    t = np.where((np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1), t, np.inf)
    return t.min(axis=1)


def _distance_to_walls(p: np.ndarray) -> np.ndarray:
    a, b = _WALLS[None, :, :2], _WALLS[None, :, 2:]
    e = b - a
    s = np.clip(np.einsum("nkd,nkd->nk", p[:, None, :] - a, e) / np.einsum("nkd,nkd->nk", e, e), 0.0, 1.0)
    return np.linalg.norm(p[:, None, :] - (a + s[..., None] * e), axis=2).min(axis=1)


def _pose(x: float, y: float, th: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
    T[:2, 3] = x, y
    return T


def _exp(twist: np.ndarray, t: np.ndarray) -> np.ndarray:
    z = np.zeros_like(t)
    return geo.se3_exp(np.column_stack([twist[0] * t, twist[1] * t, z, z, z, twist[2] * t]))


def _moving_scan(world_T_stamp: np.ndarray, twist: np.ndarray, stamp: float = 0.0, index: int = 0, n: int = 682,
                 mirror: str = "ccw") -> Frame:
    """The scan a laser sweeping over 240° in 2/3 of a revolution measures while its sensor moves with the
    constant *twist* from *world_T_stamp* (beam i from the pose at its own time). The frame lists the beams
    by increasing angle with times i·increment, as a ROS driver does; *mirror* says how they were really
    taken: ``ccw`` in that order, ``cw`` the other way round (what the rplidar_ros driver publishes),
    ``instant`` all at the stamp."""
    angles = np.linspace(-_FOV / 2, _FOV / 2, n)
    listed = sweep_times(angles, _REVOLUTION_S)
    taken = {"ccw": listed, "cw": listed[::-1], "instant": np.zeros(n)}[mirror]
    poses = world_T_stamp @ _exp(twist, taken)
    heading = np.arctan2(poses[:, 1, 0], poses[:, 0, 0]) + angles
    ranges = _cast(poses[:, :2, 3], heading)
    pts = np.column_stack([ranges * np.cos(angles), ranges * np.sin(angles)])
    return Frame(stamp=stamp, points=pts, index=index, angles=angles, ranges=ranges,
                 no_return=np.zeros(n, bool), beam_times=listed, max_range=30.0)


def test_sweep_times_are_the_share_of_a_revolution():
    a = np.linspace(-np.pi / 2, np.pi / 2, 181)
    t = sweep_times(a, 0.04)
    assert t[0] == 0.0 and t[-1] == pytest.approx(0.02) and np.all(np.diff(t) > 0)


@pytest.mark.parametrize("twist", [(0.0, 0.0, 1.5), (0.8, 0.0, 0.0), (1.2, -0.1, -2.0)])
def test_a_deskewed_scan_lies_on_the_walls_seen_from_mid_sweep(twist):
    twist = np.asarray(twist, float)
    start = _pose(-0.7, 0.4, 0.3)
    scan = _moving_scan(start, twist)
    middle = start @ _exp(twist, np.array([0.5 * scan.beam_times[-1]]))[0]  # the pose at mid-sweep
    # Read as if every beam were measured at mid-sweep, the skewed scan misses the walls by ω·t·r or v·t.
    raw = _distance_to_walls(geo.transform_points(middle, np.column_stack([scan.points, np.zeros(len(scan.points))]))[:, :2])
    fixed = deskew_planar(scan, twist)
    world = geo.transform_points(middle, np.column_stack([fixed.points, np.zeros(len(fixed.points))]))[:, :2]
    assert np.max(_distance_to_walls(world)) < 1e-9
    assert np.max(raw) > 0.02
    # The beams say the same as the points (mapping reads the beams), and the times are spent.
    np.testing.assert_allclose(fixed.ranges * np.cos(fixed.angles), fixed.points[:, 0], atol=1e-12)
    assert not np.any(fixed.beam_times)
    assert deskew_planar(fixed, np.zeros(3)).points == pytest.approx(fixed.points)


@pytest.mark.parametrize("twist", [(0.0, 0.0, 1.5), (0.8, 0.0, 0.0), (1.2, -0.1, -2.0)])
def test_the_pose_at_mid_sweep_taken_back_to_the_stamp_sees_the_scan_deskewed_to_the_stamp(twist):
    """The pose registered at mid-sweep times ``middle_T_stamp`` is the true pose at the stamp (half a
    sweep earlier), and the deskewed scan seen from there lies on the walls."""
    twist = np.asarray(twist, float)
    start = _pose(-0.7, 0.4, 0.3)
    scan = _moving_scan(start, twist)
    assert sweep_middle_s(scan.beam_times) == pytest.approx(0.5 * scan.beam_times[-1])
    middle = start @ _exp(twist, np.array([sweep_middle_s(scan.beam_times)]))[0]
    np.testing.assert_allclose(middle @ middle_T_stamp(scan, twist), start, atol=1e-12)
    at_stamp = seen_from(deskew_planar(scan, twist), np.linalg.inv(middle_T_stamp(scan, twist)))
    world = geo.transform_points(start, np.column_stack([at_stamp.points, np.zeros(len(at_stamp.points))]))[:, :2]
    assert np.max(_distance_to_walls(world)) < 1e-9
    np.testing.assert_allclose(at_stamp.ranges * np.cos(at_stamp.angles), at_stamp.points[:, 0], atol=1e-12)
    np.testing.assert_allclose(at_stamp.ranges * np.sin(at_stamp.angles), at_stamp.points[:, 1], atol=1e-12)


def test_a_frame_without_beam_times_is_left_as_it_is():
    scan = _moving_scan(np.eye(4), np.array([0.0, 0.0, 1.0]))
    plain = Frame(stamp=0.0, points=scan.points, angles=scan.angles, ranges=scan.ranges, no_return=scan.no_return)
    assert deskew_planar(plain, np.array([1.0, 0.0, 2.0])) is plain
    np.testing.assert_array_equal(middle_T_stamp(plain, np.array([1.0, 0.0, 2.0])), np.eye(4))


@pytest.mark.parametrize("seed", range(4))
def test_planar_twist_is_the_logarithm_over_the_interval(seed):
    rng = np.random.default_rng(seed)
    twist = rng.normal(0.0, [0.8, 0.3, 1.5])
    dt = float(rng.uniform(0.02, 0.3))
    np.testing.assert_allclose(planar_twist(_exp(twist, np.array([dt]))[0], dt), twist, atol=1e-9)


_SCANS, _FROM, _DT = 60, 30, 0.1  # the sweep check decides after its 20th pair; turns measured from scan 30


def _rates(steady: bool) -> np.ndarray:
    """Turn rate (rad/s) during each scan: 1.2 throughout, or 0.6 and 1.8 by turns, five scans each (the
    sweep check needs scans whose twists differ)."""
    k = np.arange(_SCANS)
    return np.full(_SCANS, 1.2) if steady else np.where((k // 5) % 2 == 0, 0.6, 1.8)


def _turn_in_place(deskew: bool = True, *, mirror: str = "ccw", untimed: bool = False, force: str | None = None,
                   steady: bool = False) -> tuple[float, float, str | None]:
    """Turning in place: the front end's heading change from scan _FROM to the last, the true one, and the
    sweep check's verdict. *untimed*: the frames carry no beam times (a CARMEN log) and the configuration
    gives the revolution; *force*: the verdict set beforehand instead of read."""
    odometry = {"deskew": deskew, "use_wheel_odometry": False}
    if untimed:
        odometry["laser_revolution_s"] = _REVOLUTION_S
    config = SlamConfig.model_validate({"odometry": odometry})
    front = FrontEnd(config, make_odometry(config, planar=True))
    front.sweep.verdict = force
    rates = _rates(steady)
    heading_at = np.concatenate([[0.0], np.cumsum(rates * _DT)])
    for k in range(_SCANS):
        scan = _moving_scan(_pose(0.3, -0.2, heading_at[k]), np.array([0.0, 0.0, rates[k]]), stamp=k * _DT,
                            index=k, mirror=mirror)
        front.process(dataclasses.replace(scan, beam_times=None) if untimed else scan)
    heading = np.unwrap([np.arctan2(P[1, 0], P[0, 0]) for P in front.track.odom_poses])
    return float(heading[-1] - heading[_FROM]), float(heading_at[_SCANS - 1] - heading_at[_FROM]), front.sweep.verdict


def test_the_front_end_reports_each_pose_at_its_scans_stamp():
    """Turning in place at 0.6 and 1.8 rad/s by turns: a pose registered at mid-sweep is ω·(half a sweep)
    ahead of the stamp, 0.04 rad more at 1.8 than at 0.6 rad/s for this laser, which a reference at the
    stamps reads as error. The front end takes each pose back to its stamp: the heading error (against the
    truth at the stamps, from scan _FROM on) is the same at both rates to within a small fraction of that
    (the median per rate: the first scan after a change is deskewed with the last rate, in any reading)."""
    config = SlamConfig.model_validate({"odometry": {"use_wheel_odometry": False}})
    front = FrontEnd(config, make_odometry(config, planar=True))
    front.sweep.verdict = "listed"
    rates = _rates(steady=False)
    heading_at = np.concatenate([[0.0], np.cumsum(rates * _DT)])
    for k in range(_SCANS):
        front.process(_moving_scan(_pose(0.3, -0.2, heading_at[k]), np.array([0.0, 0.0, rates[k]]), stamp=k * _DT, index=k))
    heading = np.unwrap([np.arctan2(P[1, 0], P[0, 0]) for P in front.track.odom_poses])
    err = (heading - heading_at[:_SCANS])[_FROM:]
    fast = rates[_FROM:] > 1.0
    lag = (1.8 - 0.6) * 0.5 * sweep_times(np.linspace(-_FOV / 2, _FOV / 2, 682), _REVOLUTION_S)[-1]
    assert lag == pytest.approx(0.04, rel=0.01)
    assert abs(np.median(err[fast]) - np.median(err[~fast])) < 0.15 * lag


def test_a_steady_turn_comes_short_by_the_closed_form_fraction():
    """A scan taken while turning at a steady ω is compressed by 1 / (1 + κ), κ = ω · the sweep's seconds
    per radian: registered without deskewing, every turn comes short by κ / (1 + κ)."""
    turned, truth, _ = _turn_in_place(False, steady=True)
    kappa = 1.2 * _REVOLUTION_S / (2 * np.pi)
    assert truth - turned == pytest.approx(truth * kappa / (1 + kappa), rel=0.35)


def test_deskewed_with_the_right_reading_a_turn_comes_out_right():
    """With the beam times read as the scans were taken (the check's verdict set beforehand: a steady turn
    gives it nothing to read, see the next tests), the shortfall is gone; the same from the configured
    revolution when the log records no beam times."""
    turned, truth, _ = _turn_in_place(False, steady=True)
    short_raw = truth - turned
    for untimed in (False, True):
        turned, truth, _ = _turn_in_place(force="listed", steady=True, untimed=untimed)
        assert abs(truth - turned) < 0.15 * short_raw


def test_read_against_the_mirror_the_error_doubles():
    """A clockwise mirror whose driver lists the beams by increasing angle, times counted from the first
    listed (what the rplidar_ros and ydlidar drivers publish): the scan is stretched, the turn comes out
    long; deskewed with the log's times, twice as long; with the times reversed, right."""
    turned, truth, _ = _turn_in_place(False, mirror="cw", steady=True)
    long_raw = turned - truth
    assert long_raw > 0.02
    blind, truth, _ = _turn_in_place(mirror="cw", force="listed", steady=True)
    assert blind - truth == pytest.approx(2 * long_raw, rel=0.35)
    turned, truth, _ = _turn_in_place(mirror="cw", force="reversed", steady=True)
    assert abs(turned - truth) < 0.15 * long_raw


def _check(mirror: str, rates: np.ndarray, dt: float = 0.1) -> SweepCheck:
    """A sweep check fed scans taken turning in place at piecewise *rates* (rad/s), with their true poses."""
    check = SweepCheck()
    heading_at = np.concatenate([[0.0], np.cumsum(rates * dt)])
    for k, rate in enumerate(rates):
        pose = _pose(0.3, -0.2, heading_at[k])
        check.add(_moving_scan(pose, np.array([0.0, 0.0, rate]), stamp=k * dt, index=k, mirror=mirror), pose)
    return check


@pytest.mark.parametrize(("mirror", "verdict"), [("ccw", "listed"), ("cw", "reversed"), ("instant", "none")])
def test_the_sweep_check_reads_which_way_the_beams_were_taken(mirror, verdict):
    """Turning by turns at 0.6 and 1.8 rad/s, the check tells beams taken as listed, against the list,
    or all at once (a driver that states times for a scan taken at once)."""
    k = np.arange(60)
    check = _check(mirror, np.where((k // 5) % 2 == 0, 0.6, 1.8))
    assert check.verdict == verdict and check.pairs == 20


def test_a_steady_turn_gives_the_sweep_check_nothing_to_read():
    """Two scans compressed alike match up to a rotation: a steady turn leaves every pair out."""
    check = _check("ccw", np.full(60, 1.2))
    assert check.verdict is None and check.pairs == 0


@pytest.mark.parametrize(("sensor", "verdict"), [("hokuyo_urg04lx", "listed"), ("rplidar_a2", "reversed")])
def test_the_front_end_reads_the_beam_times_of_simulated_lasers(sensor, verdict):
    """On a simulated tour (the simulator's own motion, wheel odometry and noise), the front end reads a
    URG-04LX's beam times as listed and a clockwise RPLIDAR's, listed against its mirror by its driver, as
    reversed, before it deskews with them."""
    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.simulate import simulate

    sim = simulate(load_world("rooms", seed=2), n_scans=300, spec=LASER_PRESETS[sensor], seed=2)
    config = SlamConfig()
    front = FrontEnd(config, make_odometry(config, planar=True))
    for frame in sim.frames():
        front.process(frame)
        if front.sweep.verdict is not None:
            break
    assert front.sweep.verdict == verdict


def test_the_beam_time_order_is_read_before_the_run():
    """The frame loop reads the order from the log's opening scans before the run proper (so that no scan
    of the run is registered with one reading and a later one with another), feeds those scans again,
    and a log without beam times is not held up: one frame read, the configuration as it was."""
    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.simulate import simulate
    from slam.pipeline.beam_times import read_beam_time_order
    from slam.pipeline.front_process import run_front_end

    sim = simulate(load_world("rooms", seed=2), n_scans=300, spec=LASER_PRESETS["rplidar_a2"], seed=2)
    config = SlamConfig.model_validate({"stage_processes": False})
    frames = iter(sim.frames())
    fixed, head, stats = read_beam_time_order(frames, config)
    assert fixed.odometry.beam_time_order == "reversed" and config.odometry.beam_time_order == "auto"
    assert len(head) == stats["beam_time_scans_read"] < 300 and stats["beam_times"] == "reversed"
    assert [f.index for f in head] == list(range(len(head))) and next(frames).index == len(head)

    summary = run_front_end(sim.frames(), config, lambda *kf: None)
    assert len(summary.track.stamps) == 300 and summary.stats["beam_times"] == "reversed"

    untimed = iter(dataclasses.replace(f, beam_times=None) for f in sim.frames())
    same, head, stats = read_beam_time_order(untimed, config)
    assert same is config and len(head) == 1 and stats == {}


def test_a_simulated_rplidars_poses_do_not_lag_half_a_sweep():
    """A simulated tour with an RPLIDAR A2 (10 Hz, its beams over the whole 0.1 s revolution; the simulator's
    truth is at the stamps): a pose registered at mid-sweep and written at the stamp would make each step's
    heading error follow the change of turn rate into it, by half the sweep (0.05 s; the front end before
    2026-11-28: 0.041 s). Taken back to the stamp, the fitted coefficient stays under a fifth of that."""
    from evaluation.sim import LASER_PRESETS, load_world
    from evaluation.sim.simulate import simulate
    from slam.pipeline.front_process import run_front_end

    sim = simulate(load_world("rooms", seed=2), n_scans=600, spec=LASER_PRESETS["rplidar_a2"], seed=2)
    summary = run_front_end(sim.frames(), SlamConfig.model_validate({"stage_processes": False}), lambda *kf: None)
    assert summary.stats["beam_times"] == "reversed"
    P = np.array(summary.track.odom_poses)
    heading = np.unwrap(np.arctan2(P[:, 1, 0], P[:, 0, 0]))
    truth = np.unwrap(np.arctan2(sim.ground_truth[:, 1, 0], sim.ground_truth[:, 0, 0]))
    rate = np.diff(truth) / np.diff(sim.stamps)
    step_error = np.diff(heading) - np.diff(truth)
    rate_change = np.r_[0.0, np.diff(rate)]
    later = slice(300, None)  # after the sweep check has read the order and the map has settled
    coefficient = np.polyfit(rate_change[later], step_error[later], 1)[0]
    assert abs(coefficient) < 0.2 * 0.05
