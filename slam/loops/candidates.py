"""Candidate sources: which old keyframes a new one may be revisiting, and where to look.

One rule sizes everything: the estimate's uncertainty of each old keyframe relative to the new one,
along the graph (:mod:`slam.loops.uncertainty`). A place is a candidate when its estimate lies within
the overlap radius plus ``window_sigmas`` standard deviations of the new keyframe, and the correlative
search around the estimate's relative pose spans the same ``window_sigmas`` standard deviations per
axis (at least the floors). The estimate *vouches* for a candidate when that window is still at its
floor: a match consistent with such an estimate is a revisit, not an alias.

Sources (Olson 2009 §2 for spatial gating, Hess et al. 2016 §V for the global search):

* spatial: the ``near_candidates`` nearest places within reach, plus the ``uncertain_candidates``
  most uncertain ones (an old pass is not crowded out by the recent pass beside it); the nearest are
  verified only until ``near_closures`` of them are accepted;
* descriptor: places whose Scan Context descriptor (Kim & Kim 2018) matches, when the spatial
  ones closed nothing: revisits the estimate has lost;
* global (2D): places whose window would exceed ``max_window_m`` yet lie within reach: one at a time,
  the one whose surroundings look most like the new keyframe's first (:mod:`slam.loops.surroundings`),
  searched over their whole local map;
* hypothesis: the place of a recent pending closure, from that closure composed with the odometry
  since, so that a revisit the estimate cannot vouch for gathers its group.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from core import geometry as G
from slam.keyframes import Keyframe

from .config import LoopConfig
from .local_map import sensor_relative
from .types import Candidate, Source, Window
from .uncertainty import NodeUncertainty

Array = NDArray[np.float64]


def overlap_radius(kf: Keyframe, config: LoopConfig) -> float:
    """Distance (m) within which two keyframes can see the same structure: the configured one, or the
    upper quartile of the ranges of *kf*'s scan points (how far this sensor sees in this environment,
    most of the time)."""
    if config.overlap_radius_m is not None:
        return float(config.overlap_radius_m)
    r = np.linalg.norm(kf.points[:, :2], axis=1)
    return float(np.percentile(r, 75)) if len(r) else 1.0


def windows(uncertainty: NodeUncertainty, config: LoopConfig, planar: bool) -> tuple[Array, Array, Array]:
    """Per keyframe: the search window half-widths (m, rad) and the per-axis position σ (m), from its
    uncertainty relative to the new keyframe (``window_sigmas`` σ, at least the floors).

    The heading-rate term of the uncertainty (:mod:`slam.loops.uncertainty`) widens a spatial window up
    to ``max_window_m`` but never past it; a place the independent edge noise alone puts beyond
    ``max_window_m`` is no spatial candidate at all (its window is returned uncapped). Places whose whole
    uncertainty reaches beyond ``max_window_m`` are also the global search's (:func:`global_places`)."""
    d, r = (2, 1) if planar else (3, 3)
    k = config.window_sigmas
    noise = uncertainty.without_drift()
    win_noise = np.maximum(k * np.sqrt(noise.position_var / d), config.window_floor_m)
    sd_xy = np.sqrt(uncertainty.position_var / d)
    win_xy = np.where(win_noise > config.max_window_m, win_noise,
                      np.minimum(np.maximum(k * sd_xy, config.window_floor_m), config.max_window_m))
    sd_th = np.sqrt(uncertainty.rotation_var / r)
    win_th = np.minimum(np.maximum(k * sd_th, np.radians(config.window_floor_deg)), np.pi)
    return win_xy, win_th, sd_xy


def _vouched(win_xy: float, win_th: float, config: LoopConfig) -> bool:
    return bool(win_xy <= config.window_floor_m and win_th <= np.radians(config.window_floor_deg))


def vouches(position_var: float, rotation_var: float, config: LoopConfig, planar: bool) -> bool:
    """Whether a relative pose with these variance traces (m², rad²) is sure enough to vouch for: its
    ``window_sigmas`` σ search window would stay at the floors (:func:`windows`, :func:`_vouched`)."""
    d, r = (2, 1) if planar else (3, 3)
    return _vouched(config.window_sigmas * float(np.sqrt(position_var / d)),
                    config.window_sigmas * float(np.sqrt(rotation_var / r)), config)


_PLAUSIBLE_WINDOWS = 3.0  # a closure is implausible beyond three search windows of the estimate (9 σ per axis)


def _plausible(win_xy: float, win_th: float) -> Window:
    """The region around the estimate where a closure is plausible at all: three search windows (an
    overconfident graph after a long loop is off by a few σ, an alias turned round by a hundred)."""
    return Window(float(_PLAUSIBLE_WINDOWS * win_xy), float(min(np.pi, _PLAUSIBLE_WINDOWS * win_th)))


def _spread(pool: NDArray[np.int64], quota: int, chosen: list[int], spacing: int) -> list[int]:
    """Up to *quota* of *pool* (in order) whose local maps (±*spacing*) do not overlap those *chosen*."""
    added: list[int] = []
    for i in pool:
        if len(added) >= quota:
            break
        if all(abs(int(i) - k) > spacing for k in chosen + added):
            added.append(int(i))
    return added


