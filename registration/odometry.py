"""Scan odometry with one interface for two sources: KISS-ICP (:mod:`registration.odometry_kiss`) and our
scan-to-local-map SVD-ICP (here).

Feed :class:`~core.frame.Frame` objects in time order to ``update``; each call returns an
:class:`OdometryStep` with ``world_T_sensor`` (4×4; *world* is the sensor frame of the first scan),
the relative pose ``prev_T_curr`` of this scan in the previous one, and its covariance in the
project tangent convention (``prev_T_curr_true = prev_T_curr · Exp(δ)``, translation first; 3×3
for planar scans, 6×6 for 3D). The covariance treats the map (or the previous scan) as fixed, so
it is the covariance of the pose increment.

When a frame carries wheel odometry (``Frame.odom``) and the odometry was built with
``use_wheel_odometry`` (the default), the
predicted increment ``base_T_sensor⁻¹ · odom_prev⁻¹ · odom_curr · base_T_sensor`` is the initial
guess; otherwise a constant-velocity guess (the last increment) is used.

* :class:`~registration.odometry_kiss.KissOdometry` — KISS-ICP (Vizzo et al., "KISS-ICP: In Defense of Point-to-Point ICP",
  RA-L 2023) through ``kiss_icp.kiss_icp.KissICP``; planar scans become z = 0 points, deskewing off.
  KISS-ICP gives no covariance: it is computed by :func:`registration.alignment.evaluate_alignment` of the
  current scan against the previous one at the KISS pose (plane model, gate 3σ of KISS's threshold).
* :class:`IcpOdometry` — our SVD-ICP (:func:`registration.icp.icp`) of each scan against the union
  of ``map_scans`` scans in the world frame: each joins when the sensor moved ``map_step_m`` or turned
  ``map_step_rad`` since the last that did (0: every scan); a scan registered without the wheel guess
  joins whatever the spacing and matches the last ``unguided_map_scans``.
"""

from __future__ import annotations

import abc
from collections import deque
from dataclasses import dataclass
from typing import Iterable

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core.errors import DegenerateInputError
from core.frame import Frame

from .config import IcpConfig, IcpOdometryConfig
from .icp import icp
from .point_to_plane import PosePrior, icp_point_to_plane
from .target import IcpTarget
from .unguided import UnguidedPlacement
from .voxel import voxel_downsample
from .wheel_lag import WheelSpeeds, wheels_lag

Array = NDArray[np.float64]

#: the constant-velocity start is scaled to the scan interval across a gap (an interval ratio of at least
#: _GAP_RATIO either way, at most _MAX_INTERVAL_RATIO) of regular stamps (_REGULAR_SPREAD, _constant_velocity)
_GAP_RATIO, _MAX_INTERVAL_RATIO, _REGULAR_SPREAD = 2.0, 20.0, 0.25

__all__ = ["OdometryStep", "Odometry", "IcpOdometry", "planar_pose", "wheel_increment"]


@dataclass(frozen=True)
class OdometryStep:
    """The odometry output for one frame (poses 4×4, metres/radians).

    Attributes:
        stamp, index: of the frame.
        world_T_sensor: sensor pose in the world (= first sensor) frame.
        world_T_base: robot base pose, ``world_T_sensor · base_T_sensor⁻¹``.
        prev_T_curr: this sensor pose in the previous one (identity for the first frame).
        covariance: covariance of δ in ``prev_T_curr · Exp(δ)`` (3×3 / 6×6), None for the first frame
            or when it could not be computed.
        accepted: χ² verdict of the registration (None when not tested).
    """

    stamp: float
    index: int
    world_T_sensor: Array
    world_T_base: Array
    prev_T_curr: Array
    covariance: Array | None
    accepted: bool | None = None


