"""A global Gaussian occupancy grid in information form, and the hyperparameter policy.

Cells hold ``info = Σ μᵢ/σᵢ²`` and ``prec = Σ 1/σᵢ²`` (BCM, see :mod:`mapping.bcm`); μ is the GP
latent occupancy (+1 occupied, −1 free), dimensionless. The grid lives in the world frame.
"""

from __future__ import annotations

import warnings

import numpy as np
from numpy.typing import NDArray

from .bcm import MIN_VARIANCE, mean_variance, probit_squash
from .config import GPConfig
from .gp import GaussianProcess, GPHyperparameters, fit_hyperparameters
from .grid import GridGeometry

Array = NDArray[np.float64]


class GaussianGrid:
    """(info, prec) arrays of shape ``geometry.shape`` indexed [iy, ix]."""

    def __init__(self, geometry: GridGeometry) -> None:
        self.geometry = geometry
        self.info = np.zeros(geometry.shape)
        self.prec = np.zeros(geometry.shape)

    def fuse_window(self, rows: slice, cols: slice, sel: NDArray[np.bool_] | NDArray[np.int64],
                    mean: Array, var: Array) -> None:
        """BCM-fuse estimates into the cells ``window[sel]`` (sel: mask or flat indices of the window)."""
        if isinstance(sel, np.ndarray) and sel.dtype == bool:
            sel = np.flatnonzero(sel)
        w = cols.stop - cols.start
        g = (rows.start + sel // w) * self.geometry.shape[1] + cols.start + sel % w
        p = 1.0 / np.maximum(var, MIN_VARIANCE)
        self.info.reshape(-1)[g] += mean * p  # window indices are unique: fancy += is exact
        self.prec.reshape(-1)[g] += p

    def mean_variance(self, prior_variance: float = np.inf) -> tuple[Array, Array]:
        return mean_variance(self.info, self.prec, prior_variance)

    def to_map(self, alpha: float = 100.0, beta: float = 0.0, method: str = "fastgpom"):
        """The :class:`~mapping.occupancy_map.OccupancyMap` (μ, σ², p) of this grid."""
        from .occupancy_map import OccupancyMap

        mean, var = self.mean_variance()
        return OccupancyMap(self.geometry, probability=probit_squash(mean, var, alpha, beta), mean=mean,
                            variance=var, observed=self.prec > 0, method=method)


def initial_hyperparameters(cfg: GPConfig, X: Array, y: Array, beams: NDArray[np.int64] | None = None) -> GPHyperparameters:
    """The configured constants, or the LML optimum on these (first-frame) samples.

    At most ``cfg.fit_max_points`` samples enter the fit; they are thinned **by beam** (every k-th
    beam keeps all its samples) so that neighbouring occupied/free samples stay together — thinning
    the flat sample list breaks those pairs and the fit then sees uncorrelated labels. An optimum
    whose signal variance is below the noise variance (a noise-only model that would predict μ ≈ 0
    everywhere) is rejected with a warning in favour of the configured values, and so is one that
    separates the samples' own labels worse than the configured values do (:func:`label_accuracy`):
    on sparse outdoor scans the likelihood's optimum can be a smooth, noisy model (ℓ ≈ 13–17 m,
    σf ≈ σn) that predicts most hits as free, and the map then has no walls.
    """
    start = GPHyperparameters(cfg.nu, cfg.length_scale_m, cfg.sigma_f, cfg.sigma_n)
    if cfg.hyperparameters == "fixed" or len(X) < 3:
        return start
    if len(X) > cfg.fit_max_points:
        groups = np.arange(len(X)) if beams is None else np.asarray(beams)
        ug, rank = np.unique(groups, return_inverse=True)
        k = int(np.ceil(len(X) / cfg.fit_max_points))
        keep = rank % k == 0
        X, y = X[keep], y[keep]
    fit = fit_hyperparameters(X, y, start, restarts=cfg.fit_restarts)
    if fit.sigma_f < fit.sigma_n:
        warnings.warn(f"GP hyperparameter fit gave a noise-only model ({fit}); using the configured values {start}",
                      stacklevel=2)
        return start
    if label_accuracy(fit, X, y) < label_accuracy(start, X, y):
        warnings.warn(f"GP hyperparameter fit ({fit}) tells the first scan's hits from its free samples worse than "
                      f"the configured values; using {start}", stacklevel=2)
        return start
    return fit


def label_accuracy(hyp: GPHyperparameters, X: Array, y: Array) -> float:
    """Balanced accuracy of the GP posterior mean's sign on its own training labels (±1): the mean of the
    fractions of occupied and of free samples it classifies right."""
    mu, _ = GaussianProcess(hyp).fit(X, y).predict(X, return_var=False)
    right = np.sign(mu) == np.sign(y)
    return float(np.mean([right[y > 0].mean() if (y > 0).any() else 1.0,
                          right[y < 0].mean() if (y < 0).any() else 1.0]))
