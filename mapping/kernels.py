"""Compiled (numba) loops of the mapping stage: the loop forms of numpy expressions in :mod:`mapping.submaps`,
with the same arithmetic in the same order (so the same cells, bit for bit) and without their temporaries."""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["resample_cells", "add_placed"]


@njit(cache=True)
def resample_cells(row0, col0, h, w, world_cols, world_origin_x, world_origin_y, world_res,
                   R00, R01, R10, R11, t0, t1, sub_origin_x, sub_origin_y, sub_res, prec):  # pragma: no cover - compiled
    """Nearest-cell resampling of a submap onto a window of the world grid.

    The window is the world grid's rows ``row0 … row0 + h − 1`` and columns ``col0 … col0 + w − 1``; each of its
    cell centres is taken into the submap's frame by ``[R | t]`` (``anchor_T_world``) and falls in one submap
    cell. Returns the flat world cells whose submap cell lies inside the submap grid with ``prec > 0`` there, and
    that submap cell's flat index, in row-major window order: :meth:`mapping.submaps.SubmapFuser._contribution`'s
    numpy form (``GridGeometry.window_in_frame``, ``world_to_cell``, ``inside``) as one loop.
    """
    ny, nx = prec.shape
    g = np.empty(h * w, np.int64)
    local = np.empty(h * w, np.int32)
    n = 0
    for i in range(h):
        cy = world_origin_y + (row0 + i + 0.5) * world_res
        for j in range(w):
            cx = world_origin_x + (col0 + j + 0.5) * world_res
            x = R00 * cx + R01 * cy + t0
            y = R10 * cx + R11 * cy + t1
            ix = np.int64(np.floor((x - sub_origin_x) / sub_res))
            iy = np.int64(np.floor((y - sub_origin_y) / sub_res))
            if iy < 0 or iy >= ny or ix < 0 or ix >= nx:
                continue
            if prec[iy, ix] > 0:
                g[n] = (row0 + i) * world_cols + col0 + j
                local[n] = np.int32(iy * nx + ix)
                n += 1
    return g[:n], local[:n]


@njit(cache=True)
def add_placed(info, prec, g, local, sub_info, sub_prec, sign):  # pragma: no cover - compiled
    """``info[g] += sign · sub_info[local]`` and the same for the precisions (flat arrays; the cells *g* are
    unique, so the loop equals numpy's fancy ``+=``): a submap's placed contribution added or taken off."""
    for k in range(g.shape[0]):
        info[g[k]] += sign * sub_info[local[k]]
        prec[g[k]] += sign * sub_prec[local[k]]