def wheel_increment(prev: Frame, curr: Frame) -> Array | None:
    """Sensor motion predicted by wheel odometry between two frames, or None without odometry."""
    if prev.odom is None or curr.odom is None:
        return None
    B = np.asarray(curr.base_T_sensor, dtype=np.float64)
    return geo.inverse(B) @ geo.relative(prev.odom, curr.odom) @ B


def planar_pose(T: Array) -> Array:
    """Project a pose on SE(2) (z = 0, yaw only) — for planar scans fed to a 6-DoF registration."""
    th = np.arctan2(T[1, 0], T[0, 0])
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, 0.0, T[0, 3]], [s, c, 0.0, T[1, 3]], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def _crop(points: Array, min_range: float, max_range: float) -> Array:
    r = np.linalg.norm(points, axis=1)
    return points[(r >= min_range) & (r <= max_range)]


class Odometry(abc.ABC):
    """Common interface: ``update(frame) → OdometryStep``; ``run(frames)`` for a whole log."""

    def __init__(self, use_wheel_odometry: bool = True) -> None:
        #: whether a frame's wheel odometry (``Frame.odom``) predicts its pose: the robot's sensors, not a tuning
        self.use_wheel_odometry = use_wheel_odometry
        self._prev_frame: Frame | None = None
        self._pose = np.eye(4)
        self._last_delta = np.eye(4)
        self._last_dt = 0.0  # the interval (s) the last increment spans
        self._intervals: deque[float] = deque(maxlen=21)  # the last scan intervals (s)
        self.steps: list[OdometryStep] = []

    @property
    def world_T_sensor(self) -> Array:
        """The latest sensor pose (identity before the first frame)."""
        return self._pose.copy()

    def planar_twist(self) -> Array | None:
        """The last increment as a constant twist ``(v_x, v_y, ω)`` per second of the sensor (planar; the
        velocity a scan is deskewed with), None before two frames or after a zero interval."""
        if self._prev_frame is None or self._last_dt <= 0.0:
            return None
        from .deskew import planar_twist

        return planar_twist(self._last_delta, self._last_dt)

    def _guess(self, frame: Frame, use_wheel: bool) -> Array:
        """Predicted ``prev_T_curr``: wheel odometry if allowed and present, else constant velocity."""
        if use_wheel and self._prev_frame is not None:
            inc = wheel_increment(self._prev_frame, frame)
            if inc is not None:
                return inc
        return self._last_delta

    def _emit(self, frame: Frame, pose: Array, cov: Array | None, accepted: bool | None) -> OdometryStep:
        first = self._prev_frame is None
        rel = np.eye(4) if first else geo.relative(self._pose, pose)
        if not first:
            self._last_delta = rel
            self._last_dt = float(frame.stamp - self._prev_frame.stamp)
            self._intervals.append(self._last_dt)
        self._pose = pose
        self._prev_frame = frame
        step = OdometryStep(frame.stamp, frame.index, pose.copy(), pose @ geo.inverse(frame.base_T_sensor),
                            rel, cov, accepted)
        self.steps.append(step)
        return step

    @abc.abstractmethod
    def update(self, frame: Frame) -> OdometryStep:
        """Register one frame (time order) and return its pose and increment covariance."""

    def run(self, frames: Iterable[Frame]) -> list[OdometryStep]:
        """Feed every frame; returns the steps (also kept in ``self.steps``)."""
        return [self.update(f) for f in frames]

    def poses(self, base: bool = False) -> Array:
        """``(N, 4, 4)`` world_T_sensor (or world_T_base) of every frame fed so far."""
        return np.array([s.world_T_base if base else s.world_T_sensor for s in self.steps]).reshape(-1, 4, 4)

    def stamps(self) -> Array:
        return np.array([s.stamp for s in self.steps], dtype=np.float64)


