"""Deskewing a planar scan (registration.deskew) and the front end that uses it.

Properties: a scan cast while the sensor moves, corrected with the true twist, lies on the world's walls
as seen from the pose at the middle of its sweep (without the correction it does not); the twist of an increment is its
logarithm over the interval (round trip through the exponential); and a front end turning in place with
a slow laser is short of the turn by the closed-form fraction ω·s / (1 + ω·s) without deskewing, and
within a small fraction of it with.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core import geometry as geo
from core.frame import Frame
from registration.deskew import deskew_planar, planar_twist, sweep_times
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


def _moving_scan(world_T_stamp: np.ndarray, twist: np.ndarray, stamp: float = 0.0, index: int = 0, n: int = 682) -> Frame:
    """The scan a laser sweeping counter-clockwise over 240° in 2/3 of a revolution measures while its
    sensor moves with the constant *twist* from *world_T_stamp* (beam i from the pose at its own time)."""
    angles = np.linspace(-_FOV / 2, _FOV / 2, n)
    times = sweep_times(angles, _REVOLUTION_S)
    poses = world_T_stamp @ _exp(twist, times)
    heading = np.arctan2(poses[:, 1, 0], poses[:, 0, 0]) + angles
    ranges = _cast(poses[:, :2, 3], heading)
    pts = np.column_stack([ranges * np.cos(angles), ranges * np.sin(angles)])
    return Frame(stamp=stamp, points=pts, index=index, angles=angles, ranges=ranges,
                 no_return=np.zeros(n, bool), beam_times=times, max_range=30.0)


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


def test_a_frame_without_beam_times_is_left_as_it_is():
    scan = _moving_scan(np.eye(4), np.array([0.0, 0.0, 1.0]))
    plain = Frame(stamp=0.0, points=scan.points, angles=scan.angles, ranges=scan.ranges, no_return=scan.no_return)
    assert deskew_planar(plain, np.array([1.0, 0.0, 2.0])) is plain


@pytest.mark.parametrize("seed", range(4))
def test_planar_twist_is_the_logarithm_over_the_interval(seed):
    rng = np.random.default_rng(seed)
    twist = rng.normal(0.0, [0.8, 0.3, 1.5])
    dt = float(rng.uniform(0.02, 0.3))
    np.testing.assert_allclose(planar_twist(_exp(twist, np.array([dt]))[0], dt), twist, atol=1e-9)


def _turn_in_place(deskew: bool, rate: float = 1.2, scans: int = 26, dt: float = 0.1, *, untimed: bool = False) -> float:
    """Heading (rad) the front end ends at after turning in place at *rate* rad/s for *scans* scans; with
    *untimed* the frames carry no beam times (a CARMEN log) and the configuration gives the revolution."""
    odometry = {"deskew": deskew, "use_wheel_odometry": False}
    if untimed:
        odometry["laser_revolution_s"] = _REVOLUTION_S
    config = SlamConfig.model_validate({"odometry": odometry})
    front = FrontEnd(config, make_odometry(config, planar=True))
    twist = np.array([0.0, 0.0, rate])
    for k in range(scans):
        scan = _moving_scan(_pose(0.3, -0.2, rate * k * dt), twist, stamp=k * dt, index=k)
        front.process(dataclasses.replace(scan, beam_times=None) if untimed else scan)
    last = front.track.odom_poses[-1]
    return float(np.arctan2(last[1, 0], last[0, 0]))


def test_the_front_end_no_longer_comes_short_of_a_turn():
    rate, scans, dt = 1.2, 26, 0.1
    truth = rate * (scans - 1) * dt
    kappa = rate * _REVOLUTION_S / (2 * np.pi)  # the sweep's seconds per radian times the turn rate
    short_raw = truth - _turn_in_place(False, rate, scans, dt)
    short_fixed = truth - _turn_in_place(True, rate, scans, dt)
    # A scan taken while turning is compressed by 1 / (1 + κ): every turn comes short by κ / (1 + κ).
    assert short_raw == pytest.approx(truth * kappa / (1 + kappa), rel=0.35)
    assert abs(short_fixed) < 0.15 * short_raw
    # The same from the configured revolution when the log records no beam times.
    assert abs(truth - _turn_in_place(True, rate, scans, dt, untimed=True)) < 0.15 * short_raw
