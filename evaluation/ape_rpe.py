"""Absolute and relative pose errors (APE / RPE) with the definitions evo uses.

APE (Kümmerle et al. 2009, Sturm et al. IROS 2012 "ATE"): at every associated stamp,
``E_i = P_i⁻¹ Q_i`` (estimate P, reference Q); the translation part is ‖p_i − q_i‖ [m].
RPE (Sturm et al. 2012, eq. 1): for index pairs (i, j),
``E_ij = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)``; the translation part is ‖trans(E_ij)‖ [m].
Pairs are consecutive and non-overlapping (i = 0, Δ, 2Δ, …) for a frame delta, or — for a
travelled-distance delta in metres — the poses at which the reference path accumulated ≥ Δ since
the previous chosen pose (starting at pose 0); with ``all_pairs`` every i is paired with the
later pose whose path distance is closest to Δ (accepted within ``rel_tol·Δ``).

Statistics: rmse = sqrt(mean e²), mean, median, std (population), min, max, sse = Σe².
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core.errors import ConfigError
from core.trajectory import Trajectory

from .trajectory import AlignMode, Alignment, align_trajectory, associate

Array = NDArray[np.float64]

__all__ = [
    "PoseRelation",
    "DeltaUnit",
    "ErrorResult",
    "statistics",
    "pose_errors",
    "ape",
    "rpe",
    "rpe_pairs",
    "evaluate_ape",
    "evaluate_rpe",
]


class PoseRelation(str, Enum):
    """Which part of the error pose E is measured (evo's names in brackets)."""

    trans = "trans"  # ‖trans(E)‖, metres (translation_part)
    rot_deg = "rot_deg"  # |angle(rot(E))|, degrees (rotation_angle_deg)
    rot_rad = "rot_rad"  # |angle(rot(E))|, radians (rotation_angle_rad)
    rot_part = "rot_part"  # ‖rot(E) − I‖_F, unitless (rotation_part)
    full = "full"  # ‖E − I‖_F, unitless (full_transformation)

    @property
    def unit(self) -> str:
        return {"trans": "m", "rot_deg": "deg", "rot_rad": "rad"}.get(self.value, "")


class DeltaUnit(str, Enum):
    """Unit of the RPE delta: frames (pose index) or metres of travelled reference path."""

    frames = "frames"
    m = "m"


def statistics(errors: Array) -> dict[str, float]:
    """rmse, mean, median, std (population, ddof = 0), min, max and sse of an error vector."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        return {k: float("nan") for k in ("rmse", "mean", "median", "std", "min", "max", "sse")}
    return {
        "rmse": float(np.sqrt(np.mean(e * e))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "sse": float(np.sum(e * e)),
    }


def pose_errors(E: Array, relation: PoseRelation | str) -> Array:
    """Scalar error of each error pose ``E (N, 4, 4)`` for the chosen *relation*."""
    relation = PoseRelation(relation)
    E = np.asarray(E, dtype=np.float64).reshape(-1, 4, 4)
    if relation is PoseRelation.trans:
        return np.linalg.norm(E[:, :3, 3], axis=1)
    if relation in (PoseRelation.rot_deg, PoseRelation.rot_rad):
        ang = np.linalg.norm(geo.so3_log(E[:, :3, :3]), axis=1) if len(E) else np.zeros(0)
        return np.degrees(ang) if relation is PoseRelation.rot_deg else ang
    if relation is PoseRelation.rot_part:
        return np.linalg.norm(E[:, :3, :3] - np.eye(3), axis=(1, 2))
    return np.linalg.norm(E - np.eye(4), axis=(1, 2))


def ape(est: Trajectory, ref: Trajectory, relation: PoseRelation | str = PoseRelation.trans) -> Array:
    """Per-pose APE of two associated, aligned trajectories (same length)."""
    if PoseRelation(relation) is PoseRelation.trans:
        return np.linalg.norm(est.positions - ref.positions, axis=1)
    E = geo.inverse(est.poses) @ ref.poses
    return pose_errors(E, relation)


def rpe_pairs(traj: Trajectory, delta: float, unit: DeltaUnit | str = DeltaUnit.frames, all_pairs: bool = False, rel_tol: float = 0.1) -> NDArray[np.int64]:
    """Index pairs ``(M, 2)`` for the RPE, chosen on the path of *traj* (see module doc)."""
    unit = DeltaUnit(unit)
    n = len(traj)
    if delta <= 0:
        raise ConfigError(f"RPE delta must be positive, got {delta}")
    if unit is DeltaUnit.frames:
        step = int(delta)
        if step != delta:
            raise ConfigError(f"a frame delta must be an integer, got {delta}")
        if all_pairs:
            i = np.arange(max(n - step, 0))
        else:
            i = np.arange(0, n, step)[:-1] if n else np.zeros(0, np.int64)
        return np.column_stack([i, i + step]).astype(np.int64)
    steps = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1) if n > 1 else np.zeros(0)
    dist = np.concatenate([[0.0], np.cumsum(steps)])
    if all_pairs:
        # For each start i the later pose whose path distance is closest to delta (earliest on ties):
        # the path length is non-decreasing, so the two neighbours of dist[i] + delta decide.
        if n < 2:
            return np.zeros((0, 2), np.int64)
        i = np.arange(n - 1)
        target = dist[:-1] + delta
        hi = np.clip(np.searchsorted(dist, target, side="left"), i + 1, n - 1)
        hi = np.maximum(np.searchsorted(dist, dist[hi], side="left"), i + 1)  # first pose with that distance
        lo = np.maximum(hi - 1, i + 1)
        lo = np.maximum(np.searchsorted(dist, dist[lo], side="left"), i + 1)
        d_hi = np.abs(dist[hi] - dist[i] - delta)
        d_lo = np.abs(dist[lo] - dist[i] - delta)
        k = np.where(d_lo <= d_hi, lo, hi)
        ok = np.abs(dist[k] - dist[i] - delta) <= rel_tol * delta
        return np.column_stack([i[ok], k[ok]]).astype(np.int64)
    # Greedy: the path accumulated since the last chosen pose reaches delta. Sequential by
    # nature (each choice resets the counter), but one pass over scalar steps.
    ids = [0]
    acc = 0.0
    for k, s in enumerate(steps.tolist(), start=1):
        acc += s
        if acc >= delta:
            ids.append(k)
            acc = 0.0
    idx = np.array(ids, dtype=np.int64)
    return np.column_stack([idx[:-1], idx[1:]])


def rpe(est: Trajectory, ref: Trajectory, pairs: NDArray[np.int64], relation: PoseRelation | str = PoseRelation.trans) -> Array:
    """Per-pair RPE ``E_ij = (Q_i⁻¹Q_j)⁻¹ (P_i⁻¹P_j)`` of two associated trajectories."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    i, j = pairs[:, 0], pairs[:, 1]
    Q = geo.relative(ref.poses[i], ref.poses[j])
    P = geo.relative(est.poses[i], est.poses[j])
    return pose_errors(geo.relative(Q, P), relation)


@dataclass
class ErrorResult:
    """The outcome of an APE or RPE evaluation.

    ``errors`` are in ``unit`` (m, deg, rad or unitless); ``stamps`` are the (reference)
    stamps the errors belong to (for RPE, the stamp of the second pose of each pair).
    """

    metric: str  # "ape" or "rpe"
    relation: str
    unit: str
    errors: Array
    stamps: Array
    stats: dict[str, float]
    n_matched: int
    alignment: Alignment | None = None
    pairs: NDArray[np.int64] | None = None
    est_aligned: Trajectory | None = None
    ref_matched: Trajectory | None = None
    settings: dict[str, object] = field(default_factory=dict)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary (statistics, counts, settings, alignment)."""
        out: dict[str, object] = {
            "metric": self.metric,
            "relation": self.relation,
            "unit": self.unit,
            "n_matched": self.n_matched,
            "n_errors": int(len(self.errors)),
            **self.stats,
            "settings": self.settings,
        }
        if self.alignment is not None:
            out["alignment"] = {
                "transform": self.alignment.transform.tolist(),
                "scale": self.alignment.scale,
                "planar": self.alignment.planar,
            }
        return out


def evaluate_ape(
    est: Trajectory,
    ref: Trajectory,
    align: AlignMode | str = AlignMode.none,
    relation: PoseRelation | str = PoseRelation.trans,
    max_diff: float = 0.01,
    offset: float = 0.0,
) -> ErrorResult:
    """Associate, align (default none, as ``evo_ape``) and compute the APE."""
    relation = PoseRelation(relation)
    e, r = associate(est, ref, max_diff, offset)
    e_al, al = align_trajectory(e, r, align)
    errs = ape(e_al, r, relation)
    return ErrorResult(
        "ape", relation.value, relation.unit, errs, r.stamps, statistics(errs), len(r), al,
        None, e_al, r, {"align": AlignMode(align).value, "max_diff": max_diff, "offset": offset},
    )


def evaluate_rpe(
    est: Trajectory,
    ref: Trajectory,
    delta: float = 1,
    delta_unit: DeltaUnit | str = DeltaUnit.frames,
    relation: PoseRelation | str = PoseRelation.trans,
    align: AlignMode | str = AlignMode.none,
    all_pairs: bool = False,
    rel_tol: float = 0.1,
    max_diff: float = 0.01,
    offset: float = 0.0,
    pairs_from_reference: bool = False,
) -> ErrorResult:
    """Associate, align (default none, as ``evo_rpe``) and compute the RPE.

    Pairs for a metric delta come from the aligned estimate's path unless *pairs_from_reference*
    (evo's ``--pairs_from_reference``).
    """
    relation = PoseRelation(relation)
    e, r = associate(est, ref, max_diff, offset)
    e_al, al = align_trajectory(e, r, align)
    pairs = rpe_pairs(r if pairs_from_reference else e_al, delta, delta_unit, all_pairs, rel_tol)
    errs = rpe(e_al, r, pairs, relation)
    return ErrorResult(
        "rpe", relation.value, relation.unit, errs, r.stamps[pairs[:, 1]], statistics(errs), len(r), al, pairs, e_al, r,
        {"delta": delta, "delta_unit": DeltaUnit(delta_unit).value, "all_pairs": all_pairs, "align": AlignMode(align).value,
         "pairs_from_reference": pairs_from_reference,
         "max_diff": max_diff, "offset": offset},
    )
