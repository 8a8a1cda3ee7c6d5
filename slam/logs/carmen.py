"""CARMEN robot logs (``.clf`` / ``.log``, plain, ``.bz2`` or ``.gz``) as a stream of laser Frames.

Format: one message per line, ``TAG field … ipc_timestamp ipc_hostname logger_timestamp``
(CARMEN logger; the layouts below are the ones of the Kümmerle et al. 2009 benchmark logs):

* ``FLASER n r_1 … r_n x y theta odom_x odom_y odom_theta ipc_ts host logger_ts`` (front laser);
  ``RLASER`` has the same layout for the rear laser. The n beams are spread evenly over 180°, the
  first at −90° (``angle_i = −π/2 + i·π/(n−1)``). ``x y theta`` is the laser pose and
  ``odom_*`` the robot pose, both in the odometry frame.
* ``ROBOTLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode n r_1 … r_n
  n_rem rem_1 … rem_k laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd_safety
  side_safety turn_axis ipc_ts host logger_ts`` (``ROBOTLASER2`` likewise, second laser):
  ``angle_i = start_angle + i·angular_res``.
* ``ODOM x y theta tv rv accel ipc_ts host logger_ts``.
* ``PARAM``, ``SYNC``, ``TRUEPOS``, ``NMEA-*``, ``RAWLASER*`` … and ``#`` comments are skipped.

Frames of reference and units: ranges and points in metres in the **laser** frame (x forward);
``Frame.odom`` is the robot pose ``odom_T_base`` from the laser line's robot-pose fields;
``Frame.base_T_sensor = odom_T_base⁻¹ · odom_T_laser`` from the two poses on the same line
(identity on many logs, a few centimetres ahead on others). The stamp is the ``ipc_timestamp`` (seconds),
the one the Kümmerle relations refer to.

Beams at or beyond the max range (81.83 / 81.91 saturation values in the benchmark logs) or
``inf`` are *no-return* beams: ``ranges`` holds ``inf`` for them, as the Frame contract says.
Zero readings (the SICK "no measurement" code) are dropped from the beam arrays (their angle
carries no information). NaN or negative ranges, wrong field counts, non-numeric fields, empty
scans and corrupt or truncated compressed streams raise :class:`LogFormatError` naming the file
and line.

Reading is streaming with constant memory: the file is decompressed in blocks of about 1 MiB
by a background thread (bz2/zlib release the GIL, so decompression overlaps parsing), each
block is split into lines in bulk, and all FLASER/RLASER numbers of a block are converted and
checked as one ``(scans, beams)`` array (each distinct range token is converted once, through
a bounded cache; no per-beam Python loop). ROBOTLASER lines, and blocks with irregular or bad lines, are parsed line
by line, which also yields the precise error message.
"""

from __future__ import annotations

import bz2
import gzip
import math
import queue
import re
import threading
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Iterator

import numpy as np

from core import geometry as geo
from core.errors import LogFormatError, TopicNotFoundError
from core.frame import Frame
from core.numbers import c_float, c_int

from .base import UNKNOWN, LogInfo, LogReader, SkipHandler, TopicInfo, counting, lost

__all__ = ["CarmenReader", "parse_laser_line", "LASER_TAGS", "DEFAULT_FLASER_MAX_RANGE"]

#: Laser message tags a reader can turn into frames, in default-preference order.
LASER_TAGS: tuple[str, ...] = ("FLASER", "ROBOTLASER1", "RLASER", "ROBOTLASER2")
_REAR_TAGS = frozenset({"RLASER", "ROBOTLASER2"})
_TOPIC_ALIASES = {"FRONT": "FLASER", "REAR": "RLASER", "FLASER": "FLASER", "RLASER": "RLASER",
                  "ROBOTLASER1": "ROBOTLASER1", "ROBOTLASER2": "ROBOTLASER2"}

#: FLASER/RLASER lines carry no max range; beams at or beyond this are no-return unless the log's
#: own saturation value is detected (see :func:`detect_saturation`) or one is given.
DEFAULT_FLASER_MAX_RANGE = 80.0

