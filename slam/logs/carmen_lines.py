"""CARMEN laser lines to Frames: FLASER / RLASER / ROBOTLASER* fields parsed and checked (one vectorised
conversion for a block of FLASER lines, through a bounded cache of range tokens), beam angles, the laser's
mounting on the robot, no-return beams. Every bad field is a LogFormatError naming the file and line. The
format is described in :mod:`slam.logs.carmen`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core import geometry as geo
from core.errors import LogFormatError
from core.frame import Frame
from core.numbers import c_float, c_int

__all__ = ["parse_laser_line", "LASER_TAGS", "DEFAULT_FLASER_MAX_RANGE"]

#: Laser message tags a reader can turn into frames, in default-preference order.
LASER_TAGS: tuple[str, ...] = ("FLASER", "ROBOTLASER1", "RLASER", "ROBOTLASER2")
REAR_TAGS = frozenset({"RLASER", "ROBOTLASER2"})

#: FLASER/RLASER lines carry no max range; beams at or beyond this are no-return unless the log's
#: own saturation value is detected (see :func:`detect_saturation`) or one is given.
DEFAULT_FLASER_MAX_RANGE = 80.0

NUMERIC_ERRORS = (ValueError, TypeError, OverflowError)


class LineError(Exception):
    """A LogFormatError with the line number it refers to (to order errors within a block)."""

    def __init__(self, error: LogFormatError, lineno: int) -> None:
        super().__init__(str(error))
        self.error = error
        self.lineno = lineno


def format_error(path: str, lineno: int, what: str) -> LogFormatError:
    return LogFormatError(path, f"line {lineno}", what)


def short_token(tok: bytes, n: int = 24) -> str:
    s = tok.decode("utf-8", "replace")
    return repr(s if len(s) <= n else s[:n] + "…")


def c_array(tokens: list[bytes]) -> np.ndarray:
    """``np.array(tokens, float64)`` by the C locale grammar (:mod:`core.numbers`): numpy reads
    bytes as ``float()`` does, which also takes ``1_000``; non-ASCII bytes it refuses already."""
    if b"_" in b"".join(tokens):
        raise ValueError("a '_' digit group")
    return np.array(tokens, dtype=np.float64)


def parse_floats(tokens: list[bytes], path: str, lineno: int, what: str, first_field: int) -> np.ndarray:
    """Vectorised float conversion of *tokens* (fields ``first_field…`` of the line, 1-based);
    a non-numeric token is a LogFormatError naming its field."""
    try:
        return c_array(tokens)
    except NUMERIC_ERRORS:
        for i, tok in enumerate(tokens):
            try:
                c_float(tok)
            except NUMERIC_ERRORS:
                raise format_error(path, lineno, f"non-numeric {what} field {first_field + i}: {short_token(tok)}") from None
        raise format_error(path, lineno, f"non-numeric {what} fields") from None


def _count(tok: bytes, path: str, lineno: int, what: str) -> int:
    try:
        n = c_int(tok)
    except NUMERIC_ERRORS:
        raise format_error(path, lineno, f"{what} must be a non-negative integer, got {short_token(tok)}") from None
    if n < 0:
        raise format_error(path, lineno, f"{what} must be a non-negative integer, got {n}")
    return n


def parse_stamp(tokens: list[bytes], k: int, what: str, path: str, lineno: int) -> float:
    """The finite stamp (s) in field *k* of a line."""
    try:
        stamp = c_float(tokens[k])
    except NUMERIC_ERRORS:
        raise format_error(path, lineno, f"{what} must be a number, got {short_token(tokens[k])}") from None
    if not math.isfinite(stamp):
        raise format_error(path, lineno, f"{what} must be finite, got {stamp}")
    return stamp


_Beams = tuple[np.ndarray, np.ndarray, np.ndarray]
_ANGLE_CACHE: dict[tuple[float, float, int], _Beams] = {}


def flaser_layout(n: int) -> tuple[float, float]:
    """``(first beam angle, step)`` (rad) of an n-beam FLASER/RLASER line, whose beam angles the line does not carry.

    The step is the SICK LMS's in the mode the count names, as CARMEN's own reader guesses it
    (``carmen_laser_guess_angle_increment``, logtools/readlog.c): 1° for 180 or 181 beams, 0.5° for 360 or
    361, 0.25° for 400 or 401 (a 180-, 360- or 400-beam line lacks one beam of the mode's 181, 361 or 401);
    any other count spreads 180° over the n beams. The first beam is at −90°, as in CARMEN (a 180-beam line
    ends at +89°). Spreading 180 beams over 180° instead stretches every scan by 0.56 %, and a scan matcher
    then turns the robot 0.56 % too far (``docs/ODOMETRY.md``)."""
    if n in (180, 181):
        step = math.pi / 180.0
    elif n in (360, 361):
        step = math.pi / 360.0
    elif n in (400, 401):
        step = math.pi / 720.0
    else:
        step = math.pi / (n - 1) if n > 1 else 0.0
    return -0.5 * math.pi, step


def _beam_angles(start: float, step: float, n: int) -> _Beams:
    """``(angles, cos, sin)`` with ``angles = start + i·step`` for i < n (rad).

    Cached and read-only: a log has a handful of beam layouts shared by thousands of frames.
    """
    key = (start, step, n)
    hit = _ANGLE_CACHE.get(key)
    if hit is None:
        a = start + step * np.arange(n, dtype=np.float64)
        hit = (a, np.cos(a), np.sin(a))
        for arr in hit:
            arr.flags.writeable = False
        if len(_ANGLE_CACHE) < 1024:
            _ANGLE_CACHE[key] = hit
    return hit


@dataclass(frozen=True)
class LaserLine:
    """The numbers of one laser line before they become a Frame."""

    tag: str
    stamp: float
    angles: _Beams  # beam angles (rad) in the laser frame, with their cos and sin
    ranges: np.ndarray  # raw readings (m)
    laser_pose: np.ndarray  # (x, y, θ) of the laser in the odometry frame
    robot_pose: np.ndarray  # (x, y, θ) of the robot base in the odometry frame
    max_range: float | None  # from the line (ROBOTLASER*), None for FLASER/RLASER
    rmin: float  # smallest and largest reading (m)
    rmax: float


def parse_numbers(tokens: list[bytes], path: str, lineno: int) -> LaserLine:
    """Split the tokens of one laser line (tag first) into its numbers, checking counts and values."""
    tag = tokens[0].decode("ascii")
    nt = len(tokens)
    if tag in ("FLASER", "RLASER"):
        if nt < 2:
            raise format_error(path, lineno, f"{tag} without num_readings")
        n = _count(tokens[1], path, lineno, "num_readings")
        if nt != n + 11:
            raise format_error(path, lineno, f"{tag} with num_readings={n} needs {n + 11} fields "
                                      f"(tag, n, {n} ranges, 6 pose values, ipc_timestamp, host, logger_timestamp), got {nt}")
        vals = parse_floats(tokens[2:n + 8], path, lineno, tag, 3)
        ranges, poses = vals[:n], vals[n:]
        laser, robot = poses[:3], poses[3:]
        angles = _beam_angles(*flaser_layout(n), n)
        max_range = None
    else:  # ROBOTLASER1 / ROBOTLASER2
        if nt < 10:
            raise format_error(path, lineno, f"{tag} needs at least 24 fields, got {nt}")
        head = parse_floats(tokens[1:8], path, lineno, f"{tag} header", 2)
        start, fov, res, max_range = (float(v) for v in head[1:5])
        n = _count(tokens[8], path, lineno, "num_readings")
        if nt < n + 10:
            raise format_error(path, lineno, f"{tag} with num_readings={n} is cut short ({nt} fields)")
        n_rem = _count(tokens[9 + n], path, lineno, "num_remissions")
        if nt != n + n_rem + 24:
            raise format_error(path, lineno, f"{tag} with {n} readings and {n_rem} remissions needs "
                                      f"{n + n_rem + 24} fields, got {nt}")
        ranges = parse_floats(tokens[9:9 + n], path, lineno, tag, 10)
        poses = parse_floats(tokens[10 + n + n_rem:16 + n + n_rem], path, lineno, f"{tag} pose", 11 + n + n_rem)
        laser, robot = poses[:3], poses[3:]
        if not (math.isfinite(start) and math.isfinite(res) and math.isfinite(fov)):
            raise format_error(path, lineno, f"{tag} start_angle/fov/angular_res must be finite")
        if not (max_range > 0.0):
            raise format_error(path, lineno, f"{tag} max_range must be positive, got {max_range}")
        angles = _beam_angles(start, res, n)
    stamp = parse_stamp(tokens, -3, "ipc_timestamp (third-last field)", path, lineno)
    parse_stamp(tokens, -1, "logger_timestamp (last field)", path, lineno)
    if n == 0:
        raise format_error(path, lineno, f"empty {tag} scan (num_readings 0)")
    if not math.isfinite(float(np.add.reduce(poses))) and not np.isfinite(poses).all():
        raise format_error(path, lineno, f"{tag} laser/robot pose must be finite")
    rmin = float(np.minimum.reduce(ranges))
    if not rmin >= 0.0:  # also catches NaN (np.minimum propagates it)
        bad = np.isnan(ranges) | (ranges < 0.0)
        i = int(np.argmax(bad))
        raise format_error(path, lineno, f"{tag} range {i + 1} is {ranges[i]} (ranges must be ≥ 0, not NaN)")
    return LaserLine(tag, stamp, angles, ranges, laser, robot, max_range, rmin, float(np.maximum.reduce(ranges)))


def _mounting(tags: list[str], odom: np.ndarray, laser: np.ndarray) -> np.ndarray:
    """``base_T_sensor = odom_T_base⁻¹ · odom_T_laser`` for a stack of lines ``(N, 4, 4)``."""
    b_T_s = geo.relative(odom, laser)
    rear = np.fromiter((t in REAR_TAGS for t in tags), bool, len(tags))
    if rear.any():
        # The rear laser faces backwards; logs that write the rear laser pose with the robot's
        # heading leave the half turn implicit.
        fix = rear & (np.abs(np.arctan2(b_T_s[:, 1, 0], b_T_s[:, 0, 0])) < 0.5 * math.pi)
        b_T_s[fix] = b_T_s[fix] @ geo.xytheta_to_matrix(0.0, 0.0, math.pi)
    return b_T_s


def lasers_to_frames(
    lasers: list[LaserLine], linenos: list[int], *, first_index: int, name: str, flaser_max_range: float | None,
    override: float | None,
) -> list[Frame]:
    """Build Frames for a batch of parsed lines (poses converted in one vectorised call).

    No-return threshold (m): *override* when given, else the line's own max range
    (ROBOTLASER*), else *flaser_max_range* (FLASER/RLASER), else :data:`DEFAULT_FLASER_MAX_RANGE`.
    """
    if not lasers:
        return []
    odom = geo.xytheta_to_matrix(np.array([las.robot_pose for las in lasers]))
    laser_T = geo.xytheta_to_matrix(np.array([las.laser_pose for las in lasers]))
    b_T_s = _mounting([las.tag for las in lasers], odom, laser_T)
    out = []
    for k, las in enumerate(lasers):
        if override is not None:
            max_range = override
        elif las.max_range is not None:
            max_range = las.max_range
        elif flaser_max_range is not None:
            max_range = flaser_max_range
        else:
            max_range = DEFAULT_FLASER_MAX_RANGE
        r = las.ranges
        angles, cos, sin = las.angles
        if las.rmin <= 0.0:  # zero = "no measurement": drop the beam
            valid = r > 0.0
            r, angles, cos, sin = r[valid], angles[valid], cos[valid], sin[valid]
        no_return = r >= max_range
        if las.rmax >= max_range:
            hit = ~no_return
            rh = r[hit]
            pts = np.stack((rh * cos[hit], rh * sin[hit]), axis=1)
            r = np.where(no_return, np.inf, r)
        else:
            pts = np.stack((r * cos, r * sin), axis=1)
        out.append(Frame(
            stamp=las.stamp, points=pts, index=first_index + k, angles=angles, ranges=r, no_return=no_return,
            odom=odom[k], base_T_sensor=b_T_s[k], max_range=float(max_range), source=f"{name}:line {linenos[k]}",
        ))
    return out


class FloatCache(dict):
    """``token → float(token)``, filled on demand and emptied when it grows past *limit* entries
    (so memory stays bounded whatever the log)."""

    def __init__(self, limit: int = 1 << 16) -> None:
        super().__init__()
        self.limit = limit

    def __missing__(self, key: bytes) -> float:
        v = c_float(key)
        if len(self) >= self.limit:
            self.clear()
        self[key] = v
        return v


def flaser_block(
    rows: list[list[bytes]], linenos: list[int], *, path: str, name: str, first_index: int, max_range: float,
    cache: FloatCache,
) -> tuple[list[Frame], "LineError | None"]:
    """Frames of a block's FLASER/RLASER lines (the hot path), and the error of the first bad line.

    When every line of the block has the same beam count, all numbers of the block are converted
    by one ``np.array`` call and checked, projected and masked as ``(m, n)`` arrays; otherwise,
    or when something is wrong, the lines go through :func:`parse_numbers` one by one, which
    names the exact problem. Frames come only from the lines before the first bad one.
    """
    m = len(rows)
    if m == 0:
        return [], None
    nt = len(rows[0])
    n = nt - 11
    vals = None
    if n >= 1 and all(len(r) == nt for r in rows):
        nb = str(n).encode()
        if all(r[1] == nb for r in rows):
            rtoks: list[bytes] = []
            other: list[bytes] = []
            for r in rows:
                rtoks += r[2:n + 2]
                other += r[n + 2:n + 8]
                other.append(r[-3])
                other.append(r[-1])
            try:
                # Ranges repeat (a few thousand distinct tokens in a log): converting each distinct
                # token once through the cache is ~3× faster than np.array on all of them, and
                # float() is exactly the conversion np.array applies to bytes.
                R = np.fromiter(map(cache.__getitem__, rtoks), np.float64, m * n).reshape(m, n)
                vals = np.concatenate([R, c_array(other).reshape(m, 8)], axis=1)
            except NUMERIC_ERRORS:
                vals = None
    if vals is None:  # irregular or malformed block: line by line
        lasers: list[LaserLine] = []
        for r, ln in zip(rows, linenos):
            try:
                lasers.append(parse_numbers(r, path, ln))
            except LogFormatError as exc:
                good = lasers_to_frames(lasers, linenos[:len(lasers)], first_index=first_index, name=name,
                                  flaser_max_range=max_range, override=None)
                return good, LineError(exc, ln)
        return lasers_to_frames(lasers, linenos, first_index=first_index, name=name, flaser_max_range=max_range,
                          override=None), None
    R = vals[:, :n]
    rmin = R.min(axis=1)
    ok = (rmin >= 0.0) & np.isfinite(vals[:, n:]).all(axis=1)  # rmin ≥ 0 is False for NaN
    error = None
    if not ok.all():
        bad = int(np.argmin(ok))
        try:
            parse_numbers(rows[bad], path, linenos[bad])
        except LogFormatError as exc:
            error = LineError(exc, linenos[bad])
        else:  # pragma: no cover - the two checks agree
            raise AssertionError(f"{path}:line {linenos[bad]}: block check and line parser disagree")
        m = bad
        R, vals, rmin = R[:m], vals[:m], rmin[:m]
    if m == 0:
        return [], error
    tag = rows[0][0].decode("ascii")
    P = vals[:, n:n + 6]
    odom = geo.xytheta_to_matrix(P[:, 3:6])
    b_T_s = _mounting([tag] * m, odom, geo.xytheta_to_matrix(P[:, 0:3]))
    angles, cos, sin = _beam_angles(*flaser_layout(n), n)
    NR = R >= max_range
    XY = np.stack((R * cos, R * sin), axis=-1)
    Rout = np.where(NR, np.inf, R)
    stamps = vals[:, n + 6]
    frames: list[Frame] = []
    for k in range(m):
        if rmin[k] <= 0.0:  # zero readings to drop: the general path
            las = LaserLine(tag, float(stamps[k]), (angles, cos, sin), R[k], P[k, :3], P[k, 3:], None,
                         float(rmin[k]), float(R[k].max()))
            frames += lasers_to_frames([las], [linenos[k]], first_index=first_index + k, name=name,
                                 flaser_max_range=max_range, override=None)
            continue
        nr = NR[k]
        frames.append(Frame(
            stamp=float(stamps[k]), points=XY[k][~nr], index=first_index + k, angles=angles, ranges=Rout[k],
            no_return=nr, odom=odom[k], base_T_sensor=b_T_s[k], max_range=float(max_range),
            source=f"{name}:line {linenos[k]}",
        ))
    return frames, error


def parse_laser_line(
    line: bytes | str,
    *,
    path: str = "<line>",
    lineno: int = 1,
    index: int = 0,
    max_range: float | None = None,
) -> Frame:
    """Parse one ``FLASER``/``RLASER``/``ROBOTLASER1``/``ROBOTLASER2`` line into a Frame.

    Args:
        line: the text of the line (bytes or str).
        path, lineno: used in error messages and ``Frame.source``.
        index: the scan's position in its log.
        max_range: no-return threshold (m); None = the line's own max range for ROBOTLASER*,
            :data:`DEFAULT_FLASER_MAX_RANGE` for FLASER/RLASER.

    Raises:
        LogFormatError: any malformed line (wrong tag, field count, non-numeric, NaN/negative
            range, empty scan), naming ``path`` and ``line lineno``.
    """
    if isinstance(line, str):
        line = line.encode("utf-8", "surrogateescape")
    tokens = line.split()
    if not tokens or tokens[0] not in (b"FLASER", b"RLASER", b"ROBOTLASER1", b"ROBOTLASER2"):
        raise format_error(path, lineno, f"expected a laser message (one of {', '.join(LASER_TAGS)}), got "
                                  f"{short_token(tokens[0]) if tokens else 'an empty line'}")
    las = parse_numbers(tokens, path, lineno)
    return lasers_to_frames([las], [lineno], first_index=index, name=Path(path).name, flaser_max_range=None,
                      override=max_range)[0]
