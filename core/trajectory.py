"""Trajectory files: TUM, KITTI and the VERTEX lines of g2o graphs, read and written at full precision.

A :class:`Trajectory` holds ``stamps (N,)`` float64 seconds and ``poses (N, 4, 4)`` float64
``world_T_base`` matrices (metres, radians). Formats:

* TUM (Sturm et al., IROS 2012, the format ``evo_traj tum`` reads): one pose per line,
  ``stamp x y z qx qy qz qw``; ``#`` starts a comment.
* KITTI odometry poses (Geiger et al., CVPR 2012): one pose per line, the 12 entries of the
  upper 3×4 block row-major; no stamps (stamps are the line index, or read from a ``times.txt``).
* g2o ``VERTEX_SE2 id x y θ`` / ``VERTEX_SE3:QUAT id x y z qx qy qz qw``; stamps are the vertex ids
  unless a stamp file is given.

The poses of robot logs' scans are read by :mod:`slam.trajectory_io`.

Every reader returns the poses sorted by stamp (:meth:`Trajectory.sorted_by_stamp`), whatever the order
of the lines: associations and relative errors must not depend on it.

Numbers are written with ``repr`` (the shortest string that reads back to the same float64), so
a write → read round trip is exact for stamps and translations. Files are written atomically.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
from numpy.typing import NDArray

from core import geometry as geo
from core import pose_formats
from core.atomic import atomic_open
from core.errors import GeometryError, LogFormatError
from core.numbers import c_floats, c_int
from core.textfile import text_lines

Array = NDArray[np.float64]
PathLike = str | os.PathLike[str]

__all__ = [
    "Trajectory",
    "read_tum",
    "write_tum",
    "read_kitti",
    "write_kitti",
    "read_g2o_vertices",
    "read_node_stamps",
    "read_trajectory_file",
]


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A timed sequence of poses.

    Attributes:
        stamps: ``(N,)`` float64, seconds (or vertex ids / line indices when the file has no time).
        poses: ``(N, 4, 4)`` float64 ``world_T_base`` poses, metres.
        name: a label for plots and reports (usually the file name).
    """

    stamps: Array
    poses: Array
    name: str = ""

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise GeometryError(f"trajectory poses must be (N, 4, 4), got {poses.shape}")
        if poses.shape[0] != stamps.shape[0]:
            raise GeometryError(f"trajectory has {stamps.shape[0]} stamps but {poses.shape[0]} poses")
        object.__setattr__(self, "stamps", stamps)
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    @property
    def positions(self) -> Array:
        """``(N, 3)`` translations, metres."""
        return self.poses[:, :3, 3]

    def is_planar(self, tol: float = 1e-9) -> bool:
        """True when every pose has z = 0 and rotates about z only (a 2D trajectory)."""
        if len(self) == 0:
            return True
        P = self.poses
        return bool(
            np.all(np.abs(P[:, 2, 3]) <= tol)
            and np.all(np.abs(P[:, 2, :2]) <= tol)
            and np.all(np.abs(P[:, :2, 2]) <= tol)
            and np.all(np.abs(P[:, 2, 2] - 1.0) <= tol)
        )

    def sorted_by_stamp(self) -> "Trajectory":
        """The poses in stamp order (every reader returns this). Equal stamps are ordered by their pose
        entries, so the result does not depend on the order of the lines it was read from."""
        n = len(self)
        order = np.lexsort((*self.poses.reshape(n, 16).T[::-1], self.stamps))
        return self.subset(order)

    def subset(self, index: NDArray[np.integer] | slice) -> "Trajectory":
        """The poses at *index* (an integer array, boolean mask or slice)."""
        return Trajectory(self.stamps[index], self.poses[index], self.name)

    def path_length(self) -> float:
        """Travelled distance Σ‖p_{k+1} − p_k‖, metres."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())


# ----------------------------------------------------------------------------- helpers

def _number_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """Yield (1-based line number, fields) for every non-empty, non-comment line."""
    for lineno, line in text_lines(path, LogFormatError, "a trajectory file"):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        yield lineno, s.replace(",", " ").split()


def _floats(path: Path, lineno: int, fields: list[str], what: str) -> list[float]:
    try:
        vals = c_floats(fields)
    except ValueError as exc:
        raise LogFormatError(path, f"line {lineno}", f"{exc}, expected {what}") from None
    if not all(np.isfinite(vals)):
        raise LogFormatError(path, f"line {lineno}", f"non-finite number, expected {what}")
    return vals


def _vertex_id(path: Path, lineno: int, field: str) -> int:
    try:
        return c_int(field)
    except ValueError:
        raise LogFormatError(path, f"line {lineno}", f"vertex id must be an integer, got {field!r}") from None


def _fmt(values: Iterable[float]) -> str:
    # repr(float) is the shortest string that round-trips to the same double.
    return " ".join(repr(float(v)) for v in values)


# ----------------------------------------------------------------------------- TUM

def read_tum(path: PathLike) -> Trajectory:
    """Read a TUM trajectory ``stamp x y z qx qy qz qw`` (quaternions normalised on read).

    Raises:
        LogFormatError: naming the file and line when a line has not 8 finite numbers or a
            zero quaternion.
    """
    p = Path(path)
    rows: list[list[float]] = []
    for lineno, fields in _number_lines(p):
        if len(fields) != 8:
            raise LogFormatError(p, f"line {lineno}", f"expected 8 fields 'stamp x y z qx qy qz qw', got {len(fields)}")
        vals = _floats(p, lineno, fields, "'stamp x y z qx qy qz qw'")
        if np.linalg.norm(vals[4:8]) < 1e-12:
            raise LogFormatError(p, f"line {lineno}", "zero quaternion")
        rows.append(vals)
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)
    poses = pose_formats.pose_from_quat(data[:, 1:4], data[:, 4:8]) if len(data) else np.zeros((0, 4, 4))
    return Trajectory(data[:, 0], poses, p.name).sorted_by_stamp()


def write_tum(path: PathLike, trajectory: Trajectory) -> None:
    """Write *trajectory* as TUM lines with ``repr``-exact numbers (atomically)."""
    t, q = pose_formats.pose_to_quat(trajectory.poses) if len(trajectory) else (np.zeros((0, 3)), np.zeros((0, 4)))
    data = np.column_stack([trajectory.stamps, t, q]) if len(trajectory) else np.zeros((0, 8))
    with atomic_open(path, "w", encoding="utf-8") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        fh.writelines(_fmt(row) + "\n" for row in data.tolist())


# ----------------------------------------------------------------------------- KITTI

def _read_stamp_file(path: Path, n: int | None = None) -> Array:
    """One stamp per line (KITTI ``times.txt``), or ``id stamp`` pairs (the second column is used)."""
    vals: list[float] = []
    for lineno, fields in _number_lines(path):
        if len(fields) not in (1, 2):
            raise LogFormatError(path, f"line {lineno}", "expected 'stamp' or 'id stamp'")
        vals.append(_floats(path, lineno, fields, "a stamp")[-1])
    out = np.array(vals, dtype=np.float64)
    if n is not None and len(out) != n:
        raise LogFormatError(path, None, f"has {len(out)} stamps but the trajectory has {n} poses")
    return out


def read_kitti(path: PathLike, stamps: PathLike | None = None) -> Trajectory:
    """Read KITTI poses (12 numbers per line, the 3×4 block row-major).

    Args:
        path: the poses file.
        stamps: optional ``times.txt`` (one stamp per line); without it the stamps are 0, 1, 2, ….
    """
    p = Path(path)
    rows: list[list[float]] = []
    for lineno, fields in _number_lines(p):
        if len(fields) != 12:
            raise LogFormatError(p, f"line {lineno}", f"expected 12 numbers (3x4 pose row-major), got {len(fields)}")
        rows.append(_floats(p, lineno, fields, "12 numbers"))
    data = np.array(rows, dtype=np.float64).reshape(-1, 3, 4)
    poses = np.zeros((len(data), 4, 4))
    poses[:, :3, :] = data
    poses[:, 3, 3] = 1.0
    st = _read_stamp_file(Path(stamps), len(data)) if stamps is not None else np.arange(len(data), dtype=np.float64)
    return Trajectory(st, poses, p.name).sorted_by_stamp()


def write_kitti(path: PathLike, trajectory: Trajectory) -> None:
    """Write KITTI pose lines (the 3×4 block row-major, ``repr``-exact; stamps are not stored)."""
    flat = trajectory.poses[:, :3, :].reshape(-1, 12)
    with atomic_open(path, "w", encoding="utf-8") as fh:
        fh.writelines(_fmt(row) + "\n" for row in flat.tolist())


# ----------------------------------------------------------------------------- g2o

def read_g2o_vertices(path: PathLike, stamps: PathLike | None = None) -> Trajectory:
    """Read the ``VERTEX_SE2`` / ``VERTEX_SE3:QUAT`` lines of a g2o file, sorted by vertex id.

    Other lines (edges, ``FIX``, comments) are ignored. Stamps are the vertex ids unless
    *stamps* names a file with one stamp per vertex (in id order) or ``id stamp`` pairs.
    """
    p = Path(path)
    ids: list[int] = []
    poses: list[Array] = []
    for lineno, fields in _number_lines(p):
        tag = fields[0]
        if tag == "VERTEX_SE2":
            if len(fields) != 5:
                raise LogFormatError(p, f"line {lineno}", "expected 'VERTEX_SE2 id x y theta'")
            ids.append(_vertex_id(p, lineno, fields[1]))
            v = _floats(p, lineno, fields[2:], "'VERTEX_SE2 id x y theta'")
            poses.append(geo.xytheta_to_matrix(v[0], v[1], v[2]))
        elif tag == "VERTEX_SE3:QUAT":
            if len(fields) != 9:
                raise LogFormatError(p, f"line {lineno}", "expected 'VERTEX_SE3:QUAT id x y z qx qy qz qw'")
            ids.append(_vertex_id(p, lineno, fields[1]))
            v = _floats(p, lineno, fields[2:], "'VERTEX_SE3:QUAT id x y z qx qy qz qw'")
            if np.linalg.norm(v[3:7]) < 1e-12:
                raise LogFormatError(p, f"line {lineno}", "zero quaternion")
            poses.append(pose_formats.pose_from_quat(v[0:3], v[3:7]))
    if len(set(ids)) != len(ids):
        raise LogFormatError(p, None, "duplicate vertex id")
    order = np.argsort(np.array(ids, dtype=np.int64), kind="stable")
    id_arr = np.array(ids, dtype=np.float64)[order]
    P = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)[order]
    st = read_node_stamps(stamps, id_arr.astype(np.int64)) if stamps is not None else id_arr
    return Trajectory(st, P, p.name).sorted_by_stamp()


def read_node_stamps(path: PathLike, ids: NDArray[np.integer]) -> Array:
    """The stamp (s) of each node id in *ids*, from a file of ``id stamp`` lines (e.g. ``node_stamps.txt``
    of a run) or of one stamp per line, in the order of *ids*.

    Raises:
        LogFormatError: naming the file (and line): a malformed line, an id without a stamp, or a count
            of bare stamps that differs from the number of ids.
    """
    p = Path(path)
    rows = list(_number_lines(p))
    if rows and all(len(f) == 2 for _, f in rows):
        pairs = {}
        for lineno, f in rows:
            pairs[_vertex_id(p, lineno, f[0])] = _floats(p, lineno, f[1:], "'id stamp'")[0]
        missing = [int(i) for i in ids if int(i) not in pairs]
        if missing:
            raise LogFormatError(p, None, f"no stamp for node id {missing[0]}")
        return np.array([pairs[int(i)] for i in ids], dtype=np.float64)
    return _read_stamp_file(p, len(ids))


def read_trajectory_file(path: PathLike, fmt: str = "auto", stamps: PathLike | None = None) -> Trajectory:
    """Read a trajectory file of format ``tum``, ``kitti``, ``g2o`` or ``auto`` (by suffix, then by the first
    line's field count: 12 numbers are KITTI, a ``VERTEX`` line g2o, anything else TUM). Robot logs are read
    by :func:`slam.trajectory_io.read_trajectory`."""
    p = Path(path)
    if fmt == "auto":
        suffix = p.suffix.lower()
        if suffix == ".g2o":
            fmt = "g2o"
        elif suffix == ".kitti":
            fmt = "kitti"
        else:
            fmt = "tum"
            for _, fields in _number_lines(p):
                if fields[0].startswith("VERTEX"):
                    fmt = "g2o"
                elif len(fields) == 12:
                    fmt = "kitti"
                break
    if fmt == "tum":
        return read_tum(p)
    if fmt == "kitti":
        return read_kitti(p, stamps)
    if fmt == "g2o":
        return read_g2o_vertices(p, stamps)
    raise LogFormatError(p, None, f"unknown trajectory format {fmt!r} (expected tum, kitti, g2o, log_gt, log_odom or auto)")
