"""Submaps anchored to keyframes and their BCM fusion into a global map at the current anchor poses.

Each submap keeps Fast-GPOM estimates in information form (Σ μ/σ², Σ 1/σ², see mapping.bcm) on its
own grid in the **anchor** frame, from the scans assigned to it (poses ``anchor_T_base``). The global
map is the BCM fusion — a sum in information form — of every submap resampled (nearest cell
centre) onto the world grid at its anchor pose ``world_T_anchor``. :meth:`SubmapFuser.update_poses`
(after a pose-graph optimisation) only re-places the submaps whose anchor moved by more than a
tolerance: their old contribution is subtracted and the new one added; no GP is run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Hashable, Mapping

import numpy as np
from numpy.typing import NDArray

from core.frame import Frame
from core.geometry import inverse, matrix_to_xytheta, relative, wrap_angle

from .bcm import mean_variance, probit_squash
from .config import MappingConfig
from .fastgpom import FastGPOM
from .gp import GPHyperparameters
from .grid import GridGeometry

Array = NDArray[np.float64]


@dataclass
class Submap:
    """One submap: anchor pose ``world_T_anchor`` (4×4) and a Fast-GPOM grid in the anchor frame."""

    key: Hashable
    world_T_anchor: Array
    mapper: FastGPOM
    scans: int = 0
    #: where the submap is placed in the global grid: flat global cell indices and, for each, the flat
    #: index of the submap cell resampled there (its values are read from the submap grid, which
    #: does not change while it is placed: :meth:`SubmapFuser.add_scan` removes it first)
    placed: tuple[NDArray[np.integer], NDArray[np.int32]] | None = None
    placed_pose: Array | None = None
    dirty: bool = True


@dataclass
class SubmapFuser:
    """Global map = BCM fusion of submaps placed at their anchor poses.

    Args:
        geometry: the world grid of the fused map.
        config: mapping configuration (Fast-GPOM parameters, squash).
        submap_half_size: half the side of each submap's square grid around its anchor (m).
        translation_tol, rotation_tol: an anchor that moved less than this (m, rad) is not re-placed.
    """

    geometry: GridGeometry
    config: MappingConfig = field(default_factory=MappingConfig)
    submap_half_size: float = 8.0
    translation_tol: float = 1e-3
    rotation_tol: float = 1e-3
    hyperparameters: GPHyperparameters | None = None
    submaps: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.info = np.zeros(self.geometry.shape)
        self.prec = np.zeros(self.geometry.shape)

    def add_submap(self, key: Hashable, world_T_anchor: Array) -> Submap:
        """Start a submap anchored at keyframe *key* with pose ``world_T_anchor``."""
        h = self.submap_half_size
        r = self.geometry.resolution
        n = int(np.ceil(2 * h / r))
        g = GridGeometry((-n * r / 2, -n * r / 2), r, (n, n))
        sm = Submap(key, np.array(world_T_anchor, float), FastGPOM(g, self.config, self.hyperparameters))
        self.submaps[key] = sm
        return sm

    def add_scan(self, key: Hashable, frame: Frame, world_T_base: Array) -> None:
        """Fuse a scan into submap *key*; its pose enters relative to the anchor (anchor_T_base)."""
        sm = self.submaps[key]
        self._unplace(sm)  # its placed contribution is read from the grid about to change
        grid = sm.mapper.grid
        if grid.info.dtype != np.float64:  # sealed (see seal): accumulate in full precision again
            grid.info, grid.prec = grid.info.astype(np.float64), grid.prec.astype(np.float64)
        sm.mapper.update(frame, relative(sm.world_T_anchor, world_T_base))
        if self.hyperparameters is None:  # fitted on the first frame, then shared by all submaps
            self.hyperparameters = sm.mapper.hyp
        sm.scans += 1
        sm.dirty = True

    def seal(self, key: Hashable) -> None:
        """Submap *key* will receive no more scans (normally): its grid is stored in float32 from now on.

        Halves the mapping stage's memory (a 24 m submap at 5 cm is 1.8 MB per float64 array, and a
        building-sized log has hundreds of submaps). Values change by < 1e-7 relative. The submap is taken off the global grid
        first and re-placed from the float32 values, so what is later subtracted is exactly what was
        added."""
        sm = self.submaps[key]
        grid = sm.mapper.grid
        if grid.info.dtype == np.float32:
            return
        self._unplace(sm)
        grid.info, grid.prec = grid.info.astype(np.float32), grid.prec.astype(np.float32)
        sm.dirty = True

    # ------------------------------------------------------------------------ placement
    def _contribution(self, sm: Submap) -> tuple[NDArray[np.integer], NDArray[np.int32]]:
        """Resample a submap onto the world grid at its anchor pose (nearest submap cell centre): the
        flat global cells it covers and the flat submap cell read at each (observed cells only)."""
        lg = sm.mapper.grid.geometry
        prec = sm.mapper.grid.prec
        ys, xs = np.nonzero(prec.any(axis=1))[0], np.nonzero(prec.any(axis=0))[0]
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int32))
        if len(ys) == 0:
            return empty
        x0, x1 = lg.origin[0] + xs[0] * lg.resolution, lg.origin[0] + (xs[-1] + 1) * lg.resolution
        y0, y1 = lg.origin[1] + ys[0] * lg.resolution, lg.origin[1] + (ys[-1] + 1) * lg.resolution
        corners = np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])
        T = sm.world_T_anchor
        wc = corners @ T[:2, :2].T + T[:2, 3]
        centre = 0.5 * (wc.min(0) + wc.max(0))
        rows, cols = self.geometry.window(centre, float(np.max(wc.max(0) - wc.min(0))) / 2 + lg.resolution)
        if rows.stop <= rows.start or cols.stop <= cols.start:
            return empty
        from .kernels import resample_cells  # numba only where maps are fused (docs/ARCHITECTURE.md)

        A = inverse(T)  # anchor_T_world: the window's cell centres into the submap's frame
        wg = self.geometry
        g, local = resample_cells(rows.start, cols.start, rows.stop - rows.start, cols.stop - cols.start,
                                  wg.shape[1], wg.origin[0], wg.origin[1], wg.resolution,
                                  A[0, 0], A[0, 1], A[1, 0], A[1, 1], A[0, 3], A[1, 3],
                                  lg.origin[0], lg.origin[1], lg.resolution, prec)
        # 8 bytes per placed cell, not 24 (indices and two float64 values): a few hundred submaps
        # hold most of a gigabyte of placed values otherwise.
        return g.astype(np.int32 if self.info.size < 2**31 else np.int64), local

    def _add(self, sm: Submap, sign: float) -> None:
        """Add (+1) or subtract (−1) the placed contribution of *sm* to the global grid."""
        from .kernels import add_placed

        if sm.placed is None:
            return
        g, local = sm.placed
        grid = sm.mapper.grid
        add_placed(self.info.reshape(-1), self.prec.reshape(-1), g, local,
                   grid.info.reshape(-1), grid.prec.reshape(-1), sign)

    def _unplace(self, sm: Submap) -> None:
        if sm.placed is not None:
            self._add(sm, -1.0)
            sm.placed = None
            sm.placed_pose = None

    def _place(self, sm: Submap) -> None:
        self._unplace(sm)
        sm.placed = self._contribution(sm)
        sm.placed_pose = sm.world_T_anchor.copy()
        self._add(sm, +1.0)
        sm.dirty = False

    def placed_values(self, key: Hashable) -> tuple[NDArray[np.integer], Array, Array]:
        """Submap *key*'s placed contribution: flat global cells, info and precision values there."""
        sm = self.submaps[key]
        if sm.placed is None:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        g, local = sm.placed
        return g, sm.mapper.grid.info.reshape(-1)[local], sm.mapper.grid.prec.reshape(-1)[local]

    def _moved(self, a: Array, b: Array) -> bool:
        d = matrix_to_xytheta(relative(a, b))
        return bool(np.hypot(d[0], d[1]) > self.translation_tol or abs(wrap_angle(d[2])) > self.rotation_tol)

    def update_poses(self, anchors: Mapping[Hashable, Array]) -> int:
        """Set new anchor poses (e.g. after pose-graph optimisation) and recompose the global map.

        Only submaps that moved by more than the tolerances (or received scans) are re-placed; no
        GP is evaluated. Returns the number of submaps re-placed.
        """
        n = 0
        for key, T in anchors.items():
            sm = self.submaps[key]
            T = np.asarray(T, float)
            moved = sm.placed_pose is None or self._moved(sm.placed_pose, T)
            sm.world_T_anchor = T.copy()
            if moved or sm.dirty:
                self._place(sm)
                n += 1
        for sm in self.submaps.values():
            if sm.dirty and sm.key not in anchors:
                self._place(sm)
                n += 1
        return n

    def resize(self, geometry: GridGeometry) -> None:
        """Move the global map onto another world grid (e.g. grown to cover new anchors); every submap
        is re-placed at its anchor on the next :meth:`update_poses` / :meth:`to_map`. No GP is run."""
        self.geometry = geometry
        self.info = np.zeros(geometry.shape)
        self.prec = np.zeros(geometry.shape)
        for sm in self.submaps.values():
            sm.placed = None
            sm.placed_pose = None

    def recompose(self) -> None:
        """Rebuild the global grid from scratch from every submap (clears accumulated round-off)."""
        self.info[:] = 0.0
        self.prec[:] = 0.0
        for sm in self.submaps.values():
            sm.placed = None
            self._place(sm)

    def to_map(self):
        """The fused :class:`~mapping.occupancy_map.OccupancyMap` (places dirty submaps first)."""
        from .occupancy_map import OccupancyMap

        for sm in self.submaps.values():
            if sm.dirty:
                self._place(sm)
        shape = self.geometry.shape
        mean, var, p = np.empty(shape), np.empty(shape), np.empty(shape)
        seen = np.empty(shape, dtype=bool)
        rows = max(1, (1 << 20) // max(shape[1], 1))  # ~1 M cells at a time: no full-size temporaries
        for r in range(0, shape[0], rows):
            cut = slice(r, r + rows)
            prec = np.maximum(self.prec[cut], 0.0)
            seen[cut] = s = prec > 1e-9  # round-off left by subtracting a re-placed submap is not a cell seen
            mean[cut], var[cut] = mean_variance(np.where(s, self.info[cut], 0.0), np.where(s, prec, 0.0))
            p[cut] = probit_squash(mean[cut], var[cut], self.config.squash_alpha, self.config.squash_beta)
        return OccupancyMap(self.geometry, p, mean, var, seen, "fastgpom-submaps")
