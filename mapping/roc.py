"""ROC curve and AUC of an occupancy-probability map against a ground-truth map.

As in Yuan et al. 2018 §V (and O'Callaghan & Ramos 2012 §6): every cell known in the ground truth
is a sample (occupied = positive), scored by its occupancy probability; unknown ground-truth cells
are ignored. AUC is the Mann–Whitney statistic with ties counted one half (Hanley & McNeil 1982),
which equals the trapezoidal area under the ROC curve.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from registration.errors import DegenerateInputError

Array = NDArray[np.float64]


def roc_curve(scores: Array, positive: NDArray[np.bool_]) -> tuple[Array, Array, Array]:
    """(false-positive rate, true-positive rate, thresholds), thresholds descending, starting at (0, 0)."""
    s = np.asarray(scores, dtype=float).ravel()
    y = np.asarray(positive, dtype=bool).ravel()
    P, N = int(y.sum()), int((~y).sum())
    if P == 0 or N == 0:
        raise DegenerateInputError(f"ROC needs positive and negative cells, got {P} occupied and {N} free")
    order = np.argsort(-s, kind="stable")
    s, y = s[order], y[order]
    last = np.r_[np.flatnonzero(np.diff(s)), len(s) - 1]  # last index of each distinct score
    tp = np.cumsum(y)[last]
    fp = (last + 1) - tp
    return np.r_[0.0, fp / N], np.r_[0.0, tp / P], np.r_[np.inf, s[last]]


def roc_auc(scores: Array, positive: NDArray[np.bool_]) -> float:
    """Area under the ROC curve (trapezoidal over distinct thresholds = Mann–Whitney with half ties)."""
    fpr, tpr, _ = roc_curve(scores, positive)
    return float(np.trapezoid(tpr, fpr))


def map_roc(probability: Array, gt_classes: NDArray[np.int8]) -> tuple[Array, Array, float]:
    """ROC (fpr, tpr) and AUC of a probability grid against ground-truth classes of the same shape.

    Cells with class −1 (unknown) are ignored; class ≥ 50 counts as occupied (the classes are 0/100).
    """
    p = np.asarray(probability, dtype=float)
    g = np.asarray(gt_classes)
    if p.shape != g.shape:
        raise DegenerateInputError(f"map {p.shape} and ground truth {g.shape} differ in shape")
    keep = (g != -1) & np.isfinite(p)
    fpr, tpr, _ = roc_curve(p[keep], g[keep] >= 50)
    return fpr, tpr, float(np.trapezoid(tpr, fpr))


def resample_to_grid(probability: Array, observed: NDArray[np.bool_], origin: Array, resolution: float,
                     target_shape: tuple[int, int], target_origin: Array, target_resolution: float) -> Array:
    """Probability at the centres of another (axis-aligned) grid by nearest cell; 0.5 outside / unobserved."""
    ty = target_origin[1] + (np.arange(target_shape[0]) + 0.5) * target_resolution
    tx = target_origin[0] + (np.arange(target_shape[1]) + 0.5) * target_resolution
    iy = np.floor((ty - origin[1]) / resolution).astype(np.int64)
    ix = np.floor((tx - origin[0]) / resolution).astype(np.int64)
    h, w = probability.shape
    oky, okx = (iy >= 0) & (iy < h), (ix >= 0) & (ix < w)
    out = np.full(target_shape, 0.5)
    sub = np.ix_(np.flatnonzero(oky), np.flatnonzero(okx))
    src = np.ix_(iy[oky], ix[okx])
    out[sub] = np.where(observed[src], probability[src], 0.5)
    return out