class IcpOdometry(Odometry):
    """SVD-ICP scan-to-local-map odometry; the map is ``map_scans`` scans spaced along the path (world frame)."""

    def _wheel_guided(self, frame: Frame) -> bool:
        return (self.use_wheel_odometry and self._prev_frame is not None and frame.odom is not None
                and self._prev_frame.odom is not None)

    def _too_far(self, guess: Array, pose: Array) -> bool:
        """True when *pose* deviates from its start (the wheel guess, or the constant-velocity one) by more than the configured bounds."""
        c = self.config
        d = geo.relative(guess, pose)
        return bool((c.max_guess_deviation_m is not None and np.linalg.norm(d[:3, 3]) > c.max_guess_deviation_m)
                    or (c.max_guess_deviation_rad is not None
                        and geo.rotation_angle(d[:3, :3]) > c.max_guess_deviation_rad))

    def __init__(self, config: IcpOdometryConfig | None = None, use_wheel_odometry: bool = True) -> None:
        super().__init__(use_wheel_odometry)
        self.config = config or IcpOdometryConfig()
        c = self.config
        # world-frame points of the map scans: the last map_scans of the guided map, of which the unguided map
        # is the last unguided_map_scans
        self._map: deque[Array] = deque(maxlen=max(c.map_scans, c.unguided_map_scans or 0))
        self._map_pose: Array | None = None
        self._target: IcpTarget | None = None  # k-d tree (and normals) of the current map, reused until it changes
        self._target_scans = 0  # how many of the last map scans the target (and the pyramid) hold
        # (world_T_sensor, frame) of each map scan, the frame None without beam geometry (its free space unknown)
        self._map_scans_seen: deque[tuple[Array, Frame | None]] = deque(maxlen=self._map.maxlen)
        self._unguided = UnguidedPlacement(c)  # the search without wheel odometry, on the current map
        self.alternative_starts = 0  # scans that also ran ICP from the constant-velocity start (lumpy wheel odometry)
        self._prev_wheel: tuple[Array, float] | None = None  # previous wheel increment and its interval (s)
        self._wheel_speeds = WheelSpeeds()  # the wheels' typical increment, for the lag test
        g = self.config.first_step_gate_m  # the first registration without wheels: a wider gate first
        self._first_icp = (self.config.icp.model_copy(update={"gates_m": (g,) + tuple(self.config.icp.gates_m)})
                           if g is not None and g > self.config.icp.gates_m[0] else None)

    @property
    def unguided_escalations(self) -> int:
        """Placements without wheel odometry whose search was widened to every heading."""
        return self._unguided.escalations

    @property
    def unguided_contradicted(self) -> int:
        """Widened searches whose best-scoring pose contradicted the local map and was passed over."""
        return self._unguided.contradicted

    def _map_scans(self, guided: bool) -> int:
        """How many of the last map scans form the map of a scan registered with (*guided*) or without the wheel guess."""
        c = self.config
        return c.map_scans if guided or c.unguided_map_scans is None else c.unguided_map_scans

    def _map_points(self, guided: bool) -> Array:
        """World-frame points of the map of a scan registered with (*guided*) or without the wheel guess."""
        n = self._map_scans(guided)
        return np.vstack(list(self._map)[-n:])

    def _constant_velocity(self, dt: float) -> Array:
        """The last estimated increment, scaled to this scan interval of *dt* seconds across a gap in the log
        (or just after one): the interval differs from the last one by ``_GAP_RATIO`` or more, and the
        intervals before the last one are regular (positive, their 10–90 % spread within ``_REGULAR_SPREAD``
        of their median: jittery logger stamps say little about the motion). A scan after a gap is a whole
        gap's motion away, the scan after it one scan's again (docs/ODOMETRY.md has the measured case)."""
        before = list(self._intervals)[:-1]
        ratio = dt / self._last_dt if self._last_dt > 0.0 and dt > 0.0 else 1.0
        if 1.0 / _GAP_RATIO < ratio < _GAP_RATIO or len(before) < 5:
            return self._last_delta
        lo, med, hi = np.percentile(np.asarray(before), [10, 50, 90])
        if lo <= 0.0 or hi - lo > _REGULAR_SPREAD * med:
            return self._last_delta
        return geo.se3_exp(geo.se3_log(self._last_delta) * min(ratio, _MAX_INTERVAL_RATIO))

    def _alternative_start(self, frame: Frame, prediction: Array) -> Array | None:
        """The constant-velocity increment (scaled to this scan interval) when the wheel odometry is
        lumpy here, else None: the wheel prediction disagrees by more than the configured bounds with
        it, and it lags the scans (:func:`~registration.wheel_lag.wheels_lag`, against its typical
        increment over the last scans too) or differs as much from the previous wheel increment (scaled
        to this scan interval). Wheel odometry that lost a gap of the log (the wheel
        pose barely moved while the scans did) is lumpy in this sense.

        The second test keeps smooth wheel odometry in charge: after an ICP slide along a corridor the
        last increment disagrees with the wheels too, and starting from it again fed the slide
        (docs/ODOMETRY.md has the measured case)."""
        c = self.config
        prev_wheel, self._prev_wheel = self._prev_wheel, None
        if not self._wheel_guided(frame) or (c.alternative_start_m is None and c.alternative_start_rad is None):
            self._wheel_speeds.clear()
            return None
        dt = frame.stamp - self._prev_frame.stamp
        self._prev_wheel = (prediction, dt)
        typical = self._wheel_speeds.typical(dt)
        self._wheel_speeds.append(prediction, dt)
        constant_velocity = self._constant_velocity(dt)
        if not self._disagree(prediction, constant_velocity):
            return None
        lags = wheels_lag(prediction, constant_velocity, c.alternative_start_m, c.alternative_start_rad, typical)
        if not lags and prev_wheel is not None and prev_wheel[1] > 0 and dt > 0:
            expected = geo.se3_exp(geo.se3_log(prev_wheel[0]) * (dt / prev_wheel[1]))
            if not self._disagree(prediction, expected):
                return None  # the wheels move as they did: they are not lumpy here
        return constant_velocity

    def _disagree(self, a: Array, b: Array) -> bool:
        """Increments *a* and *b* differ by more than ``alternative_start_m`` or ``alternative_start_rad``."""
        c = self.config
        d = geo.relative(a, b)
        return bool((c.alternative_start_m is not None and np.linalg.norm(d[:3, 3]) > c.alternative_start_m)
                    or (c.alternative_start_rad is not None and geo.rotation_angle(d[:3, :3]) > c.alternative_start_rad))

    def _prefer_alternative(self, res, start: Array, res_alt, alt_start: Array, guided: bool,  # type: ignore[no-untyped-def]
                            planar: bool) -> bool:
        """Whether the result from the constant-velocity start replaces the one from the wheel start:
        when only it stayed within the bounds around its own start, or (both or neither did) when its
        inlier fraction is clearly larger (``alternative_start_min_gain``)."""
        if res_alt is None:
            return False
        if res is None:
            return True
        if guided:
            flat = planar_pose if planar else (lambda T: T)
            inside, inside_alt = (not self._too_far(start, flat(res.transform)),
                                  not self._too_far(alt_start, flat(res_alt.transform)))
            if inside != inside_alt:
                return inside_alt
        return res_alt.fitness >= res.fitness + self.config.alternative_start_min_gain

    def _align(self, pts: Array, target: IcpTarget, start: Array, prior: PosePrior | None = None,
               icp_config: IcpConfig | None = None):  # type: ignore[no-untyped-def]
        """ICP result from *start* (with the *prior*, point-to-plane only), or None when there are too few pairs."""
        cfg = self.config
        try:
            if cfg.point_to_plane:
                return icp_point_to_plane(pts, target, start, icp_config or cfg.icp, prior=prior)
            return icp(pts, target, start, icp_config or cfg.icp)
        except DegenerateInputError:
            return None

    def _prior(self, pose: Array, increment: Array, dim: int) -> PosePrior | None:
        """The wheel prediction *pose* (world_T_sensor) as a prior, its σ from the *increment*'s length and turn."""
        c = self.config
        if c.prior_point_sigma_m is None or not c.point_to_plane:
            return None
        d = float(np.linalg.norm(increment[:3, 3]))
        turn = geo.rotation_angle(increment[:3, :3])
        s_t = c.prior_sigma_m + c.prior_sigma_per_m * d
        s_r = c.prior_sigma_rad + c.prior_sigma_rad_per_m * d + c.prior_sigma_rad_per_rad * turn
        n_r = 1 if dim == 2 else 3
        return PosePrior(pose, np.diag([(c.prior_point_sigma_m / s_t) ** 2] * dim + [(c.prior_point_sigma_m / s_r) ** 2] * n_r))

    def update(self, frame: Frame) -> OdometryStep:
        cfg = self.config
        pts = _crop(frame.points, cfg.min_range_m, cfg.max_range_m)
        if self._prev_frame is None:
            self._map.append(voxel_downsample(pts, cfg.map_voxel_m))
            self._map_scans_seen.append((np.eye(4), frame if frame.ranges is not None else None))
            self._map_pose = np.eye(4)
            return self._emit(frame, np.eye(4), None, None)
        prediction = self._guess(frame, self.use_wheel_odometry)
        guess = self._pose @ prediction
        guided = self._wheel_guided(frame)
        scans = self._map_scans(guided)
        if self._target is None or self._target_scans != scans:
            self._target = IcpTarget(self._map_points(guided), None, cfg.icp.normal_neighbors, cfg.icp.workers)
            self._target_scans = scans
            self._unguided.reset()
        target = self._target
        if not guided and frame.is_planar and cfg.unguided_window_m is not None:
            seen = [(p, f) for p, f in list(self._map_scans_seen)[-self._map_scans(False):] if f is not None]
            guess = self._unguided.place(pts, frame, guess, self._pose, lambda: self._map_points(False), seen)
        alt = self._alternative_start(frame, prediction)
        # The wheels as a prior only where they are smooth: lumpy ones are a wrong guess.
        prior = self._prior(guess, prediction, frame.dim) if guided and alt is None else None
        first = self._first_icp if not guided and len(self.steps) == 1 else None  # no increment estimated yet
        res = self._align(pts, target, guess, prior, first)
        if alt is not None:
            self.alternative_starts += 1
            start = self._pose @ alt
            res_alt = self._align(pts, target, start)
            if self._prefer_alternative(res, guess, res_alt, start, guided, frame.is_planar):
                res, guess = res_alt, start
        cov = accepted = None
        if res is None:
            pose = guess  # too few pairs (e.g. an empty scan): dead-reckon on the guess
        else:
            pose, cov, accepted = res.transform, res.covariance, res.accepted if cfg.icp.sigma_m else None
        if frame.is_planar:
            pose = planar_pose(pose)
        if guided and res is not None and self._too_far(guess, pose):
            # ICP left the basin of its own start. Judged against either start, a slide along a
            # corridor passed and fed the next constant-velocity start (docs/ODOMETRY.md).
            pose, cov, accepted = guess, None, False
        moved = geo.relative(self._map_pose, pose)
        turned = geo.rotation_angle(moved[:3, :3])
        if (not guided and cfg.unguided_map_scans is not None) or (
                cfg.map_step_m == 0.0 or np.linalg.norm(moved[:3, 3]) >= cfg.map_step_m or turned >= cfg.map_step_rad):
            self._map.append(geo.transform_points(pose, voxel_downsample(pts, cfg.map_voxel_m)))
            self._map_scans_seen.append((pose, frame if frame.ranges is not None else None))
            self._map_pose = pose
            self._target = None
            self._unguided.reset()
        return self._emit(frame, pose, cov, accepted)