def other_pass(path_m: Array, dist_m: Array, j: int, radius_m: float,
               places: NDArray[np.int64] | None = None) -> NDArray[np.bool_]:
    """Which keyframes (*places*, else ``0 … len(dist_m) − 1``, at distances *dist_m* from keyframe *j*) belong to
    another pass than *j*: the path between them (*path_m*, cumulative metres per keyframe) is longer than their
    distance plus twice the overlap radius — the trajectory left the place and came back, rather than seeing
    it still (those the odometry ties)."""
    before = path_m[: len(dist_m)] if places is None else path_m[places]
    return path_m[j] - before >= dist_m + 2.0 * radius_m


@dataclass(frozen=True)
class SpatialCandidates:
    """:func:`spatial`'s candidates: the nearest places (nearest first), then the most uncertain ones."""

    near: list[Candidate]
    uncertain: list[Candidate]

    def __iter__(self) -> Iterator[Candidate]:
        return iter(self.near + self.uncertain)


def spatial(keyframes: list[Keyframe], poses: Array, j: int, uncertainty: NodeUncertainty, config: LoopConfig,
            planar: bool, radius_m: float, path_m: Array) -> SpatialCandidates:
    """Spatial candidates of the new keyframe *j*: places of other passes (:func:`other_pass`) within
    *radius_m* + ``window_sigmas`` σ whose window stays within ``max_window_m``; the nearest first, then the
    most uncertain."""
    last = j - config.exclude_recent_keyframes
    if last <= 0:
        return SpatialCandidates([], [])
    win_xy, win_th, sd = windows(uncertainty, config, planar)
    dim = 2 if planar else 3
    dist = np.linalg.norm(poses[:last, :dim, 3] - poses[j, :dim, 3], axis=1)
    reach = ((dist <= radius_m + config.window_sigmas * sd[:last]) & (win_xy[:last] <= config.max_window_m)
             & other_pass(path_m, dist, j, radius_m))
    pool = np.flatnonzero(reach)
    pool = pool[np.argsort(dist[pool], kind="stable")]
    near = _spread(pool, config.near_candidates, [], config.local_map_keyframes)
    uncertain = pool[win_xy[pool] > config.window_floor_m]
    uncertain = uncertain[np.argsort(-sd[uncertain], kind="stable")]
    far = _spread(uncertain, config.uncertain_candidates, near, config.local_map_keyframes)

    def candidate(i: int) -> Candidate:
        est = sensor_relative(keyframes, poses, i, j)
        return Candidate(i, j, Source.SPATIAL, est, Window(float(win_xy[i]), float(win_th[i])),
                         (est, uncertainty.covariance(i, planar)), _vouched(win_xy[i], win_th[i], config),
                         plausible=_plausible(win_xy[i], win_th[i]))

    return SpatialCandidates([candidate(i) for i in near], [candidate(i) for i in far])


def global_places(poses: Array, j: int, uncertainty: NodeUncertainty, config: LoopConfig, planar: bool,
                  radius_m: float, spacing: int) -> NDArray[np.int64]:
    """Places (every *spacing*-th keyframe, older than the exclusion window) the new keyframe *j* may be
    revisiting although ``window_sigmas`` σ of its uncertainty exceed ``max_window_m``: within *radius_m* +
    ``window_sigmas`` σ of its estimate. σ includes the heading-rate term: after a long stretch without
    closures the drift it models is what puts a return tens of metres from the estimate, beyond any
    spatial window (measured: 80 m off at 2.3 σ, within reach, but at 4.6 σ of the independent noise
    alone; docs/LOOP_CLOSURE.md)."""
    last = j - config.exclude_recent_keyframes
    if last <= 0:
        return np.zeros(0, dtype=np.int64)
    ids = np.arange(0, last, max(1, spacing))
    reach = config.window_sigmas * windows(uncertainty, config, planar)[2][ids]
    dist = np.linalg.norm(poses[ids, :2, 3] - poses[j, :2, 3], axis=1)
    return ids[(reach > config.max_window_m) & (dist <= radius_m + reach)]


def unsearched(places: NDArray[np.int64], searched_at_m: dict[int, float], here_m: float,
               radius_m: float) -> NDArray[np.int64]:
    """The *places* the global search has not searched since the robot was within *radius_m* of path of
    *here_m* (*searched_at_m*: place → path at its last global search): a keyframe an overlap radius further
    on sees another part of the place, so it may be searched again — not before."""
    return np.array([p for p in places if here_m - searched_at_m.get(int(p), -np.inf) > radius_m], dtype=np.int64)


def next_global_place(places: NDArray[np.int64], alike: Array, sigmas: Array) -> int:
    """The place the global search takes: the most alike (smallest surroundings distance *alike*,
    :mod:`slam.loops.surroundings`), ties by the estimate's distance in standard deviations *sigmas*.
    Appearance first, because a place needs the global search when the estimate is off by many σ — and
    then the estimate's own order among dozens of places within reach is no better than chance."""
    return int(places[np.lexsort((sigmas, alike))[0]])


