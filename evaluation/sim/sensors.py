"""2D laser scanner specifications and presets (angles in the sensor frame, rad; ranges in m)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["LaserSpec", "LASER_PRESETS"]


@dataclass(frozen=True)
class LaserSpec:
    """A planar laser: ``num_beams`` beams evenly spaced from ``angle_min`` to ``angle_max`` inclusive
    (the sensor_msgs/LaserScan convention, ``angle_increment = (max − min)/(num_beams − 1)``).

    ``noise_std`` is the default Gaussian range noise σ (m) of the simulator for this sensor.
    ``revolution_s`` is the time the mirror takes for one turn: the beams are measured one after the
    other from ``angle_min``, the first at the scan's stamp, ``time_increment`` apart (a robot that
    moves meanwhile skews the scan); 0 takes every beam at the stamp. ``clockwise``: the mirror turns
    the other way, from ``angle_max``, while the beams are still listed by increasing angle and the log
    still says ``time_increment`` from the first listed — what the rplidar_ros and ydlidar drivers
    publish (their issue trackers: Slamtec/rplidar_ros #55, cartographer_ros #1546).
    """

    name: str
    num_beams: int
    angle_min: float
    angle_max: float
    range_min: float
    range_max: float
    rate_hz: float
    noise_std: float
    revolution_s: float = 0.0
    clockwise: bool = False

    def __post_init__(self) -> None:
        if self.num_beams < 2 or not self.angle_max > self.angle_min:
            raise ValueError(f"{self.name}: need num_beams >= 2 and angle_max > angle_min")
        if not (0.0 <= self.range_min < self.range_max) or self.rate_hz <= 0 or self.noise_std < 0:
            raise ValueError(f"{self.name}: need 0 <= range_min < range_max, rate_hz > 0, noise_std >= 0")
        if not 0.0 <= self.revolution_s * (self.angle_max - self.angle_min) / (2 * np.pi) < self.period:
            raise ValueError(f"{self.name}: need revolution_s >= 0 and a sweep shorter than the scan period")

    @property
    def angle_increment(self) -> float:
        return (self.angle_max - self.angle_min) / (self.num_beams - 1)

    @property
    def period(self) -> float:
        """Time between scans (s)."""
        return 1.0 / self.rate_hz

    @property
    def time_increment(self) -> float:
        """Time between consecutive beams (s; 0 when every beam is taken at the stamp)."""
        return self.revolution_s * self.angle_increment / (2 * np.pi)

    def beam_times(self) -> NDArray[np.float64]:
        """``(B,)`` time each beam is taken, after the scan's stamp (s)."""
        order = np.arange(self.num_beams, dtype=np.float64)
        return self.time_increment * (order[::-1] if self.clockwise else order)

    def logged_beam_times(self) -> NDArray[np.float64]:
        """``(B,)`` the times the log gives the beams (``i·time_increment``, whichever way the mirror turns)."""
        return self.time_increment * np.arange(self.num_beams, dtype=np.float64)

    def angles(self) -> NDArray[np.float64]:
        """``(B,)`` beam angles in the sensor frame (rad)."""
        return self.angle_min + self.angle_increment * np.arange(self.num_beams, dtype=np.float64)


LASER_PRESETS: dict[str, LaserSpec] = {
    # Fast-GPOM paper's simulated laser (STDR pandora robot, Kuang's fork):
    # /work/shared/data/stdr_maps/pandora_robot.kuanghaofei_fork.yaml — 667 rays over ±2.0944 rad,
    # 0.06–4.09 m, 10 Hz. STDR ignores its noise spec; we default to σ = 1 cm.
    "fastgpom": LaserSpec("fastgpom", 667, -2.09439516067505, 2.09439516067505,
                          0.0599999986588955, 4.09000015258789, 10.0, 0.01),
    # SICK LMS 200 as in the CARMEN/Radish logs: 181 beams over 180° (1°), up to 80 m; σ ≈ 1 cm.
    # 10 Hz is a typical logging rate of those datasets, not the mirror speed.
    "sick_lms": LaserSpec("sick_lms", 181, -np.pi / 2, np.pi / 2, 0.05, 80.0, 10.0, 0.01),
    # Hokuyo UTM-30LX data sheet: 270° at 0.25° (1081 beams), 0.1–30 m, 25 ms per scan; ±30 mm ≈ σ 1 cm.
    "hokuyo_utm30": LaserSpec("hokuyo_utm30", 1081, -3 * np.pi / 4, 3 * np.pi / 4, 0.1, 30.0, 40.0, 0.01),
    # Hokuyo URG-04LX data sheet: 240° over 682 of its 1024 steps a turn, 0.02–5.6 m, 100 ms a scan (one
    # mirror turn), ±10 mm to 1 m; a slow sweep: the beams are taken one after the other over 67 ms.
    "hokuyo_urg04lx": LaserSpec("hokuyo_urg04lx", 682, -681 * np.pi / 1024, 681 * np.pi / 1024, 0.02, 5.6, 10.0, 0.01,
                                revolution_s=0.1),
    # Slamtec RPLIDAR A2 data sheet: 360°, 0.15–12 m, 10 Hz, ≤ 1 % of range; turning clockwise, as its ROS
    # driver publishes it (the beams by increasing angle, the times the other way round).
    "rplidar_a2": LaserSpec("rplidar_a2", 360, -np.pi, np.pi - 2 * np.pi / 360, 0.15, 12.0, 10.0, 0.01,
                            revolution_s=0.1, clockwise=True),
}
