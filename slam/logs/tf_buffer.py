"""A small tf2 buffer (static + dynamic transforms) and the pose track that interpolates odometry and ground
truth to the scan stamps (geodesic interpolation, bounded memory)."""

from __future__ import annotations

import bisect
import math
from typing import Any, Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core import geometry as geo
from core import pose_formats

from .ros_msgs import BASE_FRAMES, header_stamp, interpolate_pose, strip_frame, transform_msg_vec, vecs_to_matrices

Array = NDArray[np.float64]


class PoseTrack:
    """A short time-ordered buffer of pose samples with geodesic interpolation.

    Samples are stored as ``(x, y, z, qx, qy, qz, qw)`` and turned into 4×4 matrices lazily —
    only those a query needs, in one vectorised call. Memory stays bounded: the reader
    trims samples that no pending scan can need.
    """

    def __init__(self, max_gap: float = 0.5) -> None:
        self.stamps: list[float] = []
        self.vecs: list[Array] = []
        self.mats: list[Array | None] = []
        self.max_gap = max_gap  # how far (s) outside the samples a query may hold the end pose

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def latest(self) -> float:
        return self.stamps[-1] if self.stamps else -math.inf

    def add(self, stamp: float, vec: Array) -> None:
        """Add a sample ``(7,)`` at *stamp* (seconds); out-of-order samples are inserted in place."""
        i = len(self.stamps)
        if self.stamps and stamp < self.stamps[-1]:
            i = bisect.bisect_right(self.stamps, stamp)
        self.stamps.insert(i, float(stamp))
        self.vecs.insert(i, np.asarray(vec, dtype=float))
        self.mats.insert(i, None)

    def _matrices(self, idx: Iterable[int]) -> dict[int, Array]:
        """4×4 poses of the samples *idx*, converting the ones not converted yet in one call."""
        idx = sorted(set(int(k) for k in idx))
        todo = [k for k in idx if self.mats[k] is None]
        if todo:
            conv = vecs_to_matrices(np.stack([self.vecs[k] for k in todo]))
            for c, k in enumerate(todo):
                self.mats[k] = conv[c]
        return {k: self.mats[k] for k in idx}  # type: ignore[misc]

    def query_many(self, ts: ArrayLike, max_gap: float | None = None) -> list[Array | None]:
        """Poses at the stamps *ts*: interpolated between the bracketing samples, the end sample
        when a stamp is at most ``max_gap`` (default: the track's) outside the buffer, else None."""
        ts = np.atleast_1d(np.asarray(ts, dtype=float))
        gap = self.max_gap if max_gap is None else max_gap
        if not self.stamps:
            return [None] * len(ts)
        S = np.asarray(self.stamps)
        n = len(S)
        i = np.searchsorted(S, ts, side="left")
        ic = np.minimum(i, n - 1)
        exact = S[ic] == ts
        before = (i == 0) & ~exact & (S[0] - ts <= gap)
        after = (i == n) & (ts - S[-1] <= gap)
        inner = (i > 0) & (i < n) & ~exact
        i1 = i[inner]
        i0 = i1 - 1
        M = self._matrices([*ic[exact], *i0, *i1, *([0] if before.any() else []), *([n - 1] if after.any() else [])])
        out: list[Array | None] = [None] * len(ts)
        if inner.any():
            alpha = (ts[inner] - S[i0]) / (S[i1] - S[i0])
            P = interpolate_pose(np.stack([M[k] for k in i0]), np.stack([M[k] for k in i1]), alpha)
            for k, j in enumerate(np.flatnonzero(inner)):
                out[j] = P[k]
        for j in np.flatnonzero(exact):
            out[j] = M[int(ic[j])].copy()
        for j in np.flatnonzero(before):
            out[j] = M[0].copy()
        for j in np.flatnonzero(after):
            out[j] = M[n - 1].copy()
        return out

    def query(self, t: float) -> Array | None:
        """Pose at one stamp (see :meth:`query_many`)."""
        return self.query_many([t])[0]

    def trim(self, t: float) -> None:
        """Drop samples no query at time ≥ *t* can use (keeps the last sample at or before *t*)."""
        i = bisect.bisect_right(self.stamps, t) - 1
        if i > 0:
            del self.stamps[:i]
            del self.vecs[:i]
            del self.mats[:i]

    def keep_last(self, n: int) -> None:
        if len(self.stamps) > n:
            k = len(self.stamps) - n
            del self.stamps[:k]
            del self.vecs[:k]
            del self.mats[:k]


