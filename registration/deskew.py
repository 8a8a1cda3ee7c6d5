"""Motion compensation ("deskewing") of a planar laser scan.

A rotating laser measures its beams one after the other over the sweep; a robot that moves meanwhile
draws a skewed scan. A scan taken while turning at ω is compressed (or stretched) in angle by
1 / (1 + ω·s), s the sweep's seconds per radian, so a scan matcher underestimates every turn by that
fraction (a Hokuyo URG-04LX, 0.1 s a revolution, at 60°/s: 1.7 %; docs/ODOMETRY.md has the measurement).
With the twist ξ = (v_x, v_y, ω) of the sensor held constant over the sweep (the constant-velocity model
with which KISS-ICP deskews its LiDAR frames: Vizzo et al., RA-L 2023, Sec. III-A), a beam measured t
seconds after the middle of the sweep was taken from the pose Exp(t·ξ) of the sensor frame at that
middle, so its point p lies at Exp(t·ξ)·p there (the exponential of :func:`core.geometry.se3_exp`, Barfoot, *State Estimation
for Robotics*, 2017, eq. 7.86, in the plane).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core.frame import Frame

Array = NDArray[np.float64]

__all__ = ["planar_twist", "sweep_times", "sweep_middle_s", "deskew_planar", "middle_T_stamp", "seen_from"]


def planar_twist(prev_T_curr: ArrayLike, dt_s: float) -> Array:
    """The constant twist ``(v_x, v_y, ω)`` per second (sensor frame) that moves through the planar
    increment *prev_T_curr* (4×4) in *dt_s* seconds: its logarithm over the interval."""
    xi = geo.se3_log(np.asarray(prev_T_curr, dtype=np.float64))
    return np.array([xi[0], xi[1], xi[5]]) / dt_s


def sweep_times(angles: ArrayLike, revolution_s: float) -> Array:
    """Beam times (s after the stamp) of a laser that turns one revolution in *revolution_s* and
    measures its beams in the order listed, the first at the stamp: |a − a₀| / 2π of a revolution."""
    a = np.asarray(angles, dtype=np.float64)
    return np.abs(a - a[0]) / (2.0 * np.pi) * revolution_s if a.size else a.copy()


def sweep_middle_s(beam_times: ArrayLike) -> float:
    """Seconds from the stamp to the middle of the sweep (beam times in seconds after the stamp)."""
    t = np.asarray(beam_times, dtype=np.float64)
    return 0.5 * (float(t.min()) + float(t.max())) if t.size else 0.0


def deskew_planar(frame: Frame, twist: ArrayLike) -> Frame:
    """*frame* with every beam moved into the sensor frame at the middle of its sweep (see the module
    text); the result's ``beam_times`` are zero. A frame without beam times is returned as it is.

    The middle, not the first beam, for registration: an error δω of the velocity then stretches the scan
    about its centre instead of turning it by δω·(half a sweep), which fed back into the next velocity and
    made the increments oscillate (``tests/test_deskew.py``). The registered pose is then the sensor's at
    mid-sweep, as it is, nearly, for a scan matched without deskewing; :func:`middle_T_stamp` takes it back
    to the stamp (a ROS stamp is the first beam's: mid-sweep is 33 ms later for a URG-04LX, 50 ms for an
    RPLIDAR at 10 Hz), and :func:`seen_from` its points.

    Hits move to ``Exp(t·ξ)·p`` (angles and ranges recomputed from them); a beam without a return keeps
    its range and turns by ``ω·t`` (its origin's shift of millimetres is left out of free space).
    """
    if frame.beam_times is None or frame.ranges is None or frame.angles is None:
        return frame
    vx, vy, w = (float(x) for x in np.asarray(twist, dtype=np.float64))
    t = frame.beam_times - sweep_middle_s(frame.beam_times)
    zeros = np.zeros_like(t)
    motion = geo.se3_exp(np.column_stack([vx * t, vy * t, zeros, zeros, zeros, w * t]))  # Exp(t·ξ) per beam
    return _moved(frame, motion, w * t)


def seen_from(frame: Frame, new_T_old: ArrayLike) -> Frame:
    """*frame*'s beams (taken at one instant, e.g. deskewed; a frame with beam geometry) as seen from a sensor
    frame moved rigidly: *new_T_old* (4×4, planar) takes its points into the new frame; angles and ranges are
    recomputed, the beams' origin shift left out as in :func:`deskew_planar`."""
    T = np.asarray(new_T_old, dtype=np.float64)
    n = len(frame.ranges)
    return _moved(frame, np.broadcast_to(T, (n, 4, 4)), np.full(n, float(np.arctan2(T[1, 0], T[0, 0]))))


def _moved(frame: Frame, motion: Array, phi: Array) -> Frame:
    """*frame* with beam i's hit moved by ``motion[i]`` (4×4) and a beam without a return turned by ``phi[i]``."""
    angles = frame.angles + phi
    ranges = frame.ranges.copy()
    hit = ~frame.no_return & np.isfinite(frame.ranges)
    r, ang = frame.ranges[hit], frame.angles[hit]
    m = motion[hit]
    px, py = r * np.cos(ang), r * np.sin(ang)
    qx = m[:, 0, 0] * px + m[:, 0, 1] * py + m[:, 0, 3]
    qy = m[:, 1, 0] * px + m[:, 1, 1] * py + m[:, 1, 3]
    ranges[hit] = np.hypot(qx, qy)
    angles[hit] = np.arctan2(qy, qx)
    if len(frame.points) == int(hit.sum()):
        points = np.column_stack([qx, qy])
    else:  # a reader that keeps a point per beam: every beam's end point moved
        rr = np.where(hit, ranges, frame.ranges)
        points = np.column_stack([rr * np.cos(angles), rr * np.sin(angles)]) if len(frame.points) == len(rr) else frame.points
    return replace(frame, points=points, angles=angles, ranges=ranges, beam_times=np.zeros_like(phi))


def middle_T_stamp(frame: Frame, twist: ArrayLike) -> Array:
    """``middle_T_stamp`` (4×4, sensor frame): the sensor's pose at *frame*'s stamp seen from its pose at the
    middle of the sweep, ``Exp(−Δ·ξ)`` under the constant twist ξ (Δ = :func:`sweep_middle_s`); the identity
    for a frame without beam times. A pose registered from the scan deskewed to the middle, right-multiplied
    by it, is the pose at the stamp, and :func:`seen_from` with its inverse gives the scan's points there."""
    if frame.beam_times is None or frame.ranges is None or frame.angles is None:
        return np.eye(4)
    vx, vy, w = (float(x) for x in np.asarray(twist, dtype=np.float64))
    d = -sweep_middle_s(frame.beam_times)
    return geo.se3_exp(np.array([vx * d, vy * d, 0.0, 0.0, 0.0, w * d]))
