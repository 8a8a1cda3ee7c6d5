"""A self-check of a finished run, without ground truth: does the result contradict its own data?

Two symptoms of a wrong map, both measured on the final solution:

1. **Closure residuals.** Each accepted loop closure (kept and pruned alike) against the final
   relative pose of its keyframes: the fraction violated by more than Cartographer's 20 cm / 1°
   (Hess et al. 2016, §VII-B) decides; the squared Mahalanobis distance under the closure's own
   covariance, and how many lie beyond the χ²(dof) quantile ``closure_probability``, are reported
   beside it (closure covariances are tighter than their errors on long-range scans).
2. **Scans that contradict the map.** A keyframe's scan contradicts the map where its points fall
   into free space another keyframe observed at the same place (its beams passed through): the
   negative-information test of scan matching (Olson 2009, §III-B) applied to the final poses, between
   each keyframe and the nearest keyframes of *other* passes (the trajectory between them is longer
   than their distance plus twice the reach). A corridor mapped twice, 3 m apart, or a room rotated onto another, puts one copy's walls
   into the other's observed free space; moving people and doors account for a few per cent.

**A wrong pose or a changed world.** Cars parked in one pass and gone in the next, or furniture moved,
contradict both ways as a misplaced scan does. What tells them apart is whether *some* placement
explains the contradiction: a contradicting pair is re-aligned by a correlative search of the one
scan on the other around the map's relative pose, in three windows (±0.5 m / ±10°, ±3 m / ±30°, ±5 m
at every heading; each window's best-scoring pose). When one of those poses cuts the contradiction to
half, the map placed the scans wrong and the pair counts. When none does, no pose could remove it:
the world changed between the passes, and the keyframe is reported as changed
(``keyframes_changed``), not held against the map — the distinction Hähnel, Triebel, Burgard & Thrun
("Map building with mobile robots in dynamic environments", ICRA 2003) draw between measurements of
dynamic objects and of a wrongly placed static world. A map misplaced by more than the widest window
reads as changed: the windows bound what the check can see.

The verdict is ``consistent`` when both fractions stay below their limits, else ``suspect``, with
the keyframe ranges (and times) where the contradictions cluster.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.stats import chi2

from core import geometry as G
from core.errors import DegenerateInputError
from registration import correlative
from slam.keyframes import Keyframe
from slam.loops.types import LoopClosure
from slam.loops.verify import free_space_violation

Array = NDArray[np.float64]


@dataclass(frozen=True)
class SelfCheckConfig:
    """Limits of the verdict (algorithm constants; ``docs/LOOP_CLOSURE.md`` has the development-set figures)."""

    closure_probability: float = 0.999  # χ² quantile a satisfied closure stays within
    max_violated_closures: float = 0.05  # fraction of closures the solution violates by more than 20 cm / 1°
    neighbours: int = 3  # nearest keyframes of other passes each keyframe is checked against
    scan_violation: float = 0.15  # a keyframe contradicts the map when this fraction of its points lies in another's free space ...
    max_contradicting_keyframes: float = 0.03  # ... and the map is suspect when this fraction of keyframes do
    exclude_recent_keyframes: int = 15  # keyframes this close in sequence are the same pass
    min_overlap: float = 0.3  # a pair counts in a direction when this fraction of the points falls on the other's returned beams
    margin_m: float = 0.2  # a point contradicts a beam that returned this much (plus 2 % of the range) beyond it
    max_neighbour_distance_m: float | None = None  # None: the median range of the keyframe's scan
    # A contradicting pair is a wrong placement when the best alignment of one scan on the other within one of
    # these windows (± m in x and y, ± degrees) leaves at most explained_fraction of its contradiction.
    realign_windows: tuple[tuple[float, float], ...] = ((0.5, 10.0), (3.0, 30.0), (5.0, 180.0))
    explained_fraction: float = 0.5
    realign_resolution_m: float = 0.1  # cells of the correlative search ...
    realign_max_range_m: float = 10.0  # ... of the points this near the sensor (the farthest sets the angular step)
    max_realignments: int = 2000  # pairs re-aligned at most (~10 ms each); beyond, a contradiction counts against the map


@dataclass
class SelfCheck:
    """Outcome of :func:`self_check` (``summary.json`` ``self_check``)."""

    verdict: str
    closures: int
    closures_violated: int  # beyond the χ² quantile
    closures_violated_20cm_1deg: int
    median_closure_chi2: float
    keyframes_checked: int
    keyframes_contradicting: int
    where: list[dict] = field(default_factory=list)  # clusters of contradicting keyframes: first/last id and stamp
    keyframes_changed: int = 0  # keyframes whose contradictions no placement explains: the world changed between passes
    start_stamp: float = 0.0  # of the first keyframe, so that the stamps above read as times into the log

    def as_dict(self) -> dict:
        return dict(vars(self))


def closure_chi2(closures: list[LoopClosure], poses: Array, planar: bool) -> Array:
    """Squared Mahalanobis distance of each closure from the solution's relative pose of its keyframes."""
    out = np.zeros(len(closures))
    for k, lc in enumerate(closures):
        d = G.relative(lc.measurement, G.relative(poses[lc.i], poses[lc.j]))
        e = G.se2_log(d) if planar else G.se3_log(d)
        out[k] = float(e @ np.linalg.solve(lc.covariance, e))
    return out