_TAG_RE = re.compile(rb"^[A-Z][A-Z0-9_\-]*$")
_BLOCK = 1 << 20
_PROBE_BYTES = 1 << 20
_PROBE_SCANS = 400
_NUMERIC_ERRORS = (ValueError, TypeError, OverflowError)


# ----------------------------------------------------------------------------- line parsing

def _fail(path: str, lineno: int, what: str) -> LogFormatError:
    return LogFormatError(path, f"line {lineno}", what)


def _short(tok: bytes, n: int = 24) -> str:
    s = tok.decode("utf-8", "replace")
    return repr(s if len(s) <= n else s[:n] + "…")


def _c_array(tokens: list[bytes]) -> np.ndarray:
    """``np.array(tokens, float64)`` by the C locale grammar (:mod:`core.numbers`): numpy reads
    bytes as ``float()`` does, which also takes ``1_000``; non-ASCII bytes it refuses already."""
    if b"_" in b"".join(tokens):
        raise ValueError("a '_' digit group")
    return np.array(tokens, dtype=np.float64)


def _floats(tokens: list[bytes], path: str, lineno: int, what: str, first_field: int) -> np.ndarray:
    """Vectorised float conversion of *tokens* (fields ``first_field…`` of the line, 1-based);
    a non-numeric token is a LogFormatError naming its field."""
    try:
        return _c_array(tokens)
    except _NUMERIC_ERRORS:
        for i, tok in enumerate(tokens):
            try:
                c_float(tok)
            except _NUMERIC_ERRORS:
                raise _fail(path, lineno, f"non-numeric {what} field {first_field + i}: {_short(tok)}") from None
        raise _fail(path, lineno, f"non-numeric {what} fields") from None


def _count(tok: bytes, path: str, lineno: int, what: str) -> int:
    try:
        n = c_int(tok)
    except _NUMERIC_ERRORS:
        raise _fail(path, lineno, f"{what} must be a non-negative integer, got {_short(tok)}") from None
    if n < 0:
        raise _fail(path, lineno, f"{what} must be a non-negative integer, got {n}")
    return n


def _stamp(tokens: list[bytes], k: int, what: str, path: str, lineno: int) -> float:
    """The finite stamp (s) in field *k* of a line."""
    try:
        stamp = c_float(tokens[k])
    except _NUMERIC_ERRORS:
        raise _fail(path, lineno, f"{what} must be a number, got {_short(tokens[k])}") from None
    if not math.isfinite(stamp):
        raise _fail(path, lineno, f"{what} must be finite, got {stamp}")
    return stamp


_Beams = tuple[np.ndarray, np.ndarray, np.ndarray]
_ANGLE_CACHE: dict[tuple[float, float, int], _Beams] = {}


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
class _Laser:
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


