"""Local maps of old keyframes: the targets loop closures are verified against.

A keyframe's local map is its scan and those of its ±h neighbouring keyframes, put into its sensor
frame by the current estimate (Olson 2009 and Cartographer's submaps match a scan against several
fused scans, not one: a single 180° scan of a corridor shares little with a view from elsewhere).
Each map keeps its ICP target (k-d tree, normals) and, in 2D, its likelihood-field pyramids for the
correlative search (:class:`registration.correlative.LikelihoodPyramid`), built on first use. A map
is rebuilt when a neighbour's pose relative to the centre changed by more than 5 mm or 0.1° (after a
loop closure moved the estimate), so the many revisits of one place reuse it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from core import geometry as G
from registration import correlative
from registration.target import IcpTarget
from slam.keyframes import Keyframe

Array = NDArray[np.float64]

_MOVED_M = 5e-3  # a neighbour this far from where the map put it (or turned by _MOVED_RAD) rebuilds the map
_MOVED_RAD = np.radians(0.1)


@dataclass
class LocalMap:
    """Keyframes ``i − half … i + half`` in keyframe *i*'s sensor frame.

    Attributes:
        i, half: centre keyframe and half-width (keyframes).
        rel: ``(n, 4, 4)`` ``i_sensor_T_m_sensor`` of the members at build time.
        target: ICP target of the members' points (m, in *i*'s sensor frame).
        pyramids: likelihood pyramids by resolution (m), built on demand.
    """

    i: int
    half: int
    rel: Array
    target: IcpTarget
    pyramids: dict[float, correlative.LikelihoodPyramid] = field(default_factory=dict)

    @property
    def points(self) -> Array:
        return self.target.points

    def extent(self) -> tuple[Array, Array]:
        """Lower and upper corner (m) of the map's points in the plane."""
        return G.bounds(self.points[:, :2])


def sensor_relative(keyframes: list[Keyframe], poses: Array, i: int, j: int) -> Array:
    """The estimate's ``i_sensor_T_j_sensor`` from the keyframes' ``world_T_base`` *poses*."""
    return G.inverse(poses[i] @ keyframes[i].base_T_sensor) @ poses[j] @ keyframes[j].base_T_sensor


class LocalMaps:
    """A bounded cache of :class:`LocalMap` (the *capacity* most recently used) and their pyramids
    (the *pyramid_capacity* most recently used; ~1–3 MB each)."""

    def __init__(self, capacity: int = 512, pyramid_capacity: int = 64) -> None:
        self.capacity = capacity
        self.pyramid_capacity = pyramid_capacity
        self._maps: dict[tuple[int, int], LocalMap] = {}
        self._with_pyramids: list[tuple[int, int, float]] = []  # most recent last

    def get(self, keyframes: list[Keyframe], poses: Array, i: int, half: int) -> LocalMap:
        """The local map of keyframe *i* with ±*half* neighbours (clipped to the keyframes known), from *poses*."""
        lo, hi = max(0, i - half), min(len(poses), i + half + 1)
        inv_ref = G.inverse(poses[i] @ keyframes[i].base_T_sensor)
        rel = np.einsum("ij,njk,nkl->nil", inv_ref, poses[lo:hi], np.array([keyframes[m].base_T_sensor for m in range(lo, hi)]))
        key = (i, half)
        lm = self._maps.pop(key, None)
        if lm is not None and (lm.rel.shape != rel.shape or _moved(G.relative(lm.rel, rel))):
            lm = None
        if lm is None:
            pts = np.vstack([G.transform_points(T, keyframes[m].points) for T, m in zip(rel, range(lo, hi))])
            lm = LocalMap(i, half, rel, IcpTarget(pts, normal_neighbors=8, workers=1))
        self._maps[key] = lm  # most recently used last
        if len(self._maps) > self.capacity:
            for old in list(self._maps)[: self.capacity // 4]:
                del self._maps[old]
        return lm

    def pyramid(self, lm: LocalMap, resolution: float, levels: int) -> correlative.LikelihoodPyramid:
        """*lm*'s likelihood pyramid at *resolution* (field σ = the cell), built when missing."""
        tag = (lm.i, lm.half, resolution)
        pyr = lm.pyramids.get(resolution)
        if pyr is None or pyr.levels < levels:
            pyr = correlative.LikelihoodPyramid(lm.points, resolution, resolution, levels=levels)
            lm.pyramids[resolution] = pyr
        if tag in self._with_pyramids:
            self._with_pyramids.remove(tag)
        self._with_pyramids.append(tag)
        while len(self._with_pyramids) > self.pyramid_capacity:
            i, half, res = self._with_pyramids.pop(0)
            owner = self._maps.get((i, half))
            if owner is not None:
                owner.pyramids.pop(res, None)
        return pyr


def _moved(d: Array) -> bool:
    """Whether any relative pose of *d* ``(K, 4, 4)`` is farther than 5 mm or 0.1° from the identity."""
    return bool(np.abs(d[:, :3, 3]).max() >= _MOVED_M or G.rotation_angles(d[:, :3, :3]).max() >= _MOVED_RAD)
