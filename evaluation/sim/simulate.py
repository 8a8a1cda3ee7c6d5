"""Simulated 2D laser logs: a robot tour, noisy scans, drifting wheel odometry (written as an MCAP log by
:mod:`slam.logs.simulated`).

Frames: ``map`` (the world / ground-truth frame), ``odom`` (wheel odometry, coincides with the
start pose of the robot), ``base_link`` (robot base), ``laser`` (the scanner, ``base_T_sensor``).

Odometry follows the sample odometry motion model of Thrun, Burgard & Fox, *Probabilistic
Robotics* (2005), §5.4, Table 5.6: each true increment between consecutive scans is split into
(δrot1, δtrans, δrot2) and perturbed with zero-mean Gaussians of variance
    δrot1: α1·δrot1² + α2·δtrans²,   δtrans: α3·δtrans² + α4·(δrot1² + δrot2²),
    δrot2: α1·δrot2² + α2·δtrans²
(α1 rad²/rad², α2 rad²/m², α3 m²/m², α4 m²/rad², per scan increment), then integrated, so the
error is a random walk growing with the distance travelled and the angle turned.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core.errors import ConfigError
from core.frame import Frame

from .path import plan_path
from .raycast import cast_rays
from .sensors import LaserSpec
from .world import World

if TYPE_CHECKING:
    from .coverage import CoverageTour

__all__ = ["SimulatedLog", "simulate", "odometry_from_ground_truth", "DEFAULT_ODOM_NOISE",
           "START_STAMP"]

# α1…α4 of Probabilistic Robotics Table 5.6, per scan increment. At the default 0.5 m/s, 1 rad/s and
# 10 Hz (5 cm / 0.1 rad per scan) they give σ ≈ 1.6° per 90° in-place turn and, per 10 m driven,
# σ ≈ 1.3° of heading and ≈ 7 cm along track — a drifting but usable wheel odometry.
DEFAULT_ODOM_NOISE = (0.005, 0.0005, 0.01, 0.001)
START_STAMP = 1_700_000_000.0  # s; fixed so that logs are reproducible bit for bit
DEFAULT_BASE_T_SENSOR_XYT = (0.1, 0.0, 0.0)  # laser 10 cm ahead of the base centre


@dataclass
class SimulatedLog:
    """A simulated run.

    Attributes:
        world, spec: the ground truth and the laser.
        stamps: ``(N,)`` s. ground_truth: ``(N, 4, 4)`` ``map_T_base``. odometry: ``(N, 4, 4)``
        ``odom_T_base`` (drifting). angles: ``(B,)`` rad. ranges: ``(N, B)`` m, ``inf`` = no return.
        base_T_sensor: ``(4, 4)`` laser on the base. range_noise: σ used (m). odom_noise: α1…α4.
        seed: the seed that reproduces the run.
    """

    world: World
    spec: LaserSpec
    stamps: NDArray[np.float64]
    ground_truth: NDArray[np.float64]
    odometry: NDArray[np.float64]
    angles: NDArray[np.float64]
    ranges: NDArray[np.float64]
    base_T_sensor: NDArray[np.float64]
    range_noise: float = 0.0
    odom_noise: tuple[float, float, float, float] = DEFAULT_ODOM_NOISE
    seed: int = 0
    tour: "CoverageTour | None" = None  # the coverage tour (with its coverage and unreachable space) when planned

    def __len__(self) -> int:
        return int(len(self.stamps))

    def sensor_poses(self) -> NDArray[np.float64]:
        """``(N, 4, 4)`` ``map_T_laser``."""
        return self.ground_truth @ self.base_T_sensor

    def frames(self) -> Iterator[Frame]:
        """The scans as :class:`Frame` objects (points in the laser frame, beams, odometry, truth)."""
        c, s = np.cos(self.angles), np.sin(self.angles)
        for i in range(len(self)):
            r = self.ranges[i]
            hit = np.isfinite(r)
            pts = np.column_stack([r[hit] * c[hit], r[hit] * s[hit]])
            yield Frame(
                stamp=float(self.stamps[i]), points=pts, index=i, angles=self.angles, ranges=r.copy(),
                no_return=~hit, beam_times=self.spec.logged_beam_times() if self.spec.revolution_s > 0 else None,
                odom=self.odometry[i].copy(), ground_truth=self.ground_truth[i].copy(),
                base_T_sensor=self.base_T_sensor.copy(), max_range=self.spec.range_max,
                min_range=self.spec.range_min, source=f"simulated {self.world.name} scan {i}",
            )


def odometry_from_ground_truth(xyt: ArrayLike, alphas: Sequence[float], rng: np.random.Generator) -> NDArray[np.float64]:
    """Drifting odometry ``(N, 3)`` (x, y, θ in the odom frame, starting at 0) from true base poses
    ``(N, 3)`` with the odometry motion model of Probabilistic Robotics Table 5.6 (module docstring)."""
    p = np.asarray(xyt, dtype=np.float64).reshape(-1, 3)
    a1, a2, a3, a4 = (float(a) for a in alphas)
    if min(a1, a2, a3, a4) < 0:
        raise ConfigError(f"odometry noise parameters must be >= 0, got {tuple(alphas)}")
    d = np.diff(p[:, :2], axis=0)
    trans = np.hypot(d[:, 0], d[:, 1])
    dth = geo.wrap_angle(np.diff(p[:, 2]))
    moving = trans > 1e-9  # in-place turns have no defined travel direction: all rotation in δrot2
    rot1 = np.where(moving, geo.wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - p[:-1, 2]), 0.0)
    rot2 = geo.wrap_angle(dth - rot1)
    m = len(trans)
    n = rng.standard_normal((3, m))
    rot1_h = rot1 - n[0] * np.sqrt(a1 * rot1**2 + a2 * trans**2)
    trans_h = trans - n[1] * np.sqrt(a3 * trans**2 + a4 * (rot1**2 + rot2**2))
    rot2_h = rot2 - n[2] * np.sqrt(a1 * rot2**2 + a2 * trans**2)
    th = np.concatenate([[0.0], np.cumsum(rot1_h + rot2_h)])
    heading = th[:-1] + rot1_h
    x = np.concatenate([[0.0], np.cumsum(trans_h * np.cos(heading))])
    y = np.concatenate([[0.0], np.cumsum(trans_h * np.sin(heading))])
    return np.column_stack([x, y, geo.wrap_angle(th)])


def _during_sweep(sensor_xyt: NDArray[np.float64], stamps: NDArray[np.float64],
                  beam_times: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(N, B, 3)`` sensor pose at each beam's time (stamp + beam time), linear in x, y and the unwrapped
    heading between the scans' poses (held after the last)."""
    t = stamps[:, None] + beam_times[None, :]
    heading = np.unwrap(sensor_xyt[:, 2])
    return np.stack([np.interp(t, stamps, sensor_xyt[:, 0]), np.interp(t, stamps, sensor_xyt[:, 1]),
                     geo.wrap_angle(np.interp(t, stamps, heading))], axis=-1)


