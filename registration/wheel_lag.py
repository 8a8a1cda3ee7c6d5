"""Whether wheel odometry lags the scans: the test behind :class:`~registration.odometry.IcpOdometry`'s
constant-velocity start (and with it the front end's licence to leave a lumpy wheel edge out).

Real wheel odometry reports a robot's motion in lumps where its messages come slower than the scans or
its integration stalls: no turn while the scans turned, a gap the wheel pose barely crossed. A
registration that slid along a corridor disagrees with the wheels as well, and there the wheels are the
ones to keep. The two are told apart by how the wheels' increment compares with the scans' last one and
with the wheels' own recent ones (docs/LOOP_CLOSURE.md, "The wheel-lag test" and "The wheels' own
history", has the measured cases).
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo

Array = NDArray[np.float64]

_STALE_M = 1e-3  # slack of the lag test: a wheel increment this small is no motion at all
_STALE_RAD = 1e-3
_WHEEL_HISTORY = 10  # scans over which the wheels' own typical increment is taken (their median speed)


def wheels_lag(wheel: Array, scans: Array, bound_m: float | None, bound_rad: float | None,
               typical: tuple[float, float] | None = None) -> bool:
    """Whether the wheel increment *wheel* lags the scans' own last increment *scans* (both ``prev_T_curr``):
    the wheels report less than the bounds' motion, and in a part where they disagree with the scans by
    more than its bound (translation *bound_m*, rotation *bound_rad*; None leaves a part out) they report
    at most half the scans' motion (+1 mm / 0.001 rad) — no turn while the scans turned, a gap the wheel
    pose barely crossed. Slow, steady wheels beside a registration that stopped or went the other way do
    not lag: there it is the registration that slid.

    *typical* is the wheels' own typical increment over the last scans (translation m, rotation rad, scaled
    to this interval; None: unknown). A lag is also a drop to at most half of it: lagging wheels report less
    than they have been reporting, while steady wheels beside a registration that slid forward along a
    corridor report what they always do (a lumpy odometry's typical turn or step may be nil; then only no
    motion at all is a lag)."""
    def small(T: Array) -> tuple[float, float]:
        return float(np.linalg.norm(T[:3, 3])), geo.rotation_angle(T[:3, :3])

    w_m, w_rad = small(wheel)
    s_m, s_rad = small(scans)
    d_m, d_rad = small(geo.relative(wheel, scans))
    t_m, t_rad = typical if typical is not None else (np.inf, np.inf)
    if (bound_m is not None and w_m > bound_m) or (bound_rad is not None and w_rad > bound_rad):
        return False
    return bool((bound_m is not None and d_m > bound_m and w_m <= 0.5 * min(s_m, t_m) + _STALE_M)
                or (bound_rad is not None and d_rad > bound_rad and w_rad <= 0.5 * min(s_rad, t_rad) + _STALE_RAD))


class WheelSpeeds:
    """The wheels' last increments as speeds (m/s, rad/s) and their typical increment over an interval."""

    def __init__(self, history: int = _WHEEL_HISTORY) -> None:
        self._speeds: deque[tuple[float, float]] = deque(maxlen=history)

    def append(self, increment: Array, dt: float) -> None:
        """Remember the wheel *increment* (``prev_T_curr``) over *dt* seconds (none when *dt* ≤ 0)."""
        if dt > 0:
            self._speeds.append((float(np.linalg.norm(increment[:3, 3])) / dt, geo.rotation_angle(increment[:3, :3]) / dt))

    def clear(self) -> None:
        self._speeds.clear()

    def typical(self, dt: float) -> tuple[float, float] | None:
        """The median speed over the remembered increments (at least 3) times *dt* s: the wheels' typical
        step (m) and turn (rad) over this interval, or None."""
        if len(self._speeds) < 3 or dt <= 0:
            return None
        m, rad = np.median(np.asarray(self._speeds), axis=0) * dt
        return float(m), float(rad)
