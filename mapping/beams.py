"""Occupied and free training samples from a planar laser Frame, in the sensor frame (m).

Yuan et al. 2018 §III-A: each beam gives one occupied sample at its hit (+1) and free samples
(−1) every d along the beam, the last one at least 1.5·d before the hit; beams without a return
give free samples all the way to the maximum range (the paper's reading; the reference code drops
them). Beam i's angle is the Frame's ``angles[i]`` (angle_min + i·increment).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from core.errors import GeometryError
from core.frame import Frame

Array = NDArray[np.float64]


@dataclass(frozen=True)
class BeamSamples:
    """Per usable beam (sorted by angle): angle, whether it hit, hit range / last free range.

    ``outer`` is the hit range (max range for a beam without a return), ``inner`` the range of its
    last free sample (0 when the beam is too short to hold one), ``n_free`` its number of free
    samples spaced ``step``. ``free_xy``/``free_beam`` (computed on demand) hold every free sample and
    the index of its beam.
    """

    angles: Array
    hit: NDArray[np.bool_]
    outer: Array
    inner: Array
    n_free: NDArray[np.int64]
    step: float

    @property
    def free_beam(self) -> NDArray[np.int64]:
        return np.repeat(np.arange(len(self.n_free)), self.n_free)

    @property
    def free_xy(self) -> Array:
        bi = self.free_beam
        if len(bi) == 0:
            return np.zeros((0, 2))
        first = np.repeat(np.cumsum(self.n_free) - self.n_free, self.n_free)
        s = (np.arange(len(bi)) - first + 1) * self.step
        a = self.angles[bi]
        return np.column_stack([s * np.cos(a), s * np.sin(a)])

    @property
    def hit_xy(self) -> Array:
        a = self.angles[self.hit]
        r = self.outer[self.hit]
        return np.column_stack([r * np.cos(a), r * np.sin(a)])

    @property
    def inner_xy(self) -> Array:
        return np.column_stack([self.inner * np.cos(self.angles), self.inner * np.sin(self.angles)])


def beam_samples(frame: Frame, free_step: float, stop_before: float = 1.5, beam_stride: int = 1,
                 max_range: float | None = None) -> BeamSamples:
    """Sample a 2D scan: hits and free points every *free_step* (m) per beam (vectorised).

    Beams with NaN or below-minimum ranges are skipped; beams without a return are used only when
    the maximum range (argument or ``frame.max_range``) is finite.
    """
    if frame.ranges is None or frame.angles is None:
        raise GeometryError(f"{frame.source or 'frame'}: mapping needs a 2D laser scan with beam angles and ranges")
    if not free_step > 0:
        raise GeometryError(f"free_step must be > 0, got {free_step}")
    far = frame.max_range if max_range is None else max_range
    a = frame.angles[::beam_stride]
    r = frame.ranges[::beam_stride]
    nr = frame.no_return[::beam_stride]
    with np.errstate(invalid="ignore"):
        hit = ~nr & np.isfinite(r) & (r >= frame.min_range) & (r > 0)
        if np.isfinite(far):
            hit &= r <= far
    use_nr = nr & np.isfinite(far)
    keep = hit | use_nr
    order = np.argsort(a[keep], kind="stable")
    a = a[keep][order]
    hit = hit[keep][order]
    outer = np.where(hit, r[keep][order], far if np.isfinite(far) else 0.0)
    # number of free samples: k·d ≤ r − stop·d for hits, k·d ≤ max range otherwise
    limit = np.where(hit, outer - stop_before * free_step, outer)
    nfree = np.maximum(0, np.floor(limit / free_step + 1e-9)).astype(np.int64)
    inner = nfree * free_step
    return BeamSamples(a, hit, outer, inner.astype(float), nfree, float(free_step))


def clip_range(frame: Frame, max_range: float) -> Frame:
    """A copy of a 2D scan whose returns beyond *max_range* (m) count as no return at that range."""
    if frame.ranges is None:
        return frame
    from dataclasses import replace

    far = min(max_range, frame.max_range)
    with np.errstate(invalid="ignore"):
        nr = frame.no_return | (frame.ranges > far)
        keep = ~nr & np.isfinite(frame.ranges)
    pts = np.column_stack([frame.ranges[keep] * np.cos(frame.angles[keep]), frame.ranges[keep] * np.sin(frame.angles[keep])])
    return replace(frame, no_return=nr, max_range=far, points=pts)
