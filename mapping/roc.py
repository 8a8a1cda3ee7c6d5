"""ROC curve and AUC of an occupancy-probability map against a ground-truth map.

As in Yuan et al. 2018 §V (and O'Callaghan & Ramos 2012 §6): every cell known in the ground truth
is a sample (occupied = positive), scored by its occupancy probability; unknown ground-truth cells
are ignored. AUC is the Mann–Whitney statistic with ties counted one half (Hanley & McNeil 1982),
which equals the trapezoidal area under the ROC curve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core.errors import DegenerateInputError

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


@dataclass(frozen=True)
class MapScores:
    """A map's scores against a ground truth on the ground truth's grid (:func:`map_scores`).

    Attributes:
        auc: ROC AUC over every known ground-truth cell, unobserved ones scored 0.5 (Yuan et al. 2018).
        auc_observed: the same over the known cells the map observed (None when they are all one class).
        coverage: fraction of the ground truth's free space (:func:`free_space`) the map observed.
        accuracy, accuracy_threshold: the best accuracy over occupancy thresholds (occupied ≥ threshold) and
            its threshold, over every known cell.
        f1, f1_threshold: the best F1 score of the occupied class and its threshold.
    """

    auc: float
    auc_observed: float | None
    coverage: float
    accuracy: float
    accuracy_threshold: float
    f1: float
    f1_threshold: float

    def as_dict(self) -> dict:
        return dict(vars(self))


MIN_SPACE_M2 = 0.5  # isolated pieces of free cells smaller than this are specks, not space


def free_space(gt_classes: NDArray[np.int8], resolution: float) -> tuple[NDArray[np.bool_], int, float]:
    """A plan's free space: its free cells (class 0…49) whose 8-connected piece of free cells covers at least
    MIN_SPACE_M2. Returns the mask and the number and area (m²) of the specks left out: isolated free cells
    a drawing leaves outside its walls, which no laser inside sees and no robot enters."""
    from scipy import ndimage

    g = np.asarray(gt_classes)
    labels, n = ndimage.label((g >= 0) & (g < 50), structure=np.ones((3, 3), bool))
    cells = np.bincount(labels.ravel(), minlength=n + 1)
    cells[0] = 0
    big = cells * resolution**2 >= MIN_SPACE_M2
    big[0] = False
    small = (cells > 0) & ~big
    return big[labels], int(small.sum()), float(cells[small].sum() * resolution**2)


def map_scores(probability: Array, observed: NDArray[np.bool_], gt_classes: NDArray[np.int8],
               resolution: float | None = None) -> MapScores:
    """:class:`MapScores` of a probability grid with its *observed* mask against ground-truth classes of the same
    shape (−1 unknown, ≥ 50 occupied). Accuracy and F1 are read off the ROC's counts at every distinct
    threshold, so the best of each is exact. With the plan's *resolution* (m) the coverage leaves out
    its specks (:func:`free_space`); without, it counts every free cell."""
    p = np.asarray(probability, dtype=float)
    obs = np.asarray(observed, dtype=bool)
    g = np.asarray(gt_classes)
    if not (p.shape == obs.shape == g.shape):
        raise DegenerateInputError(f"map {p.shape}, observed {obs.shape} and ground truth {g.shape} differ in shape")
    known = (g != -1) & np.isfinite(p)
    occupied = g >= 50
    fpr, tpr, thr = roc_curve(p[known], occupied[known])
    auc = float(np.trapezoid(tpr, fpr))
    seen = known & obs
    try:
        auc_observed: float | None = roc_auc(p[seen], occupied[seen])
    except DegenerateInputError:
        auc_observed = None
    free = known & ~occupied
    P, N = int((known & occupied).sum()), int(free.sum())
    tp, fp = tpr * P, fpr * N
    accuracy = (tp + (N - fp)) / (P + N)
    f1 = 2 * tp / np.maximum(2 * tp + fp + (P - tp), 1e-300)
    a, f = int(np.argmax(accuracy)), int(np.argmax(f1))
    space = free if resolution is None else free & free_space(g, resolution)[0]
    return MapScores(auc, auc_observed, float((space & obs).sum() / max(int(space.sum()), 1)), float(accuracy[a]),
                     float(thr[a]),
                     float(f1[f]), float(thr[f]))


def observed_on_grid(observed: NDArray[np.bool_], origin: Array, resolution: float, target_shape: tuple[int, int],
                     target_origin: Array, target_resolution: float) -> NDArray[np.bool_]:
    """The *observed* mask at the centres of another (axis-aligned) grid by nearest cell; False outside."""
    return resample_to_grid(np.ones(observed.shape), observed, origin, resolution, target_shape, target_origin,
                            target_resolution) == 1.0


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
