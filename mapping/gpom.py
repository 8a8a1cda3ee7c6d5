"""Classic GPOM (O'Callaghan & Ramos, IJRR 2012; Yuan et al. 2018 Alg. 2).

Per scan: one exact GP trained on every hit (+1) and free (−1) sample of the scan predicts every
cell of the local window (the disc of the scan's longest range around the sensor); the local
(μ, σ²) is BCM-fused into the global grid. Cells behind walls are predicted too — the defect the
Fast-GPOM paper shows in its Fig. 1. To keep the exact GP tractable the training set uses every
``beam_stride``-th beam and a free-sample spacing ``free_step_m`` (see mapping/README.md).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core.frame import Frame
from core.geometry import inverse

from .beams import beam_samples
from .config import MappingConfig
from .gaussian_grid import GaussianGrid, initial_hyperparameters
from .gp import GaussianProcess, GPHyperparameters
from .grid import GridGeometry

Array = NDArray[np.float64]


class ClassicGPOM:
    """Incremental classic-GPOM mapper on a fixed world grid."""

    def __init__(self, geometry: GridGeometry, config: MappingConfig | None = None,
                 hyperparameters: GPHyperparameters | None = None) -> None:
        self.config = config or MappingConfig()
        self.grid = GaussianGrid(geometry)
        self.hyp = hyperparameters

    def training_set(self, frame: Frame) -> tuple[Array, Array, float, NDArray[np.int64]]:
        """Hits (+1) and free samples (−1) in the sensor frame, the longest beam (m), each sample's beam."""
        gc = self.config.gpom
        bs = beam_samples(frame, gc.free_step_m, gc.stop_before_hit, beam_stride=gc.beam_stride)
        H = bs.hit_xy
        X = np.concatenate([H, bs.free_xy])
        y = np.concatenate([np.ones(len(H)), -np.ones(len(X) - len(H))])
        beams = np.concatenate([np.flatnonzero(bs.hit), bs.free_beam])
        return X, y, float(bs.outer.max()) if len(bs.outer) else 0.0, beams

    def update(self, frame: Frame, world_T_base: Array) -> None:
        """Fuse one scan taken at robot pose ``world_T_base`` (4×4) into the global grid."""
        geom = self.grid.geometry
        world_T_sensor = np.asarray(world_T_base, float) @ frame.base_T_sensor
        X, y, reach, beams = self.training_set(frame)
        if len(X) == 0:
            return
        if self.hyp is None:
            self.hyp = initial_hyperparameters(self.config.gp, X, y, beams)
        rows, cols = geom.window(world_T_sensor[:2, 3], reach)
        x, yy = geom.window_in_frame(rows, cols, inverse(world_T_sensor))
        sel = np.flatnonzero(np.hypot(x, yy).ravel() <= reach)
        if len(sel) == 0:
            return
        mean, var = GaussianProcess(self.hyp).fit(X, y).predict(np.column_stack([x.ravel()[sel], yy.ravel()[sel]]))
        self.grid.fuse_window(rows, cols, sel, mean, var)

    def to_map(self):
        return self.grid.to_map(self.config.squash_alpha, self.config.squash_beta, "gpom")
