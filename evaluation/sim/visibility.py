"""Which cells of a world a 2D laser sees: compiled (numba) grid traversal for coverage.

A beam is walked cell by cell (Amanatides & Woo 1987, the traversal of :mod:`.raycast`) from the
sensor until it enters an occupied cell, leaves the grid or passes its range; every cell it crosses
before that is *seen*. Unknown cells are transparent, as in the simulator. Two uses:

- :func:`seen_cells`: the cells a sequence of scans saw (the coverage of a simulated log);
- :func:`visible_targets`: for each candidate viewpoint, the coverage targets (coarse cells) a full
  360° sweep would see — the sets the coverage planner chooses from.

Importing this module pulls in numba (~120 MB); only the coverage planner and ``slam simulate`` do.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from .world import World

__all__ = ["seen_cells", "visible_targets"]


@njit(cache=True)
def _walk(occ, gx, gy, dx, dy, max_t, out):  # pragma: no cover - compiled
    """Flat indices of the cells a ray from cell coordinates (gx, gy) along the unit (dx, dy)
    crosses before an occupied cell, the grid's edge or *max_t* cells; returns how many (≤ len(out))."""
    h, w = occ.shape
    ix, iy = int(math.floor(gx)), int(math.floor(gy))
    sx = 1 if dx >= 0 else -1
    sy = 1 if dy >= 0 else -1
    inv_x = 1.0 / abs(dx) if dx != 0 else np.inf
    inv_y = 1.0 / abs(dy) if dy != 0 else np.inf
    tx = ((ix + 1 - gx) if dx > 0 else (gx - ix)) * inv_x if dx != 0 else np.inf
    ty = ((iy + 1 - gy) if dy > 0 else (gy - iy)) * inv_y if dy != 0 else np.inf
    t = 0.0
    n = 0
    while 0 <= ix < w and 0 <= iy < h and t <= max_t and n < len(out):
        if occ[iy, ix]:
            break
        out[n] = iy * w + ix
        n += 1
        if tx < ty:
            t = tx
            tx += inv_x
            ix += sx
        else:
            t = ty
            ty += inv_y
            iy += sy
    return n


@njit(cache=True)
def _mark(occ, gx, gy, theta, angles, max_t, seen):  # pragma: no cover - compiled
    buf = np.empty(int(4 * max_t) + 8, dtype=np.int64)
    flat = seen.ravel()
    for i in range(len(gx)):
        for b in range(len(angles)):
            a = theta[i] + angles[b]
            n = _walk(occ, gx[i], gy[i], math.cos(a), math.sin(a), max_t, buf)
            for k in range(n):
                flat[buf[k]] = True


@njit(cache=True)
def _targets(occ, target_of, gx, gy, n_rays, max_t, fill, indptr, indices, stamp):  # pragma: no cover - compiled
    """Distinct targets seen from each origin: counts into indptr (fill=False) or ids into indices."""
    buf = np.empty(int(4 * max_t) + 8, dtype=np.int64)
    flat_t = target_of.ravel()
    for i in range(len(gx)):
        pos = indptr[i]
        c = 0
        for r in range(n_rays):
            a = 2.0 * math.pi * r / n_rays
            n = _walk(occ, gx[i], gy[i], math.cos(a), math.sin(a), max_t, buf)
            for k in range(n):
                t = flat_t[buf[k]]
                if t >= 0 and stamp[t] != i + 1:
                    stamp[t] = i + 1
                    if fill:
                        indices[pos + c] = t
                    c += 1
        if not fill:
            indptr[i + 1] = c


def _cell_coords(world: World, xy: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    g = (np.asarray(xy, dtype=np.float64).reshape(-1, 2) - world.origin_xy) / world.resolution
    return np.ascontiguousarray(g[:, 0]), np.ascontiguousarray(g[:, 1])


def seen_cells(world: World, sensor_poses_xyt: ArrayLike, angles: ArrayLike, range_max: float) -> NDArray[np.bool_]:
    """Bool grid of the cells crossed by the beams (sensor-frame *angles*, rad) of scans taken at
    world sensor poses ``(N, 3)`` (x, y, θ), each beam up to its first occupied cell or *range_max* (m)."""
    p = np.asarray(sensor_poses_xyt, dtype=np.float64).reshape(-1, 3)
    gx, gy = _cell_coords(world, p[:, :2])
    seen = np.zeros(world.shape, dtype=bool)
    _mark(np.ascontiguousarray(world.occupied), gx, gy, np.ascontiguousarray(p[:, 2]),
          np.ascontiguousarray(np.asarray(angles, dtype=np.float64)), range_max / world.resolution, seen)
    return seen


def visible_targets(world: World, target_of: NDArray[np.int64], origins_xy: ArrayLike, range_m: float,
                    n_rays: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """CSR ``(indptr, indices)``: the distinct targets (``target_of[iy, ix]`` ≥ 0 of the cells crossed)
    that *n_rays* evenly spaced beams from each origin ``(K, 2)`` see within *range_m* (m)."""
    gx, gy = _cell_coords(world, np.asarray(origins_xy))
    occ = np.ascontiguousarray(world.occupied)
    tgt = np.ascontiguousarray(target_of, dtype=np.int64)
    max_t = range_m / world.resolution
    indptr = np.zeros(len(gx) + 1, dtype=np.int64)
    stamp = np.zeros(int(tgt.max()) + 1 if tgt.size and tgt.max() >= 0 else 1, dtype=np.int64)
    _targets(occ, tgt, gx, gy, n_rays, max_t, False, indptr, np.empty(0, np.int64), stamp)
    counts = indptr[1:].copy()
    indptr[1:] = np.cumsum(counts)
    indices = np.empty(int(indptr[-1]), dtype=np.int64)
    stamp[:] = 0
    _targets(occ, tgt, gx, gy, n_rays, max_t, True, indptr, indices, stamp)
    return indptr, indices
