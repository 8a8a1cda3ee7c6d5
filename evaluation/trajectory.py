"""Associating two trajectories by time and aligning them (Umeyama SE(3) / Sim(3), 2D-aware).

Association follows the nearest-stamp rule evo uses: the trajectory with fewer poses is kept
whole and each of its stamps is paired with the closest stamp of the other, if that is within
``max_diff`` seconds (on an exact tie the earlier stamp wins).

Alignment: S. Umeyama, "Least-squares estimation of transformation parameters between two
point patterns", IEEE TPAMI 13(4), 1991, eqs. (34)–(42): the rotation, translation and
(optionally) scale minimising Σ‖y_i − (s R x_i + t)‖². For planar trajectories the problem is
solved in 2D, so that the rotation stays about z even when the best 2D fit is degenerate.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from core.errors import DegenerateInputError, GpslamError
from core.trajectory import Trajectory

Array = NDArray[np.float64]

__all__ = ["AlignMode", "Alignment", "AssociationError", "associate", "umeyama", "align_trajectory"]


class AssociationError(GpslamError, ValueError):
    """No (or too few) stamps of the two trajectories match within the tolerance."""


class AlignMode(str, Enum):
    """How the estimate is aligned to the reference before computing errors."""

    none = "none"
    se3 = "se3"
    sim3 = "sim3"


@dataclass(frozen=True)
class Alignment:
    """``ref ≈ s · R · est + t`` applied to the estimate: a 4×4 rigid part and a scale."""

    transform: Array  # (4, 4), rotation R and translation t
    scale: float
    planar: bool  # solved in 2D


def nearest_indices(short_stamps: Array, long_stamps: Array, max_diff: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For every stamp of *short_stamps*, the index of the nearest of *long_stamps* (vectorised).

    Returns ``(i_short, i_long)`` of the pairs whose time difference is ≤ *max_diff* seconds.
    On an exact tie the earlier of the two neighbours is chosen.
    """
    s = np.asarray(short_stamps, dtype=np.float64)
    L = np.asarray(long_stamps, dtype=np.float64)
    if len(s) == 0 or len(L) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(L, kind="stable")
    Ls = L[order]
    hi = np.clip(np.searchsorted(Ls, s, side="right"), 0, len(Ls) - 1)
    lo = np.clip(hi - 1, 0, len(Ls) - 1)
    d_hi = np.abs(Ls[hi] - s)
    d_lo = np.where(hi > 0, np.abs(s - Ls[lo]), np.inf)
    take_lo = d_lo <= d_hi
    best = np.where(take_lo, lo, hi)
    dist = np.where(take_lo, d_lo, d_hi)
    ok = dist <= max_diff
    return np.nonzero(ok)[0].astype(np.int64), order[best[ok]].astype(np.int64)


def associate(est: Trajectory, ref: Trajectory, max_diff: float = 0.01, offset: float = 0.0) -> tuple[Trajectory, Trajectory]:
    """Pair the poses of *est* and *ref* by stamp (evo's nearest-time rule).

    Args:
        est, ref: trajectories; stamps in seconds.
        max_diff: largest accepted stamp difference, seconds.
        offset: added to the reference stamps before matching, seconds.

    Returns:
        ``(est_matched, ref_matched)``, equal lengths, in the order of the shorter trajectory.
    """
    ref_st = ref.stamps + offset
    if len(ref) > len(est):
        i_est, i_ref = nearest_indices(est.stamps, ref_st, max_diff)
    else:
        i_ref, i_est = nearest_indices(ref_st, est.stamps, max_diff)
    if len(i_est) == 0:
        raise AssociationError(
            f"no stamps of {est.name or 'the estimate'} and {ref.name or 'the reference'} match within {max_diff} s"
        )
    return est.subset(i_est), ref.subset(i_ref)


def umeyama(src: Array, dst: Array, with_scale: bool = False) -> tuple[Array, Array, float]:
    """Umeyama (1991) eqs. (34)–(42): ``R, t, s`` minimising Σ‖dst_i − (s R src_i + t)‖².

    Args:
        src, dst: ``(N, d)`` corresponding points, d = 2 or 3.
        with_scale: estimate the scale s (Sim(d)); otherwise s = 1 (SE(d)).

    Returns:
        ``(R (d, d), t (d,), s)``.
    """
    X = np.asarray(src, dtype=np.float64)
    Y = np.asarray(dst, dtype=np.float64)
    if X.shape != Y.shape or X.ndim != 2:
        raise DegenerateInputError(f"umeyama needs two (N, d) arrays of equal shape, got {X.shape} and {Y.shape}")
    n, d = X.shape
    if n < 2:
        raise DegenerateInputError(f"umeyama needs at least 2 point pairs, got {n}")
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    sigma_x = (Xc**2).sum() / n  # eq. (36)
    cov = Yc.T @ Xc / n  # eq. (38)
    U, D, Vt = np.linalg.svd(cov)
    S = np.ones(d)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # eq. (39)
        S[-1] = -1.0
    R = (U * S) @ Vt  # eq. (40)
    if with_scale:
        if sigma_x <= 0:
            raise DegenerateInputError("umeyama with scale: the source points are all identical")
        s = float((D * S).sum() / sigma_x)  # eq. (42)
    else:
        s = 1.0
    t = my - s * R @ mx  # eq. (41)
    return R, t, s


def align_trajectory(est: Trajectory, ref: Trajectory, mode: AlignMode | str = AlignMode.se3, planar: bool | None = None) -> tuple[Trajectory, Alignment]:
    """Align associated *est* onto *ref* (positions only, as evo does): ``est' = s R est + t``.

    The rotations of *est* are rotated by R; with ``sim3`` the positions are also scaled by s.
    *planar* = None solves in 2D when both trajectories are planar.
    """
    mode = AlignMode(mode)
    if len(est) != len(ref):
        raise AssociationError(f"alignment needs associated trajectories, got {len(est)} and {len(ref)} poses")
    if mode is AlignMode.none:
        return est, Alignment(np.eye(4), 1.0, False)
    if planar is None:
        planar = est.is_planar() and ref.is_planar()
    T = np.eye(4)
    if planar:
        R2, t2, s = umeyama(est.positions[:, :2], ref.positions[:, :2], mode is AlignMode.sim3)
        T[:2, :2] = R2
        T[:2, 3] = t2
    else:
        R3, t3, s = umeyama(est.positions, ref.positions, mode is AlignMode.sim3)
        T[:3, :3] = R3
        T[:3, 3] = t3
    P = est.poses.copy()
    P[:, :3, 3] *= s
    P = T @ P
    return Trajectory(est.stamps, P, est.name), Alignment(T, float(s), bool(planar))
