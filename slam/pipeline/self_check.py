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


def contradictions(keyframes: list[Keyframe], poses: Array, config: SelfCheckConfig) -> tuple[Array, Array]:
    """Per keyframe, the median over its ``neighbours`` nearest keyframes of other passes of the fraction of
    points one scan of the pair has in the other's observed free space, the smaller of the two
    directions, and whether it was checked at all (it has such neighbours within reach that overlap
    it). Both directions: a scan placed wrong puts its walls into the other's free space and the
    other's into its own, while a door closed in one pass or a person walking past contradicts one
    direction only. The median over neighbours: a misplaced map contradicts every pass. 2D only."""
    K = len(keyframes)
    values: list[list[float]] = [[] for _ in range(K)]
    if K < 2 or keyframes[0].frame.angles is None:
        return np.zeros(K), np.zeros(K, dtype=bool)
    world_T_sensor = np.einsum("nij,njk->nik", poses, np.array([kf.base_T_sensor for kf in keyframes]))
    xy = world_T_sensor[:, :2, 3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    tree = cKDTree(xy)
    k_query = min(K, 4 * config.neighbours + 2 * config.exclude_recent_keyframes + 1)
    dist, idx = tree.query(xy, k=k_query)
    done: set[tuple[int, int]] = set()
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
            v_j = free_space_violation(G.transform_points(i_T_j, keyframes[j].frame.points), keyframes[i],
                                       margin=config.margin_m, min_inside=m)
            v_i = free_space_violation(G.transform_points(G.inverse(i_T_j), keyframes[i].frame.points), keyframes[j],
                                       margin=config.margin_m, min_inside=m)
            if v_i == 0.0 and v_j == 0.0 and not _overlaps(keyframes[i], keyframes[j], i_T_j, m):
                continue  # too little overlap to say anything
            done.add(pair)
            taken += 1
            v = min(v_i, v_j)  # both ways: a door or a person in one scan contradicts only the other
            values[i].append(v)
            values[j].append(v)
    checked = np.array([len(v) > 0 for v in values])
    med = np.array([float(np.median(v)) if v else 0.0 for v in values])
    return med, checked


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
    worst, checked = contradictions(keyframes, poses, config) if planar else (np.zeros(len(keyframes)), np.zeros(len(keyframes), bool))
    bad_kf = np.flatnonzero(checked & (worst > config.scan_violation))
    frac_closures = crit / len(closures) if closures else 0.0
    frac_kf = len(bad_kf) / max(int(checked.sum()), 1)
    ok = frac_closures <= config.max_violated_closures and frac_kf <= config.max_contradicting_keyframes
    return SelfCheck("consistent" if ok else "suspect", len(closures), n_bad, crit,
                     float(np.median(m2)) if len(m2) else 0.0, int(checked.sum()), len(bad_kf),
                     _clusters(bad_kf, keyframes, config.exclude_recent_keyframes),
                     float(keyframes[0].stamp) if keyframes else 0.0)