def _parse_numbers(tokens: list[bytes], path: str, lineno: int) -> _Laser:
    """Split the tokens of one laser line (tag first) into its numbers, checking counts and values."""
    tag = tokens[0].decode("ascii")
    nt = len(tokens)
    if tag in ("FLASER", "RLASER"):
        if nt < 2:
            raise _fail(path, lineno, f"{tag} without num_readings")
        n = _count(tokens[1], path, lineno, "num_readings")
        if nt != n + 11:
            raise _fail(path, lineno, f"{tag} with num_readings={n} needs {n + 11} fields "
                                      f"(tag, n, {n} ranges, 6 pose values, ipc_timestamp, host, logger_timestamp), got {nt}")
        vals = _floats(tokens[2:n + 8], path, lineno, tag, 3)
        ranges, poses = vals[:n], vals[n:]
        laser, robot = poses[:3], poses[3:]
        angles = _beam_angles(-0.5 * math.pi, math.pi / (n - 1) if n > 1 else 0.0, n)
        max_range = None
    else:  # ROBOTLASER1 / ROBOTLASER2
        if nt < 10:
            raise _fail(path, lineno, f"{tag} needs at least 24 fields, got {nt}")
        head = _floats(tokens[1:8], path, lineno, f"{tag} header", 2)
        start, fov, res, max_range = (float(v) for v in head[1:5])
        n = _count(tokens[8], path, lineno, "num_readings")
        if nt < n + 10:
            raise _fail(path, lineno, f"{tag} with num_readings={n} is cut short ({nt} fields)")
        n_rem = _count(tokens[9 + n], path, lineno, "num_remissions")
        if nt != n + n_rem + 24:
            raise _fail(path, lineno, f"{tag} with {n} readings and {n_rem} remissions needs "
                                      f"{n + n_rem + 24} fields, got {nt}")
        ranges = _floats(tokens[9:9 + n], path, lineno, tag, 10)
        poses = _floats(tokens[10 + n + n_rem:16 + n + n_rem], path, lineno, f"{tag} pose", 11 + n + n_rem)
        laser, robot = poses[:3], poses[3:]
        if not (math.isfinite(start) and math.isfinite(res) and math.isfinite(fov)):
            raise _fail(path, lineno, f"{tag} start_angle/fov/angular_res must be finite")
        if not (max_range > 0.0):
            raise _fail(path, lineno, f"{tag} max_range must be positive, got {max_range}")
        angles = _beam_angles(start, res, n)
    stamp = _stamp(tokens, -3, "ipc_timestamp (third-last field)", path, lineno)
    _stamp(tokens, -1, "logger_timestamp (last field)", path, lineno)
    if n == 0:
        raise _fail(path, lineno, f"empty {tag} scan (num_readings 0)")
    if not math.isfinite(float(np.add.reduce(poses))) and not np.isfinite(poses).all():
        raise _fail(path, lineno, f"{tag} laser/robot pose must be finite")
    rmin = float(np.minimum.reduce(ranges))
    if not rmin >= 0.0:  # also catches NaN (np.minimum propagates it)
        bad = np.isnan(ranges) | (ranges < 0.0)
        i = int(np.argmax(bad))
        raise _fail(path, lineno, f"{tag} range {i + 1} is {ranges[i]} (ranges must be ≥ 0, not NaN)")
    return _Laser(tag, stamp, angles, ranges, laser, robot, max_range, rmin, float(np.maximum.reduce(ranges)))


def _mounting(tags: list[str], odom: np.ndarray, laser: np.ndarray) -> np.ndarray:
    """``base_T_sensor = odom_T_base⁻¹ · odom_T_laser`` for a stack of lines ``(N, 4, 4)``."""
    b_T_s = geo.relative(odom, laser)
    rear = np.fromiter((t in _REAR_TAGS for t in tags), bool, len(tags))
    if rear.any():
        # The rear laser faces backwards; logs that write the rear laser pose with the robot's
        # heading leave the half turn implicit.
        fix = rear & (np.abs(np.arctan2(b_T_s[:, 1, 0], b_T_s[:, 0, 0])) < 0.5 * math.pi)
        b_T_s[fix] = b_T_s[fix] @ geo.xytheta_to_matrix(0.0, 0.0, math.pi)
    return b_T_s


