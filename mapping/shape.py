"""How square a map is drawn: the share of its wall cells that run along its two dominant perpendicular directions.

Most buildings are drawn on a rectilinear plan (the "Manhattan world" of Coughlan & Yuille, ICCV 1999). A room
placed at a wrong angle against the rest, or a wall mapped twice at two headings, puts its wall cells off the
dominant directions, so without any ground truth the share falls. It measures a map against itself: compare
two maps of the same log, not two buildings (a round hall or an outdoor site scores low when drawn right).

Wall cells are the observed cells with occupancy probability above ``occupied``; a cell's direction is the
principal axis of the wall cells within ``radius_m`` of it (at least five, elongated: the second moment along
the axis at least four times that across it). The dominant direction (modulo 90°) is the mode of a histogram of
1° bins smoothed over ±5°.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from core.errors import DegenerateInputError

Array = NDArray[np.float64]


def wall_directions_deg(probability: Array, observed: NDArray[np.bool_], resolution_m: float, *,
                        occupied: float = 0.65, radius_m: float = 0.25, neighbours: int = 24) -> Array:
    """Direction (°, modulo 90) of every wall cell that lies on a line of wall cells."""
    cells = np.argwhere((probability > occupied) & observed).astype(np.float64) * resolution_m
    if len(cells) < 5:
        return np.zeros(0)
    dist, idx = cKDTree(cells).query(cells, k=min(neighbours, len(cells)), distance_upper_bound=radius_m)
    near = np.isfinite(dist)
    n = near.sum(axis=1)
    pts = cells[np.where(near, idx, 0)]  # (N, k, 2); far entries masked below
    w = near[..., None].astype(np.float64)
    mean = (pts * w).sum(axis=1) / n[:, None]
    d = (pts - mean[:, None, :]) * w
    sxx, syy, sxy = (d[..., 0] ** 2).sum(1), (d[..., 1] ** 2).sum(1), (d[..., 0] * d[..., 1]).sum(1)
    half_trace, gap = 0.5 * (sxx + syy), np.hypot(0.5 * (sxx - syy), sxy)
    along, across = half_trace + gap, half_trace - gap
    line = (n >= 5) & (along >= 4.0 * np.maximum(across, 1e-12))
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # principal axis
    return np.degrees(angle[line]) % 90.0


def square_share(probability: Array, observed: NDArray[np.bool_], resolution_m: float, *,
                 tolerance_deg: float = 5.0, **kwargs) -> float:
    """Share of the wall cells within ±*tolerance_deg* of the map's dominant perpendicular directions."""
    ang = wall_directions_deg(probability, observed, resolution_m, **kwargs)
    if len(ang) == 0:
        raise DegenerateInputError("the map has no wall cells on a line")
    hist, _ = np.histogram(ang, bins=90, range=(0.0, 90.0))
    smooth = np.convolve(np.r_[hist, hist, hist], np.ones(11), "same")[90:180]  # circular, ±5°
    mode = float(np.argmax(smooth)) + 0.5
    off = np.abs((ang - mode + 45.0) % 90.0 - 45.0)
    return float(np.mean(off <= tolerance_deg))