def contradictions(keyframes: list[Keyframe], poses: Array, config: SelfCheckConfig) -> tuple[Array, Array, Array]:
    """Per keyframe, the median over its ``neighbours`` nearest keyframes of other passes of the fraction of
    points one scan of the pair has in the other's observed free space, the smaller of the two
    directions; whether it was checked at all (it has such neighbours within reach that overlap
    it); and the same median with the pairs no placement explains (:func:`misplaced`) left in, which
    the first leaves out. Both directions: a scan placed wrong puts its walls into the other's free
    space and the other's into its own, while a door closed in one pass or a person walking past
    contradicts one direction only. The median over neighbours: a misplaced map contradicts every
    pass. 2D only."""
    K = len(keyframes)
    values: list[list[float]] = [[] for _ in range(K)]
    raw: list[list[float]] = [[] for _ in range(K)]
    if K < 2 or keyframes[0].frame.angles is None:
        return np.zeros(K), np.zeros(K, dtype=bool), np.zeros(K)
    world_T_sensor = np.einsum("nij,njk->nik", poses, np.array([kf.base_T_sensor for kf in keyframes]))
    xy = world_T_sensor[:, :2, 3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    tree = cKDTree(xy)
    k_query = min(K, 4 * config.neighbours + 2 * config.exclude_recent_keyframes + 1)
    dist, idx = tree.query(xy, k=k_query)
    done: set[tuple[int, int]] = set()
    realigned = 0
    m = config.min_overlap
    for j in range(K):
        reach = config.max_neighbour_distance_m
        if reach is None:
            r = np.linalg.norm(keyframes[j].points[:, :2], axis=1)
            reach = float(np.median(r)) if len(r) else 1.0
        taken = 0
        for d, i in zip(dist[j], idx[j]):
            if taken >= config.neighbours or not np.isfinite(d) or d > reach:
                break
            i = int(i)
            if abs(i - j) <= config.exclude_recent_keyframes or abs(path[i] - path[j]) < d + 2.0 * reach:
                continue  # the same pass: the trajectory did not leave and come back
            pair = (min(i, j), max(i, j))
            if pair in done:
                taken += 1
                continue
            i_T_j = G.relative(world_T_sensor[i], world_T_sensor[j])
            v_i, v_j = _violations(keyframes[i], keyframes[j], i_T_j, config)
            if v_i == 0.0 and v_j == 0.0 and not _overlaps(keyframes[i], keyframes[j], i_T_j, m):
                continue  # too little overlap to say anything
            done.add(pair)
            taken += 1
            v = min(v_i, v_j)  # both ways: a door or a person in one scan contradicts only the other
            raw[i].append(v)
            raw[j].append(v)
            if v > config.scan_violation and realigned < config.max_realignments:
                realigned += 1
                if not misplaced(keyframes[i], keyframes[j], i_T_j, v, config):
                    v = 0.0  # no placement explains it: the world changed between the passes
            values[i].append(v)
            values[j].append(v)
    checked = np.array([len(v) > 0 for v in values])
    med = np.array([float(np.median(v)) if v else 0.0 for v in values])
    med_raw = np.array([float(np.median(v)) if v else 0.0 for v in raw])
    return med, checked, med_raw


def _violations(ki: Keyframe, kj: Keyframe, i_T_j: Array, config: SelfCheckConfig) -> tuple[float, float]:
    """The pair's free-space violations at the relative pose *i_T_j*: *ki*'s points in *kj*'s free space, and
    *kj*'s in *ki*'s."""
    v_j = free_space_violation(G.transform_points(i_T_j, kj.frame.points), ki, margin=config.margin_m,
                               min_inside=config.min_overlap)
    v_i = free_space_violation(G.transform_points(G.inverse(i_T_j), ki.frame.points), kj, margin=config.margin_m,
                               min_inside=config.min_overlap)
    return v_i, v_j


def _pair_violation(ki: Keyframe, kj: Keyframe, i_T_j: Array, config: SelfCheckConfig) -> float:
    """The smaller of the two directions of :func:`_violations`."""
    return min(_violations(ki, kj, i_T_j, config))


def misplaced(ki: Keyframe, kj: Keyframe, i_T_j: Array, violation: float, config: SelfCheckConfig) -> bool:
    """Whether the contradiction *violation* of the pair at the map's relative pose *i_T_j* (sensor frames)
    is the map's: the best-scoring placement of *kj*'s scan on *ki*'s within one of ``realign_windows``
    (correlative branch and bound, :func:`registration.correlative.match`) leaves at most
    ``explained_fraction`` of it. False when no window's placement does (the world changed)."""
    res = config.realign_resolution_m

    def near(points: Array) -> Array:
        return points[np.hypot(points[:, 0], points[:, 1]) <= config.realign_max_range_m, :2]

    target, scan = near(ki.frame.points), near(kj.frame.points)
    if len(target) < 3:
        return True  # too few points to say: count it against the map
    pyramid = correlative.LikelihoodPyramid(target, res, res, levels=6)
    start = G.xytheta_to_matrix(*G.matrix_to_xytheta(i_T_j))
    for window_m, window_deg in config.realign_windows:
        try:
            found = correlative.match(scan, pyramid, start, window_m, np.radians(window_deg))
        except DegenerateInputError:
            return True  # too few points to say: count it against the map
        if _pair_violation(ki, kj, found.transform, config) <= config.explained_fraction * violation:
            return True
    return False


def _overlaps(ki: Keyframe, kj: Keyframe, i_T_j: Array, min_inside: float) -> bool:
    """Whether at least *min_inside* of *kj*'s points fall within *ki*'s field of view (on returned beams)."""
    pts = G.transform_points(i_T_j, kj.frame.points)
    return free_space_violation(pts, ki, margin=-1e9, rel_margin=0.0, min_inside=min_inside) > 0.0


def _clusters(ids: NDArray[np.int64], keyframes: list[Keyframe], gap: int) -> list[dict]:
    """Runs of keyframe ids no more than *gap* apart, with their first and last stamps."""
    out: list[dict] = []
    for k in ids:
        if out and k - out[-1]["last_keyframe"] <= gap:
            out[-1]["last_keyframe"] = int(k)
            out[-1]["last_stamp"] = float(keyframes[k].stamp)
            out[-1]["keyframes"] += 1
        else:
            out.append({"first_keyframe": int(k), "last_keyframe": int(k), "first_stamp": float(keyframes[k].stamp),
                        "last_stamp": float(keyframes[k].stamp), "keyframes": 1})
    return out


def self_check(keyframes: list[Keyframe], poses: Array, closures: list[LoopClosure], planar: bool,
               config: SelfCheckConfig = SelfCheckConfig()) -> SelfCheck:
    """The run's self-check (see the module docstring) from its keyframes, final keyframe poses and every
    closure the verifier accepted (pruned ones included)."""
    dof = 3 if planar else 6
    m2 = closure_chi2(closures, poses, planar)
    gate = float(chi2.ppf(config.closure_probability, dof))
    n_bad = int(np.count_nonzero(m2 > gate))
    crit = 0
    for lc in closures:
        d = G.relative(lc.measurement, G.relative(poses[lc.i], poses[lc.j]))
        if np.linalg.norm(d[:3, 3]) > 0.2 or np.degrees(G.rotation_angle(d[:3, :3])) > 1.0:
            crit += 1
    K = len(keyframes)
    worst, checked, raw = contradictions(keyframes, poses, config) if planar else (np.zeros(K), np.zeros(K, bool), np.zeros(K))
    bad_kf = np.flatnonzero(checked & (worst > config.scan_violation))
    changed = int(np.count_nonzero(checked & (raw > config.scan_violation) & ~(worst > config.scan_violation)))
    frac_closures = crit / len(closures) if closures else 0.0
    frac_kf = len(bad_kf) / max(int(checked.sum()), 1)
    ok = frac_closures <= config.max_violated_closures and frac_kf <= config.max_contradicting_keyframes
    return SelfCheck("consistent" if ok else "suspect", len(closures), n_bad, crit,
                     float(np.median(m2)) if len(m2) else 0.0, int(checked.sum()), len(bad_kf),
                     _clusters(bad_kf, keyframes, config.exclude_recent_keyframes), keyframes_changed=changed,
                     start_stamp=float(keyframes[0].stamp) if keyframes else 0.0)