# A global match is plausible within this χ² quantile of the estimate's whole uncertainty (3 dof: 16.3) ...
GLOBAL_PLAUSIBLE_PROBABILITY = 0.999
# ... and within this one (3 dof: 30.7) when an independent global match agrees with it (slam.loops.accept).
GLOBAL_CORROBORATED_PROBABILITY = 1.0 - 1e-6


def global_candidate(keyframes: list[Keyframe], poses: Array, i: int, j: int, uncertainty: NodeUncertainty,
                     config: LoopConfig, extent: tuple[Array, Array]) -> Candidate:
    """Search place *i* whole for keyframe *j*: every position over the local map's *extent* (its lower
    and upper corners, m) and every heading (Cartographer's ``MatchFullSubmap``: an estimate this far off
    says little about the heading either). The search is not bounded by the estimate, so its match is
    held to it afterwards: within the ``GLOBAL_PLAUSIBLE_PROBABILITY`` quantile of χ²(3) of the estimate's
    whole uncertainty, heading-rate term included — the same σ that put the place within reach — or within
    the looser ``GLOBAL_CORROBORATED_PROBABILITY`` quantile when an independent global match agrees
    (:mod:`slam.loops.accept`). (An outdoor scan matched 90° round, 60 m from its reference pose, was 7.8
    heading σ from the estimate; real returns after 0.05 °/m of injected drift lie at χ² 9–10, after 0.06 °/m
    at 19–21; docs/LOOP_CLOSURE.md.)"""
    lo, hi = extent
    est = sensor_relative(keyframes, poses, i, j)
    centre = G.xytheta_to_matrix(*(0.5 * (lo + hi)), G.matrix_to_xytheta(est)[2])
    return Candidate(i, j, Source.GLOBAL, centre, Window(float(0.5 * (hi - lo).max()), np.pi),
                     (est, uncertainty.covariance(i, True)), False,
                     max_mahalanobis2=float(chi2.ppf(GLOBAL_PLAUSIBLE_PROBABILITY, 3)),
                     corroborated_mahalanobis2=float(chi2.ppf(GLOBAL_CORROBORATED_PROBABILITY, 3)))


def descriptor(hits: list[tuple[int, float]], keyframes: list[Keyframe], poses: Array, j: int,
               uncertainty: NodeUncertainty, config: LoopConfig, planar: bool, radius_m: float,
               sector_rad: float) -> list[Candidate]:
    """Candidates from descriptor *hits* ``(place, yaw)``: the same position, the descriptor's relative
    heading (about the sensor's z axis, also in 3D), searched over ± half the overlap radius and ± two
    sectors; vouched like a spatial candidate when the estimate is sure of the pair; plausible only within
    three of the estimate's own search windows when the place is within spatial reach (a symmetric
    corridor looks the same turned round). Where the estimate cannot vouch, the match is held to it as a
    global one is (``GLOBAL_PLAUSIBLE_PROBABILITY``, or ``GLOBAL_CORROBORATED_PROBABILITY`` with an
    independent match that agrees): a place picked by its looks is the same evidence whichever search
    found it, and the three-window box alone let an alias 8.9 σ from an estimate right to 0.7 σ carry a
    group (docs/LOOP_CLOSURE.md, "A place picked by its looks")."""
    win_xy, win_th, _ = windows(uncertainty, config, planar)
    dof = 3 if planar else 6
    gate, corroborated = float(chi2.ppf(GLOBAL_PLAUSIBLE_PROBABILITY, dof)), float(chi2.ppf(GLOBAL_CORROBORATED_PROBABILITY, dof))
    out = []
    for i, yaw in hits:
        est = sensor_relative(keyframes, poses, i, j)
        w = Window(max(config.window_floor_m, 0.5 * radius_m), 2.0 * sector_rad)
        within = win_xy[i] <= config.max_window_m
        vouched = _vouched(win_xy[i], win_th[i], config)
        out.append(Candidate(i, j, Source.DESCRIPTOR, G.xytheta_to_matrix(0.0, 0.0, yaw), w,
                             (est, uncertainty.covariance(i, planar)), vouched,
                             plausible=_plausible(win_xy[i], win_th[i]) if within else None,
                             max_mahalanobis2=None if vouched else gate,
                             corroborated_mahalanobis2=None if vouched else corroborated))
    return out


def hypothesis(i: int, j_from: int, i_T_from: Array, keyframes: list[Keyframe], poses: Array, j: int,
               config: LoopConfig, map_half: int) -> Candidate:
    """Follow the pending closure ``i_sensor_T_{j_from}_sensor`` to the new keyframe *j* along the
    estimate's odometry since *j_from*; searched at the floor window against the local map of ±*map_half*
    keyframes the closure was found against, never vouched for."""
    guess = i_T_from @ sensor_relative(keyframes, poses, j_from, j)
    return Candidate(i, j, Source.HYPOTHESIS, guess, Window(config.window_floor_m, np.radians(config.window_floor_deg)),
                     None, False, map_half)
