"""CARMEN robot logs (``.clf`` / ``.log``, plain, ``.bz2`` or ``.gz``) as a stream of laser Frames.

Format: one message per line, ``TAG field … ipc_timestamp ipc_hostname logger_timestamp``
(CARMEN logger; the layouts below are the ones of the Kümmerle et al. 2009 benchmark logs):

* ``FLASER n r_1 … r_n x y theta odom_x odom_y odom_theta ipc_ts host logger_ts`` (front laser);
  ``RLASER`` has the same layout for the rear laser. The line carries no beam angles: the n beams are
  the SICK LMS's at the step of the mode their count names (1° for 180/181 beams, 0.5° for 360/361, as
  CARMEN's own reader has them), the first at −90° (:func:`~slam.logs.carmen_lines.flaser_layout`).
  ``x y theta`` is the laser pose and ``odom_*`` the robot pose, both in the odometry frame.
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
by line, which also yields the precise error message. The lines are parsed in :mod:`slam.logs.carmen_lines`,
the file is streamed by :mod:`slam.logs.text_stream`; here the reader: the laser stream chosen, blocks of
lines turned into frames, bad lines stopped at (or skipped with ``on_skip``), the saturation code probed.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path
from typing import Iterator

import numpy as np

from core.errors import LogFormatError, TopicNotFoundError
from core.frame import Frame

from .base import UNKNOWN, LogInfo, LogReader, SkipHandler, TopicInfo, counting, lost
from .carmen_lines import (DEFAULT_FLASER_MAX_RANGE, LASER_TAGS, NUMERIC_ERRORS, FloatCache, LaserLine, LineError, c_array,
                           flaser_block, format_error, lasers_to_frames, parse_floats, parse_numbers, parse_stamp,
                           short_token)
from .text_stream import line_blocks, numbered_lines

__all__ = ["CarmenReader", "detect_saturation"]

_TOPIC_ALIASES = {"FRONT": "FLASER", "REAR": "RLASER", "FLASER": "FLASER", "RLASER": "RLASER",
                  "ROBOTLASER1": "ROBOTLASER1", "ROBOTLASER2": "ROBOTLASER2"}
_TAG_RE = re.compile(rb"^[A-Z][A-Z0-9_\-]*$")
_PROBE_BYTES = 1 << 20
_PROBE_SCANS = 400


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


def _check_odom(tokens: list[bytes], linenos: list[int], path: str) -> LineError | None:
    """Validate the numbers of a block's ODOM lines in one vectorised conversion: 8 per line, the 7 of
    ``x y theta tv rv accel ipc_timestamp`` and the ``logger_timestamp``, all finite.

    Their stamps are not required to increase: the gmapping-corrected logs of the development set
    write uninitialised ODOM stamps (0, 4.6e-72, …) between proper ones, and the reader takes the
    odometry from the laser lines anyway."""
    try:
        ok = bool(np.isfinite(c_array(tokens)).all())
    except NUMERIC_ERRORS:
        ok = False
    if ok:
        return None
    for k, lineno in enumerate(linenos):
        try:
            v = parse_floats(tokens[8 * k:8 * k + 7], path, lineno, "ODOM", 2)
            if not np.isfinite(v).all():
                raise format_error(path, lineno, "ODOM values must be finite")
            parse_stamp(tokens[8 * k:8 * k + 8], -1, "ODOM logger_timestamp (last field)", path, lineno)
        except LogFormatError as exc:
            return LineError(exc, lineno)
    return None


class _BlockParser:
    """Frames of a run of consecutive lines, stopping at the first bad line (see ``CarmenReader._stream``)."""

    def __init__(self, path: str, name: str, want: bytes, fast: bool, fl_max: float, override: float | None) -> None:
        self.path, self.name, self.want, self.fast = path, name, want, fast
        self.fl_max, self.override = fl_max, override
        self.cache = FloatCache()

    def __call__(self, first: int, lines: list[bytes], index: int) -> tuple[list[Frame], LineError | None, Counter]:
        """``(frames, error, tag_counts)`` of *lines* (the first is line *first*; frames numbered from
        *index*): the frames and message-tag counts of the lines before the first bad one, and its error."""
        path, want, fast = self.path, self.want, self.fast
        counts: Counter = Counter()
        lasers: list[LaserLine] = []
        rows: list[list[bytes]] = []
        linenos: list[int] = []
        odom_tokens: list[bytes] = []
        odom_lines: list[int] = []
        error: LineError | None = None
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
                        lasers.append(parse_numbers(tokens, path, lineno))
                    linenos.append(lineno)
                    continue
                if t0[:1] == b"#":
                    continue
                if t0 != b"ODOM" and not _TAG_RE.match(t0):
                    raise format_error(path, lineno, f"garbage line: expected a CARMEN message tag, got {short_token(t0)}")
                if t0 == b"ODOM":
                    if len(tokens) != 10:
                        raise format_error(path, lineno, "ODOM needs 10 fields (x y theta tv rv accel ipc_timestamp "
                                                  f"host logger_timestamp), got {len(tokens)}")
                    odom_tokens += tokens[1:8]
                    odom_tokens.append(tokens[9])
                    odom_lines.append(lineno)
                counts[t0.decode("ascii")] += 1
        except LogFormatError as exc:
            error = LineError(exc, lineno)  # hand out the good scans before it first
        loop_error = error
        if odom_lines:
            bad_odom = _check_odom(odom_tokens, odom_lines, path)
            if bad_odom is not None and (error is None or bad_odom.lineno < error.lineno):
                error = bad_odom
        if error is not None:  # only the scans before the first bad line
            keep = sum(1 for ln in linenos if ln < error.lineno)
            lasers, rows, linenos = lasers[:keep], rows[:keep], linenos[:keep]
        if fast:
            frames, laser_error = flaser_block(rows, linenos, path=path, name=self.name, first_index=index,
                                                max_range=self.fl_max, cache=self.cache)
            if laser_error is not None:
                error = laser_error
        else:
            frames = lasers_to_frames(lasers, linenos, first_index=index, name=self.name, flaser_max_range=self.fl_max,
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
            for lineno, ln in numbered_lines(self.path, _PROBE_BYTES):
                tok = ln.split(None, 1)
                if not tok:
                    continue
                t = tok[0]
                if t in (b"FLASER", b"RLASER", b"ROBOTLASER1", b"ROBOTLASER2"):
                    tags.add(t.decode())
                    if t in (b"FLASER", b"RLASER") and len(sample) < _PROBE_SCANS and (want is None or want == t.decode()):
                        try:
                            sample.append(parse_numbers(ln.split(), str(self.path), lineno).ranges)
                        except LogFormatError:
                            pass  # reported with its line by the real pass
        except LogFormatError:
            pass  # a broken stream is reported by the real pass, with the line it reached
        if want is None:
            if not tags:  # nothing in the head: look through the whole log once
                try:
                    for _, ln in numbered_lines(self.path):
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
        blocks = line_blocks(self.path)
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
