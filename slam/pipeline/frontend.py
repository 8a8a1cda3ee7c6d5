"""Front end: per-scan odometry, keyframe selection and the odometry edges between keyframes.

Poses here are robot-base poses ``world_T_base`` (4×4). The odometry source registers sensor
frames; ``base_T_sensor`` converts. Each odometry edge's covariance is the registration
covariance σ²(∂²f/∂x²)⁻¹ of the keyframe's scan against the previous keyframe's scan at the
odometry's relative pose (:func:`registration.alignment.evaluate_alignment`, plane model, a-priori σ),
the same for KISS-ICP and our ICP, scaled up by the a-posteriori variance factor σ̂²/σ² when the
scan fits worse than σ (config ``odometry.edge_sigma_from_residuals``), plus a noise floor growing
with the motion (config ``odometry.floor_*``) because that covariance treats the previous scan as
exact. When the edge cannot be evaluated (too few overlapping points) the per-scan covariances
compounded along the way (:func:`core.geometry.compound_covariance`) are used instead.
A registration edge (2D) that no wheel edge backs, or whose smooth wheels disagree with it, also carries
how far it may have slid: the second moment of the poses that score as well on the keyframe-to-keyframe
correlative surface (config ``odometry.edge_ambiguity_*``; Olson 2009; docs/LOOP_CLOSURE.md, "How far a
step without wheels may have slid"). Its Fisher information does not say so: along a corridor whose far
end lies beyond the laser's range a few points at a door jamb pin it to centimetres, while scan-to-map
odometry there can hold still for dozens of scans beside wheels that report steady motion; the wheel
edge beside it holds the step only once the registration edge admits the slide (docs/LOOP_CLOSURE.md,
"A registration that holds still in a corridor").

Wheel odometry, when the log has it, gives a second edge per keyframe interval, its noise model
calibrated online against the registration (:mod:`slam.noise_scale`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from core.errors import DegenerateInputError
from core.frame import Frame
from registration import correlative
from registration.alignment import evaluate_alignment
from registration.config import IcpConfig
from registration.deskew import deskew_planar, middle_T_stamp, seen_from
from registration.sweep_check import SweepCheck, as_read
from registration.odometry import Odometry, OdometryStep
from registration.target import IcpTarget
from registration.voxel import voxel_downsample
from slam.keyframes import Keyframe, KeyframeSelector

from .beam_times import timed_frame
from .config import SlamConfig
from slam.noise_scale import NoiseScaleCalibration

Array = NDArray[np.float64]


@dataclass
class OdometryEdge:
    """Relative pose ``i_T_j`` between consecutive keyframes (base frames) and its covariance."""

    i: int
    j: int
    measurement: Array
    covariance: Array
    wheels: bool = False  # wheel odometry measured this step too (its edge may still have been left out as lumpy)


@dataclass
class WheelEdge:
    """Relative pose ``i_T_j`` of the robot base between two keyframes from wheel odometry alone."""

    i: int
    j: int
    measurement: Array
    covariance: Array


class EdgeCovariance(NamedTuple):
    """A keyframe edge's registration covariance (base frame): *posterior* scaled by the a-posteriori
    variance factor (the edge's), *prior* at the a-priori point σ (the wheel gate's)."""

    posterior: Array
    prior: Array


@dataclass
class ScanTrack:
    """Per-scan bookkeeping to give every scan a pose after optimisation."""

    stamps: list[float] = field(default_factory=list)
    odom_poses: list[Array] = field(default_factory=list)  # world_T_base from the odometry source
    wheel_poses: list[Array | None] = field(default_factory=list)  # raw wheel odometry, if the log has it
    keyframe: list[int] = field(default_factory=list)  # id of the latest keyframe at or before the scan


class FrontEnd:
    """Feeds frames to an odometry source and emits keyframes and odometry edges."""

    def __init__(self, config: SlamConfig, odometry: Odometry, keep_keyframes: bool = True) -> None:
        """*keep_keyframes* False keeps only the latest keyframe (a front-end process that hands each over)."""
        self.config = config
        self.odometry = odometry
        self.selector = KeyframeSelector(config.keyframes)
        self.keyframes: list[Keyframe] = []  # every keyframe, with keep_keyframes
        self._keep = keep_keyframes
        self._last: Keyframe | None = None
        self._count = 0
        self.track = ScanTrack()
        self._cov_since_kf: Array | None = None
        self._dof: int | None = None
        self.wheel_edges: list[WheelEdge] = []
        self.wheel_edges_dropped = 0
        self.slid_edges = 0  # odometry edges that carry a slide (registration alone, a second pose as good)
        self.max_slide_m = 0.0  # the largest σ along a slide among them
        self.wheel_calibration: NoiseScaleCalibration | None = None  # created with the first wheel edge
        self._lumpy_since_kf = False  # the odometry took its constant-velocity start since the last keyframe
        self._field: tuple[int, correlative.LikelihoodPyramid] | None = None  # (keyframe id, its likelihood field)
        self.sweep = SweepCheck()  # which way the beam times run, read from the scans before deskewing with them
        if config.odometry.beam_time_order != "auto":  # set, or read before the run (slam.pipeline.beam_times)
            self.sweep.verdict = config.odometry.beam_time_order

    def latest_wheel_edge(self, kf: Keyframe) -> WheelEdge | None:
        """The wheel-odometry edge ending at keyframe *kf*, if the log has wheel odometry."""
        if self.wheel_edges and self.wheel_edges[-1].j == kf.id:
            return self.wheel_edges[-1]
        return None

    def _diagonal(self, var_translation: float, var_rotation: float) -> Array:
        """Diagonal covariance in the (translation, rotation) tangent order of this log's dimension."""
        n_t = 2 if self._dof == 3 else 3
        return np.diag([var_translation] * n_t + [var_rotation] * (self._dof - n_t))

    def _floor(self, rel: Array) -> Array:
        c = self.config.odometry
        dist = float(np.linalg.norm(rel[:3, 3]))
        ang = float(np.linalg.norm(G.so3_log(rel[:3, :3])))
        return self._diagonal(c.floor_translation_m**2 + c.floor_translation_per_m**2 * dist,
                              c.floor_rotation_rad**2 + c.floor_rotation_per_rad**2 * ang)

    def _edge_covariance(self, prev: Keyframe, kf: Keyframe, rel_base: Array) -> EdgeCovariance | None:
        """Registration covariance of keyframe *kf* against *prev* at the odometry's relative pose (base
        frame), with and without the a-posteriori variance factor, or None when it cannot be evaluated.

        The factor is max(1, σ̂²/σ²), σ̂² = Σe²/(n − dof) of the plane residuals (the unit-weight
        variance of least squares): long, sparse ranges fit at several times the σ̂ of short, dense
        ones, and a fixed σ = 2 cm made such edges ~12× too confident in variance against the wheels
        (docs/ODOMETRY.md)."""
        c = self.config.odometry
        if len(prev.points) < 10 or len(kf.points) < 10:
            return None
        rel_sensor = G.inverse(prev.base_T_sensor) @ rel_base @ kf.base_T_sensor
        cfg = IcpConfig(gates_m=(c.edge_gate_m,), sigma_m=c.edge_sigma_m, covariance_model="plane", workers=1,
                        normal_neighbors=8)
        try:
            res = evaluate_alignment(kf.points, IcpTarget(prev.points, normal_neighbors=8, workers=1), rel_sensor,
                                     c.edge_gate_m, cfg)
        except DegenerateInputError:
            return None
        if res.degenerate or not np.all(np.isfinite(res.covariance)):
            return None
        A = G.adjoint(kf.base_T_sensor, planar=self._dof == 3)
        prior = A @ res.covariance @ A.T
        factor = 1.0
        if c.edge_sigma_from_residuals:
            factor = max(1.0, res.residual / max(res.n_residuals - res.dof, 1) / c.edge_sigma_m**2)
        return EdgeCovariance(prior * factor, prior)

    def _ambiguity(self, prev: Keyframe, kf: Keyframe, rel_base: Array) -> Array:
        """Second moment (base frame) of the relative poses that score as well as the odometry's on the
        correlative surface of *kf*'s scan against *prev*'s (:func:`registration.correlative.ambiguity`):
        zero for a sharp match, the slide for a scan matched along a corridor. 2D only."""
        c = self.config.odometry
        if c.edge_ambiguity_window_m is None or self._dof != 3 or len(prev.points) < 10 or len(kf.points) < 10:
            return np.zeros((self._dof, self._dof))
        rel_sensor = G.inverse(prev.base_T_sensor) @ rel_base @ kf.base_T_sensor
        A = G.adjoint(kf.base_T_sensor, planar=True)
        if self._field is None or self._field[0] != prev.id:
            self._field = (prev.id, correlative.LikelihoodPyramid(prev.points[:, :2], c.edge_ambiguity_cell_m,
                                                                  c.edge_ambiguity_cell_m, levels=0))
        try:
            slide = correlative.ambiguity(kf.points[:, :2], self._field[1], rel_sensor, c.edge_ambiguity_window_m,
                                          c.edge_ambiguity_ratio)
        except DegenerateInputError:
            return np.zeros((3, 3))
        return A @ slide @ A.T

    def _wheel_covariance(self, rel: Array) -> Array:
        c = self.config.odometry
        d = float(np.linalg.norm(rel[:3, 3]))
        ang = float(np.linalg.norm(G.so3_log(rel[:3, :3])))
        return self._diagonal((c.wheel_sigma_per_m * d + c.wheel_sigma_m_per_rad * ang + 1e-3) ** 2,
                              (c.wheel_sigma_rad_per_m * d + c.wheel_sigma_rad_per_rad * ang + 1e-3) ** 2)

    def _innovation(self, edge: OdometryEdge, wheel_rel: Array) -> Array:
        """Disagreement Log(edge⁻¹ · wheels) of the wheel increment with the registration edge (tangent vector)."""
        rel = G.relative(edge.measurement, wheel_rel)
        return G.se2_log(rel) if self._dof == 3 else G.se3_log(rel)

    def _consistent(self, innovation: Array, registration_cov: Array, wheel_cov: Array) -> bool:
        """χ² test of the wheel edge against the registration edge over the same keyframe interval:
        dᵀ (Σ_edge + Σ_wheel)⁻¹ d ≤ the ``wheel_gate_probability`` quantile, with the a-priori
        registration covariance and the uncalibrated wheel model (the gate looks for faults, and
        with the a-posteriori covariance it let wheel lumps through; docs/ODOMETRY.md)."""
        p = self.config.odometry.wheel_gate_probability
        if p is None:
            return True
        from scipy.stats import chi2

        m2 = float(innovation @ np.linalg.solve(registration_cov + wheel_cov, innovation))
        return m2 <= float(chi2.ppf(p, self._dof))

    def _wheel_edge(self, prev: Keyframe, kf: Keyframe, edge: OdometryEdge,
                    prior_cov: Array, own_cov: Array) -> tuple[WheelEdge | None, bool]:
        """The wheel edge over keyframes *prev* → *kf* (None when the gate leaves it out) and whether it passed
        the gate's test; *prior_cov* is the registration edge's covariance at the a-priori σ, floor included
        (the gate's), *own_cov* its a-posteriori covariance without the floor (the calibration's fallback,
        :mod:`slam.noise_scale`).

        Left out when it fails the χ² test against the registration edge and the wheels were lumpy
        in the interval (``wheel_gate_lumpy_only``; the odometry took its constant-velocity start at
        some scan): over smooth wheels the disagreement is the registration's, a slide along a
        corridor (±0.25 m on 0.2 m steps in the measured case, docs/ODOMETRY.md), and the wheel edge is
        what holds the chain (once the registration edge carries its slide). Edges that pass the test are the
        calibration's samples."""
        c = self.config.odometry
        wrel = G.relative(prev.frame.odom, kf.frame.odom)
        model = self._wheel_covariance(wrel)
        d = self._innovation(edge, wrel)
        consistent = self._consistent(d, prior_cov, model)
        if not consistent and (self._lumpy_since_kf or not c.wheel_gate_lumpy_only):
            self.wheel_edges_dropped += 1
            return None, False
        if c.wheel_calibration:
            if self.wheel_calibration is None:
                self.wheel_calibration = NoiseScaleCalibration(2 if self._dof == 3 else 3, c.wheel_calibration_min_edges)
            if consistent:
                self.wheel_calibration.add(d, edge.covariance, model, own_cov)
            model = self.wheel_calibration.calibrated(model)
        return WheelEdge(prev.id, kf.id, wrel, model), consistent

    def _deskewed(self, timed: Frame) -> tuple[Frame, Frame | None]:
        """*timed* corrected for the motion during its sweep once the sweep check has read its beam times
        (as listed, reversed, or not to be used) and the odometry has a velocity; as it is before. Also the
        scan with its times as read (None when it was not deskewed)."""
        if self.sweep.verdict in (None, "none"):
            return timed, None
        twist = self.odometry.planar_twist()
        if twist is None:
            return timed, None
        read = as_read(timed, self.sweep.verdict)
        return deskew_planar(read, twist), read

    def process(self, frame: Frame) -> tuple[Keyframe | None, OdometryEdge | None, OdometryStep]:
        """Register *frame*; return (new keyframe or None, its odometry edge or None, the odometry step).

        A deskewed scan is registered at the middle of its sweep (:func:`registration.deskew.deskew_planar`);
        its pose and, for a keyframe, its points are then taken back to its stamp along the increment just
        registered (the stamp lies between the two registered poses), so that every pose the run reports,
        keyframes and graph included, is the robot's at its scan's stamp, as a reference's is."""
        timed = timed_frame(frame, self.config.odometry)
        read = None
        if timed is not None:
            frame, read = self._deskewed(timed)
        lumps_before = getattr(self.odometry, "alternative_starts", 0)
        step = self.odometry.update(frame)
        if timed is not None and self.sweep.verdict is None:
            self.sweep.add(timed, step.world_T_sensor)
        self._lumpy_since_kf |= getattr(self.odometry, "alternative_starts", 0) > lumps_before
        if self._dof is None:
            self._dof = 3 if frame.is_planar else 6
        pose = step.world_T_base
        mid_T_stamp = None
        if read is not None and (twist := self.odometry.planar_twist()) is not None:
            mid_T_stamp = middle_T_stamp(read, twist)
            B = frame.base_T_sensor
            pose = pose @ B @ mid_T_stamp @ G.inverse(B)
        if step.covariance is not None and self._cov_since_kf is not None:
            # Covariance of the base increment equals that of the sensor increment conjugated by base_T_sensor.
            A = G.adjoint(frame.base_T_sensor, planar=self._dof == 3)
            cov_base = A @ step.covariance @ A.T
            B = frame.base_T_sensor
            base_inc = B @ step.prev_T_curr @ G.inverse(B)
            self._cov_since_kf = G.compound_covariance(self._cov_since_kf, base_inc, cov_base)
        self.track.stamps.append(frame.stamp)
        self.track.odom_poses.append(pose)
        self.track.wheel_poses.append(frame.odom)
        new_kf = edge = None
        if self.selector.is_keyframe(frame.stamp, pose):
            if mid_T_stamp is not None:
                frame = seen_from(frame, G.inverse(mid_T_stamp))
            pts = frame.points
            r = np.linalg.norm(pts, axis=1)
            c = self.config.odometry
            kc = self.config.keyframes
            pts = pts[(r >= kc.min_range_m) & (r <= kc.max_range_m)]
            vs = 0.02 if frame.is_planar else 0.3
            kf = Keyframe(self._count, len(self.track.stamps) - 1, frame.stamp, pose,
                          np.asarray(frame.base_T_sensor, dtype=float), voxel_downsample(pts, vs), frame)
            if self._last is not None:
                prev = self._last
                rel = G.relative(prev.odom_pose, pose)
                covs = self._edge_covariance(prev, kf, rel)
                if covs is None:
                    cov = self._cov_since_kf if self._cov_since_kf is not None else np.zeros((self._dof, self._dof))
                    covs = EdgeCovariance(cov, cov)
                floor = self._floor(rel)
                wheels = c.wheel_edges and prev.frame.odom is not None and frame.odom is not None
                edge = OdometryEdge(prev.id, kf.id, rel, covs.posterior + floor, wheels)
                wheel, agree = self._wheel_edge(prev, kf, edge, covs.prior + floor, covs.posterior) if wheels else (None, False)
                if wheel is not None:
                    self.wheel_edges.append(wheel)
                # No wheel edge backs the step, or smooth wheels disagree with it: the registration must say how
                # far it may have slid (a corridor, a second match), which its Fisher information does not. A
                # wheel edge beside it then holds the step; where the wheels agree, the two edges stand as they are.
                if not agree:
                    slide = self._ambiguity(prev, kf, rel)
                    if np.any(slide):
                        self.slid_edges += 1
                        self.max_slide_m = max(self.max_slide_m, float(np.sqrt(np.linalg.eigvalsh(slide[:2, :2])[-1])))
                        edge.covariance = edge.covariance + slide
            if self._keep:
                self.keyframes.append(kf)
            self._last = kf
            self._count += 1
            self._cov_since_kf = np.zeros((self._dof, self._dof))
            self._lumpy_since_kf = False
            new_kf = kf
        self.track.keyframe.append(self._count - 1)
        return new_kf, edge, step