def _to_frames(
    lasers: list[_Laser], linenos: list[int], *, first_index: int, name: str, flaser_max_range: float | None,
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


class _FloatCache(dict):
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


def _flaser_block(
    rows: list[list[bytes]], linenos: list[int], *, path: str, name: str, first_index: int, max_range: float,
    cache: _FloatCache,
) -> tuple[list[Frame], "_LineError | None"]:
    """Frames of a block's FLASER/RLASER lines (the hot path), and the error of the first bad line.

    When every line of the block has the same beam count, all numbers of the block are converted
    by one ``np.array`` call and checked, projected and masked as ``(m, n)`` arrays; otherwise,
    or when something is wrong, the lines go through :func:`_parse_numbers` one by one, which
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
                vals = np.concatenate([R, _c_array(other).reshape(m, 8)], axis=1)
            except _NUMERIC_ERRORS:
                vals = None
    if vals is None:  # irregular or malformed block: line by line
        lasers: list[_Laser] = []
        for r, ln in zip(rows, linenos):
            try:
                lasers.append(_parse_numbers(r, path, ln))
            except LogFormatError as exc:
                good = _to_frames(lasers, linenos[:len(lasers)], first_index=first_index, name=name,
                                  flaser_max_range=max_range, override=None)
                return good, _LineError(exc, ln)
        return _to_frames(lasers, linenos, first_index=first_index, name=name, flaser_max_range=max_range,
                          override=None), None
    R = vals[:, :n]
    rmin = R.min(axis=1)
    ok = (rmin >= 0.0) & np.isfinite(vals[:, n:]).all(axis=1)  # rmin ≥ 0 is False for NaN
    error = None
    if not ok.all():
        bad = int(np.argmin(ok))
        try:
            _parse_numbers(rows[bad], path, linenos[bad])
        except LogFormatError as exc:
            error = _LineError(exc, linenos[bad])
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
    angles, cos, sin = _beam_angles(-0.5 * math.pi, math.pi / (n - 1) if n > 1 else 0.0, n)
    NR = R >= max_range
    XY = np.stack((R * cos, R * sin), axis=-1)
    Rout = np.where(NR, np.inf, R)
    stamps = vals[:, n + 6]
    frames: list[Frame] = []
    for k in range(m):
        if rmin[k] <= 0.0:  # zero readings to drop: the general path
            las = _Laser(tag, float(stamps[k]), (angles, cos, sin), R[k], P[k, :3], P[k, 3:], None,
                         float(rmin[k]), float(R[k].max()))
            frames += _to_frames([las], [linenos[k]], first_index=first_index + k, name=name,
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
        raise _fail(path, lineno, f"expected a laser message (one of {', '.join(LASER_TAGS)}), got "
                                  f"{_short(tokens[0]) if tokens else 'an empty line'}")
    las = _parse_numbers(tokens, path, lineno)
    return _to_frames([las], [lineno], first_index=index, name=Path(path).name, flaser_max_range=None,
                      override=max_range)[0]


# ----------------------------------------------------------------------------- streaming

def _open_stream(path: Path) -> tuple[IO[bytes], str]:
    """Open *path* for binary reading, decompressing by magic number (not by suffix)."""
    try:
        with open(path, "rb") as fh:
            magic = fh.read(3)
        if magic == b"BZh":
            return bz2.open(path, "rb"), "bz2"
        if magic[:2] == b"\x1f\x8b":
            return gzip.open(path, "rb"), "gzip"
        return open(path, "rb"), "plain"
    except OSError as exc:
        raise LogFormatError(path, None, f"cannot open: {exc.strerror or exc}") from None


def _line_blocks(path: Path, limit_bytes: int | None = None) -> Iterator[tuple[int, list[bytes]]]:
    """Yield ``(number_of_first_line, lines)`` per ~1 MiB block (1-based, bytes without newline).

    Lines are split in bulk per decompressed block; a truncated or corrupt compressed stream
    raises LogFormatError naming the line reached.
    """
    fh, kind = _open_stream(path)
    lineno = 0  # lines handed out so far
    rest = b""
    total = 0
    blocks = _prefetch(fh) if kind != "plain" and limit_bytes is None else _plain_blocks(fh)
    try:
        for block in blocks:
            if isinstance(block, BaseException):
                exc = block
                if not isinstance(exc, (EOFError, OSError, zlib.error, ValueError)):
                    raise exc
                what = "truncated" if isinstance(exc, EOFError) else "corrupt"
                raise LogFormatError(path, f"line {lineno + 1}",
                                     f"{what} {kind} stream after {total} decompressed bytes ({exc})") from None
            total += len(block)
            parts = (rest + block).split(b"\n")
            rest = parts.pop()
            if parts:
                yield lineno + 1, parts
                lineno += len(parts)
            if limit_bytes is not None and total >= limit_bytes:
                return
    finally:
        blocks.close()
        fh.close()
    if rest:
        yield lineno + 1, [rest]


def _plain_blocks(fh: IO[bytes]) -> Iterator[bytes | BaseException]:
    """Blocks of about 1 MiB of *fh* read in this thread; a read error is yielded (not raised) as
    the last item, after the bytes read before it.

    The block is gathered from ``read1`` calls (one decompressor step each, for bz2/gzip), so a
    truncated or corrupt compressed stream loses only the step that failed, not the whole block.
    """
    read = getattr(fh, "read1", fh.read)
    parts: list[bytes] = []
    size = 0
    while True:
        try:
            chunk = read(_BLOCK - size)
        except Exception as exc:  # noqa: BLE001 - handed to the caller, which classifies it
            if parts:
                yield b"".join(parts)
            yield exc
            return
        if chunk:
            parts.append(chunk)
            size += len(chunk)
        if size >= _BLOCK or (not chunk and parts):
            yield parts[0] if len(parts) == 1 else b"".join(parts)
            parts, size = [], 0
        if not chunk:
            return


def _prefetch(fh: IO[bytes], depth: int = 3) -> Iterator[bytes | BaseException]:
    """Blocks of *fh* decompressed by a background thread (bz2/zlib release the GIL).

    Decompression of the next blocks overlaps with parsing of the current one; at most *depth*
    blocks wait in the queue, so memory stays constant. Closing the generator stops the thread.
    """
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def work() -> None:
        for item in _plain_blocks(fh):
            while not stop.is_set():
                try:
                    q.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if stop.is_set():
                return
        while not stop.is_set():
            try:
                q.put(None, timeout=0.1)
                return
            except queue.Full:
                continue

    th = threading.Thread(target=work, name="carmen-decompress", daemon=True)
    th.start()
    try:
        while True:
            item = q.get()
            if item is None:
                return
            yield item
            if isinstance(item, BaseException):
                return
    finally:
        stop.set()
        th.join()


def _lines(path: Path, limit_bytes: int | None = None) -> Iterator[tuple[int, bytes]]:
    """Yield ``(line_number, line)`` one by one (see :func:`_line_blocks`)."""
    for first, lines in _line_blocks(path, limit_bytes):
        yield from zip(range(first, first + len(lines)), lines)


def detect_saturation(ranges: np.ndarray, min_fraction: float = 0.002, floor: float = 20.0) -> float | None:
    """The max-range code of a laser (m) if the readings saturate at one value, else None.

    Heuristic: the largest reading counts as a saturation code when at least *min_fraction* of
    all beams lie within 0.1 m below it and it is beyond *floor* metres (SICK lasers logged through
    CARMEN report about 81.8–81.9 m). The returned threshold is 0.1 m below that value.
    """
    r = np.asarray(ranges, dtype=float)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return None
    m = float(r.max())
    if m < floor:
        return None
    thr = m - 0.1
    return thr if np.count_nonzero(r >= thr) >= min_fraction * r.size else None


class _LineError(Exception):
    """A LogFormatError with the line number it refers to (to order errors within a block)."""

    def __init__(self, error: LogFormatError, lineno: int) -> None:
        super().__init__(str(error))
        self.error = error
        self.lineno = lineno


def _check_odom(tokens: list[bytes], linenos: list[int], path: str) -> _LineError | None:
    """Validate the numbers of a block's ODOM lines in one vectorised conversion: 8 per line, the 7 of
    ``x y theta tv rv accel ipc_timestamp`` and the ``logger_timestamp``, all finite.

    Their stamps are not required to increase: the gmapping-corrected logs of the development set
    write uninitialised ODOM stamps (0, 4.6e-72, …) between proper ones, and the reader takes the
    odometry from the laser lines anyway."""
    try:
        ok = bool(np.isfinite(_c_array(tokens)).all())
    except _NUMERIC_ERRORS:
        ok = False
    if ok:
        return None
    for k, lineno in enumerate(linenos):
        try:
            v = _floats(tokens[8 * k:8 * k + 7], path, lineno, "ODOM", 2)
            if not np.isfinite(v).all():
                raise _fail(path, lineno, "ODOM values must be finite")
            _stamp(tokens[8 * k:8 * k + 8], -1, "ODOM logger_timestamp (last field)", path, lineno)
        except LogFormatError as exc:
            return _LineError(exc, lineno)
    return None


class _BlockParser:
    """Frames of a run of consecutive lines, stopping at the first bad line (see ``CarmenReader._stream``)."""

    def __init__(self, path: str, name: str, want: bytes, fast: bool, fl_max: float, override: float | None) -> None:
        self.path, self.name, self.want, self.fast = path, name, want, fast
        self.fl_max, self.override = fl_max, override
        self.cache = _FloatCache()

    def __call__(self, first: int, lines: list[bytes], index: int) -> tuple[list[Frame], _LineError | None, Counter]:
        """``(frames, error, tag_counts)`` of *lines* (the first is line *first*; frames numbered from
        *index*): the frames and message-tag counts of the lines before the first bad one, and its error."""
        path, want, fast = self.path, self.want, self.fast
        counts: Counter = Counter()
        lasers: list[_Laser] = []
        rows: list[list[bytes]] = []
        linenos: list[int] = []
        odom_tokens: list[bytes] = []
        odom_lines: list[int] = []
        error: _LineError | None = None
        lineno = first
        try:
            for lineno, ln in zip(range(first, first + len(lines)), lines):
                tokens = ln.split()
                if not tokens:
                    continue
                t0 = tokens[0]
                if t0 == want:
                    if fast:
                        rows.append(tokens)
                    else:
                        lasers.append(_parse_numbers(tokens, path, lineno))
                    linenos.append(lineno)
                    continue
                if t0[:1] == b"#":
                    continue
                if t0 != b"ODOM" and not _TAG_RE.match(t0):
                    raise _fail(path, lineno, f"garbage line: expected a CARMEN message tag, got {_short(t0)}")
                if t0 == b"ODOM":
                    if len(tokens) != 10:
                        raise _fail(path, lineno, "ODOM needs 10 fields (x y theta tv rv accel ipc_timestamp "
                                                  f"host logger_timestamp), got {len(tokens)}")
                    odom_tokens += tokens[1:8]
                    odom_tokens.append(tokens[9])
                    odom_lines.append(lineno)
                counts[t0.decode("ascii")] += 1
        except LogFormatError as exc:
            error = _LineError(exc, lineno)  # hand out the good scans before it first
        loop_error = error
        if odom_lines:
            bad_odom = _check_odom(odom_tokens, odom_lines, path)
            if bad_odom is not None and (error is None or bad_odom.lineno < error.lineno):
                error = bad_odom
        if error is not None:  # only the scans before the first bad line
            keep = sum(1 for ln in linenos if ln < error.lineno)
            lasers, rows, linenos = lasers[:keep], rows[:keep], linenos[:keep]
        if fast:
            frames, laser_error = _flaser_block(rows, linenos, path=path, name=self.name, first_index=index,
                                                max_range=self.fl_max, cache=self.cache)
            if laser_error is not None:
                error = laser_error
        else:
            frames = _to_frames(lasers, linenos, first_index=index, name=self.name, flaser_max_range=self.fl_max,
                                override=self.override)
        if error is not None and error is not loop_error:  # tags were counted past the bad line: count again
            counts = Counter(_tags(lines[: error.lineno - first], want))
        return frames, error, counts


def _line_tag(line: bytes) -> str:
    """The message tag of a line (:data:`~slam.logs.base.UNKNOWN` for a garbled one: it may have been a scan)."""
    tok = line.split(None, 1)
    return tok[0].decode("ascii") if tok and _TAG_RE.match(tok[0]) else UNKNOWN


def _tags(lines: list[bytes], want: bytes) -> Iterator[str]:
    """The message tags of good *lines*, as the parser counts them (not the sensor tag, not comments)."""
    for ln in lines:
        tok = ln.split(None, 1)
        if tok and tok[0] != want and tok[0][:1] != b"#":
            yield tok[0].decode("ascii")


class CarmenReader(LogReader):
    """Streaming reader of one laser stream of a CARMEN log.

    Args:
        path: ``.clf``/``.log`` file, optionally bz2/gzip compressed.
        topic: ``FLASER`` (front, default when present), ``RLASER`` (rear), ``ROBOTLASER1`` or
            ``ROBOTLASER2`` (also ``front``/``rear``); None picks the first of ``FLASER``,
            ``ROBOTLASER1``, ``RLASER``, ``ROBOTLASER2`` found in the log.
        max_range: no-return threshold in metres for FLASER/RLASER (and, when given, for
            ROBOTLASER*). None = the log's saturation code when detected in its first scans,
            else 80 m for FLASER/RLASER, the line's own ``max_range`` for ROBOTLASER*.

    Raises:
        TopicNotFoundError: *topic* is not a CARMEN laser message.
    """

    format = "carmen"

    def __init__(self, path: str | Path, topic: str | None = None, max_range: float | None = None) -> None:
        super().__init__(path, topic)
        if topic is not None:
            canon = _TOPIC_ALIASES.get(topic.strip().upper())
            if canon is None:
                raise TopicNotFoundError(self.path, None, f"unknown CARMEN topic {topic!r} "
                                                          f"(expected one of {', '.join(LASER_TAGS)}, front, rear)")
            self.topic = canon
        if max_range is not None and not (max_range > 0):
            raise LogFormatError(self.path, None, f"max_range must be positive, got {max_range}")
        self._user_max_range = max_range
        self._probed: tuple[str, float | None] | None = None

    # -- probing the head of the log: default topic and the FLASER saturation value
    def _probe(self) -> tuple[str, float | None]:
        if self._probed is not None:
            return self._probed
        tags: set[str] = set()
        sample: list[np.ndarray] = []
        want = self.topic
        try:
            for lineno, ln in _lines(self.path, _PROBE_BYTES):
                tok = ln.split(None, 1)
                if not tok:
                    continue
                t = tok[0]
                if t in (b"FLASER", b"RLASER", b"ROBOTLASER1", b"ROBOTLASER2"):
                    tags.add(t.decode())
                    if t in (b"FLASER", b"RLASER") and len(sample) < _PROBE_SCANS and (want is None or want == t.decode()):
                        try:
                            sample.append(_parse_numbers(ln.split(), str(self.path), lineno).ranges)
                        except LogFormatError:
                            pass  # reported with its line by the real pass
        except LogFormatError:
            pass  # a broken stream is reported by the real pass, with the line it reached
        if want is None:
            if not tags:  # nothing in the head: look through the whole log once
                try:
                    for _, ln in _lines(self.path):
                        t = ln.split(None, 1)[:1]
                        if t and t[0] in (b"FLASER", b"RLASER", b"ROBOTLASER1", b"ROBOTLASER2"):
                            tags.add(t[0].decode())
                            break
                except LogFormatError:
                    pass
            want = next((t for t in LASER_TAGS if t in tags), "FLASER")
        sat = detect_saturation(np.concatenate(sample)) if sample else None
        self._probed = (want, sat)
        return self._probed

    @property
    def sensor_topic(self) -> str:
        """The laser message tag whose lines become frames."""
        return self._probe()[0]

    def flaser_max_range(self) -> float:
        """No-return threshold (m) used for FLASER/RLASER lines of this log."""
        if self._user_max_range is not None:
            return float(self._user_max_range)
        sat = self._probe()[1]
        return sat if sat is not None else DEFAULT_FLASER_MAX_RANGE

    def _stream(self, tag_counts: Counter, odom_fields: list[bool] | None = None,
                on_skip: SkipHandler | None = None) -> Iterator[Frame]:
        """Parse the log block by block; count every message tag into *tag_counts*.

        With *on_skip*, a bad line is reported and parsing resumes on the next line; a corrupt or
        truncated compressed stream is reported and ends the frames (what was read is kept).
        """
        topic = self.sensor_topic
        path = str(self.path)
        # FLASER/RLASER take the block-vectorised path; ROBOTLASER* lines are parsed one by one
        # (a user max range applies to both kinds, see flaser_max_range()).
        parse = _BlockParser(path, self.path.name, topic.encode(), topic in ("FLASER", "RLASER"),
                             self.flaser_max_range(), self._user_max_range)
        index = 0
        last = 0
        n_topic = 0
        if on_skip is not None:
            on_skip = counting(on_skip, topic)
        blocks = _line_blocks(self.path)
        try:
            while True:
                try:
                    first, lines = next(blocks)
                except StopIteration:
                    break
                except LogFormatError as exc:  # corrupt / truncated compressed stream: nothing after it
                    if on_skip is None:
                        raise
                    on_skip(lost(exc, None))  # how many lines it cut off is not known
                    break
                while lines:
                    frames, error, counts = parse(first, lines, index)
                    last = first + len(lines) - 1 if error is None else error.lineno
                    tag_counts.update(counts)
                    n_topic += len(frames)
                    if odom_fields is not None and frames and not odom_fields[0]:
                        odom_fields[0] = any((f.odom[:2, 3] != 0.0).any() or f.odom[1, 0] != 0.0 for f in frames)
                    index += len(frames)
                    yield from frames
                    if error is None:
                        break
                    if on_skip is None:
                        raise error.error
                    on_skip(lost(error.error, {_line_tag(lines[error.lineno - first]): 1}))  # resume after it
                    lines = lines[error.lineno + 1 - first:]
                    first = error.lineno + 1
        finally:
            blocks.close()
        tag_counts[topic] += n_topic
        if n_topic == 0:
            del tag_counts[topic]
            lasers_seen = [f"{t} ×{tag_counts[t]}" for t in LASER_TAGS if tag_counts.get(t)]
            if lasers_seen:
                raise TopicNotFoundError(self.path, None, f"no {topic} scans; the log has {', '.join(lasers_seen)} (use --topic)")
            others = f" (messages: {', '.join(f'{k} ×{v}' for k, v in sorted(tag_counts.items()))})" if tag_counts else ""
            where = f"line {last}" if last else None
            raise LogFormatError(self.path, where, f"no scans: the log has no {topic} messages{others}")

    def frames(self, on_skip: SkipHandler | None = None) -> Iterator[Frame]:
        """Yield every scan of the chosen laser as a Frame, in file order (streaming).

        With *on_skip* a malformed line is reported and skipped, and a corrupt or truncated
        compressed stream is reported and ends the frames (see :meth:`LogReader.frames`).
        """
        counts: Counter = Counter()
        yield from self._stream(counts, on_skip=on_skip)

    def info(self) -> LogInfo:
        """Stream the log once, validating every scan line, and summarise it."""
        counts: Counter = Counter()
        odom_fields = [False]
        scans = 0
        beams = 0
        start = end = None
        for fr in self._stream(counts, odom_fields):
            scans += 1
            beams = max(beams, int(fr.ranges.shape[0]))
            # min/max, not first/last: ipc_timestamps may step back (hundreds of times in one benchmark log)
            if start is None or fr.stamp < start:
                start = fr.stamp
            if end is None or fr.stamp > end:
                end = fr.stamp
        topic = self.sensor_topic
        topics = [TopicInfo(name=k, msgtype=k, count=v) for k, v in counts.items()]
        return LogInfo(
            path=str(self.path), format=self.format, sensor_topic=topic, scans=scans,
            beams_per_scan=beams, dimension=2, start=start, end=end,
            has_odometry=bool(counts.get("ODOM", 0)) or odom_fields[0],
            has_ground_truth=False, topics=topics,
        )