def simulate(
    world: World,
    *,
    n_scans: int | None,
    spec: LaserSpec,
    seed: int,
    range_noise: float | None = None,
    odom_noise: Sequence[float] = DEFAULT_ODOM_NOISE,
    base_T_sensor: ArrayLike | None = None,
    max_speed: float = 0.5,
    max_turn_rate: float = 1.0,
    robot_radius: float = 0.2,
    laps: int = 1,
) -> SimulatedLog:
    """Simulate *n_scans* scans of *spec* along a planned closed tour through *world*; with
    ``n_scans=None``, exactly the scans of *laps* coverage tours (:func:`.coverage.coverage_tour`).

    Args:
        range_noise: Gaussian range σ (m); the preset's ``noise_std`` when None.
        odom_noise: α1…α4 of the odometry motion model (module docstring).
        base_T_sensor: 4×4 laser pose on the base (default 0.1 m ahead, facing forward).
        max_speed (m/s), max_turn_rate (rad/s), robot_radius (m): see :func:`plan_path`.

    The path, the range noise and the odometry noise use independent random streams spawned
    from *seed*, so changing a noise level does not change the path. A laser with a ``revolution_s``
    takes each beam at its own time during the sweep, from the pose the path has then (the log then
    records ``time_increment``); the others take every beam at the stamp.
    """
    if n_scans is not None and n_scans < 1:
        raise ConfigError(f"--scans must be >= 1, got {n_scans}")
    if n_scans is not None and laps != 1:
        raise ConfigError("--laps goes with --scans auto (a fixed number of scans sets its own revisits)")
    sigma = spec.noise_std if range_noise is None else float(range_noise)
    if sigma < 0 or not np.isfinite(sigma):
        raise ConfigError(f"range noise must be a finite number >= 0, got {range_noise}")
    alphas = tuple(float(a) for a in odom_noise)
    if len(alphas) != 4:
        raise ConfigError(f"odometry noise needs four values α1..α4, got {len(alphas)}")
    b_T_s = geo.xytheta_to_matrix(np.asarray(DEFAULT_BASE_T_SENSOR_XYT)) if base_T_sensor is None else np.asarray(base_T_sensor, dtype=np.float64)
    if b_T_s.shape != (4, 4) or not geo.is_pose(b_T_s):
        raise ConfigError("base_T_sensor must be a 4×4 rigid transform")
    path_ss, range_ss, odom_ss = np.random.SeedSequence(seed).spawn(3)
    if n_scans is None:
        from .coverage import coverage_tour  # compiles the visibility kernels (numba) on first use

        tour = coverage_tour(world, spec, np.random.default_rng(path_ss), robot_radius=robot_radius, laps=laps,
                             max_speed=max_speed, max_turn_rate=max_turn_rate, base_T_sensor=b_T_s)
        xyt, n_scans = tour.poses, len(tour.poses)
    else:
        tour = None
        xyt = plan_path(world, n_scans, spec, np.random.default_rng(path_ss), max_speed=max_speed,
                        max_turn_rate=max_turn_rate, robot_radius=robot_radius)
    gt = geo.xytheta_to_matrix(xyt)
    sensor_xyt = geo.matrix_to_xytheta(gt @ b_T_s)
    stamps = START_STAMP + np.arange(n_scans) * spec.period
    beam_xyt = _during_sweep(sensor_xyt, stamps, spec.beam_times()) if spec.revolution_s > 0 else sensor_xyt
    ranges = cast_rays(world, beam_xyt, spec, rng=np.random.default_rng(range_ss), range_noise=sigma)
    odom = geo.xytheta_to_matrix(odometry_from_ground_truth(xyt, alphas, np.random.default_rng(odom_ss)))
    return SimulatedLog(world=world, spec=spec, stamps=stamps, ground_truth=gt, odometry=odom, angles=spec.angles(),
                        ranges=ranges, base_T_sensor=b_T_s, range_noise=sigma, odom_noise=alphas, seed=seed,
                        tour=tour)