class TfBuffer:
    """Static and dynamic transforms of a tf2 tree (each child has one parent; Foote 2013, "tf: The
    transform library", TePRA — lookups compose the edges through the common ancestor).

    Dynamic edges keep the last ``history`` samples and are interpolated at the query stamp
    (held at the ends); static edges are fixed. Frame ids are compared without a leading ``/``.
    A lookup composes the edges up to the lowest common ancestor of the two frames only, so a
    static sensor mount is not disturbed by the (dynamic) odometry edges above the base.
    """

    def __init__(self, history: int = 1000) -> None:
        self.parent: dict[str, str] = {}
        self.latest_dynamic = -math.inf  # newest stamp of any dynamic transform (s)
        self.static: dict[str, Array] = {}
        self.dynamic: dict[str, PoseTrack] = {}
        self.history = history
        self.version = 0  # bumped whenever the tree or a static edge changes
        self._cache: dict[tuple[str, str], tuple[int, Array | None]] = {}

    def __contains__(self, frame: str) -> bool:
        f = strip_frame(frame)
        return f in self.parent or f in self.parent.values()

    def set_transform(self, parent: str, child: str, vec_or_pose: Array, stamp: float = 0.0, static: bool = False) -> None:
        """Record ``parent_T_child``, given as a 4×4 pose or a ``(7,)`` translation + quaternion."""
        parent, child = strip_frame(parent), strip_frame(child)
        v = np.asarray(vec_or_pose, dtype=float)
        if self.parent.get(child) != parent:
            self.static.pop(child, None)
            self.dynamic.pop(child, None)
            self.parent[child] = parent
            self.version += 1
        if static or child in self.static:  # a static edge re-published on /tf stays static
            self.static[child] = vecs_to_matrices(v) if v.shape == (7,) else v
            self.dynamic.pop(child, None)
            self.version += 1
            return
        if v.shape != (7,):
            t, q = pose_formats.pose_to_quat(v)
            v = np.concatenate([t, q])
        track = self.dynamic.setdefault(child, PoseTrack(max_gap=math.inf))
        track.add(stamp, v)
        self.latest_dynamic = max(self.latest_dynamic, stamp)
        track.keep_last(self.history)

    def add_message(self, msg: Any, static: bool) -> None:
        """Add every ``geometry_msgs/TransformStamped`` of a ``tf2_msgs/TFMessage``."""
        for ts in msg.transforms:
            self.set_transform(ts.header.frame_id, ts.child_frame_id, transform_msg_vec(ts.transform), header_stamp(ts), static)

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        seen = {frame}
        while chain[-1] in self.parent:
            p = self.parent[chain[-1]]
            if p in seen:
                break  # a cycle: stop here
            chain.append(p)
            seen.add(p)
        return chain

    def _up(self, chain: list[str], stamp: float) -> tuple[Array, bool]:
        """``chain[-1]_T_chain[0]`` and whether every edge on the way is static."""
        T = np.eye(4)
        static = True
        for child in reversed(chain[:-1]):
            if child in self.static:
                E = self.static[child]
            else:
                static = False
                E = self.dynamic[child].query(stamp)
                assert E is not None
            T = T @ E
        return T, static

    def lookup(self, target: str, source: str, stamp: float) -> Array | None:
        """``target_T_source`` at *stamp* (maps points from *source* into *target*), or None when
        the two frames are not connected."""
        target, source = strip_frame(target), strip_frame(source)
        if target == source:
            return np.eye(4)
        hit = self._cache.get((target, source))
        if hit is not None and hit[0] == self.version:
            return None if hit[1] is None else hit[1].copy()
        ct, cs = self._chain(target), self._chain(source)
        common = set(ct) & set(cs)
        if not common:
            self._cache[(target, source)] = (self.version, None)
            return None
        lca = next(f for f in ct if f in common)
        lca_T_t, st = self._up(ct[: ct.index(lca) + 1], stamp)
        lca_T_s, ss = self._up(cs[: cs.index(lca) + 1], stamp)
        T = geo.inverse(lca_T_t) @ lca_T_s
        if st and ss:
            self._cache[(target, source)] = (self.version, T.copy())
        return T


# ----------------------------------------------------------------------------- shared reader


def base_candidates(odom_child: str | None) -> list[str]:
    """The frames that may be the robot base: the odometry's child frame, then base_link and base_footprint."""
    return ([odom_child] if odom_child else []) + [b for b in BASE_FRAMES if b != odom_child]


def tf_odometry(tf: TfBuffer, child: str, stamps: Sequence[float], max_gap: float) -> list[Array | None]:
    """``odom_T_child`` at *stamps* from TF, interpolated; None farther than *max_gap* (s) outside the samples
    of a direct odom → child edge, or when TF does not connect the two frames."""
    track = tf.dynamic.get(child) if tf.parent.get(child) == "odom" else None
    if track is not None:
        return track.query_many(stamps, max_gap=max_gap)
    return [tf.lookup("odom", child, t) for t in stamps]


def base_T_sensor(tf: TfBuffer, odom_child: str | None, sensor: str, stamp: float) -> Array:
    """``base_T_sensor`` from TF: base = the odometry child frame, else base_link / base_footprint; identity
    when TF does not connect any of them to the sensor frame."""
    for base in base_candidates(odom_child):
        if base == sensor or (base in tf and sensor in tf):
            T = tf.lookup(base, sensor, stamp)
            if T is not None:
                return T
    return np.eye(4)
