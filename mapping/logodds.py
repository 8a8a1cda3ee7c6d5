"""Log-odds occupancy grid: the classic baseline (Thrun, Burgard & Fox, Probabilistic Robotics, §9.2,
Table 9.1 with the inverse sensor model of Table 9.2).

Per scan every cell a beam crosses before its end point gets ``l_free``, the cell holding a hit gets
``l_occ`` (each at most once per scan, a hit wins over free); log odds are clamped to
[l_min, l_max]. Ray traversal is vectorised: all beams are sampled at half-cell steps at once.
Beams without a return clear free space up to the maximum range.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from core.frame import Frame
from core.geometry import transform_points

from .beams import beam_samples
from .config import MappingConfig
from .grid import GridGeometry

Array = NDArray[np.float64]


class LogOddsGrid:
    """Incremental log-odds mapper on a fixed world grid."""

    def __init__(self, geometry: GridGeometry, config: MappingConfig | None = None) -> None:
        self.config = config or MappingConfig()
        self.geometry = geometry
        self.logodds = np.zeros(geometry.shape)
        self.observed = np.zeros(geometry.shape, bool)

    def update(self, frame: Frame, world_T_base: Array) -> None:
        """Fuse one scan taken at robot pose ``world_T_base`` (4×4)."""
        lc = self.config.logodds
        g = self.geometry
        world_T_sensor = np.asarray(world_T_base, float) @ frame.base_T_sensor
        bs = beam_samples(frame, g.resolution)  # only angles / ranges / hit flags are used
        if len(bs.angles) == 0:
            return
        step = 0.5 * g.resolution
        n = np.ceil(bs.outer / step).astype(np.int64)
        k = np.arange(int(n.max()) + 1)
        # sample j of beam b at range min(j·step, r_b); samples strictly before the end point are free
        s = np.minimum(k[None, :] * step, bs.outer[:, None])
        pts = np.stack([s * np.cos(bs.angles)[:, None], s * np.sin(bs.angles)[:, None]], -1).reshape(-1, 2)
        world = transform_points(world_T_sensor, pts)
        iy, ix = g.world_to_cell(world)
        iy = iy.reshape(s.shape)
        ix = ix.reshape(s.shape)
        end_iy, end_ix = iy[np.arange(len(n)), n], ix[np.arange(len(n)), n]
        flat = iy * g.shape[1] + ix
        end_flat = end_iy * g.shape[1] + end_ix
        free = (k[None, :] < n[:, None]) & (flat != end_flat[:, None]) & g.inside(iy, ix)
        occ_ok = bs.hit & g.inside(end_iy, end_ix)
        occ_cells = np.unique(end_flat[occ_ok])
        free_cells = np.setdiff1d(np.unique(flat[free]), occ_cells, assume_unique=True)
        L = self.logodds.reshape(-1)
        L[free_cells] += lc.l_free
        L[occ_cells] += lc.l_occ
        L[free_cells] = np.clip(L[free_cells], lc.l_min, lc.l_max)
        L[occ_cells] = np.clip(L[occ_cells], lc.l_min, lc.l_max)
        obs = self.observed.reshape(-1)
        obs[free_cells] = True
        obs[occ_cells] = True

    def to_map(self):
        from .occupancy_map import OccupancyMap

        p = 1.0 / (1.0 + np.exp(-self.logodds))
        return OccupancyMap(self.geometry, probability=p, observed=self.observed.copy(), method="logodds")
