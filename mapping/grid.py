"""Grid geometry: world ↔ cell conversions for arrays indexed ``[iy, ix]`` (docs/ARCHITECTURE.md).

Row 0 is the row at the origin (lowest y); the centre of cell (iy, ix) is
``origin + ((ix + 0.5)·res, (iy + 0.5)·res)`` in the grid's frame (metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core.errors import ConfigError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class GridGeometry:
    """Origin (x, y) of the lower-left corner (m), cell size (m) and shape (ny, nx)."""

    origin: tuple[float, float]
    resolution: float
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        if not self.resolution > 0 or self.shape[0] <= 0 or self.shape[1] <= 0:
            raise ConfigError(f"grid needs resolution > 0 and a positive shape, got {self.resolution}, {self.shape}")

    @classmethod
    def covering(cls, xy_min: Array, xy_max: Array, resolution: float, margin: float = 0.0) -> "GridGeometry":
        """The grid aligned to multiples of *resolution* that covers the box [xy_min, xy_max] ± margin."""
        lo = np.floor((np.asarray(xy_min, float) - margin) / resolution) * resolution
        hi = np.asarray(xy_max, float) + margin
        n = np.maximum(1, np.ceil((hi - lo) / resolution - 1e-9).astype(int))
        return cls((float(lo[0]), float(lo[1])), float(resolution), (int(n[1]), int(n[0])))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) in metres."""
        x0, y0 = self.origin
        return x0, x0 + self.shape[1] * self.resolution, y0, y0 + self.shape[0] * self.resolution

    def world_to_cell(self, xy: Array) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(iy, ix) of the cells containing points ``(N, 2)`` (may lie outside the grid)."""
        xy = np.asarray(xy, dtype=float)
        ix = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        iy = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        return iy, ix

    def inside(self, iy: NDArray[np.int64], ix: NDArray[np.int64]) -> NDArray[np.bool_]:
        return (iy >= 0) & (iy < self.shape[0]) & (ix >= 0) & (ix < self.shape[1])

    def centres_x(self, ix0: int = 0, ix1: int | None = None) -> Array:
        ix1 = self.shape[1] if ix1 is None else ix1
        return self.origin[0] + (np.arange(ix0, ix1) + 0.5) * self.resolution

    def centres_y(self, iy0: int = 0, iy1: int | None = None) -> Array:
        iy1 = self.shape[0] if iy1 is None else iy1
        return self.origin[1] + (np.arange(iy0, iy1) + 0.5) * self.resolution

    def window(self, centre: Array, radius: float) -> tuple[slice, slice]:
        """(rows, cols) slices of the cells whose centres may lie within *radius* of *centre*, clipped."""
        c = np.asarray(centre, dtype=float)[:2]
        return self.window_box(c - radius, c + radius)

    def window_box(self, xy_min: Array, xy_max: Array) -> tuple[slice, slice]:
        """(rows, cols) slices of the cells whose centres may lie in the box [xy_min, xy_max] (m), clipped."""
        r = self.resolution
        ix0 = max(0, int(np.floor((float(xy_min[0]) - self.origin[0]) / r)))
        ix1 = min(self.shape[1], int(np.ceil((float(xy_max[0]) - self.origin[0]) / r)) + 1)
        iy0 = max(0, int(np.floor((float(xy_min[1]) - self.origin[1]) / r)))
        iy1 = min(self.shape[0], int(np.ceil((float(xy_max[1]) - self.origin[1]) / r)) + 1)
        return slice(iy0, max(iy0, iy1)), slice(ix0, max(ix0, ix1))

    def window_in_frame(self, rows: slice, cols: slice, frame_T_grid: Array) -> tuple[Array, Array]:
        """Centres of the window's cells expressed in another frame: x, y arrays of shape (h, w)."""
        cx = self.centres_x(cols.start, cols.stop)
        cy = self.centres_y(rows.start, rows.stop)
        R = frame_T_grid[:2, :2]
        t = frame_T_grid[:2, 3]
        x = R[0, 0] * cx[None, :] + R[0, 1] * cy[:, None] + t[0]
        y = R[1, 0] * cx[None, :] + R[1, 1] * cy[:, None] + t[1]
        return x, y
