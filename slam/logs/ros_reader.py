"""The streaming frame assembly the MCAP (ROS 2) and ROS 1 bag readers share: topic roles, then every scan as a
:class:`~core.frame.Frame` with odometry and ground truth interpolated to its stamp and its mount from TF."""

from __future__ import annotations

import abc
import contextlib
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from core.errors import LogFormatError
from core.frame import Frame

from .base import LogInfo, LogReader, SkipHandler, TopicInfo, counting, lost
from .pointcloud2 import cloud_to_frame, pointcloud2_structured
from .ros_msgs import LASER_SCAN, ODOMETRY, RawMessage, check_scan, header_stamp, pose_msg_vec, scan_to_frame, strip_frame
from .ros_topics import TopicChoice, choose_topics
from .tf_buffer import PoseTrack, TfBuffer, base_candidates, base_T_sensor, tf_odometry

Array = NDArray[np.float64]


class RosLogReader(LogReader):
    """Streaming frame assembly for ROS logs (MCAP / ROS 1 bag); subclasses provide the messages.

    Memory is constant in the log length: the reader holds the scans still waiting for an
    odometry / ground-truth sample at or after their stamp (at most ``max_pending``), the pose
    samples bracketing them, and the last ``history`` samples of each dynamic TF edge.

    Args:
        path: the log file.
        topic: the sensor topic; default: the LaserScan topic with most messages, else the
            PointCloud2 topic with most messages.
        odom_topic: a ``nav_msgs/Odometry`` topic; default ``/odom`` or the Odometry topic with
            most messages (ground-truth-named topics excluded) and, when the log has none, the
            TF edge ``odom → base`` (REP-105). ``""`` disables odometry.
        ground_truth_topic: an Odometry or PoseStamped topic; default a topic named
            ``ground_truth`` / ``groundtruth`` / ``gt`` / ``base_pose_ground_truth``.
        max_gap: odometry/ground truth is held (not extrapolated) up to this many seconds
            beyond its first/last sample; farther out the frame gets None.
    """

    max_pending = 256
    trim_margin = 1.0  # s of pose samples kept before the oldest waiting scan

    def __init__(
        self,
        path: str | Path,
        topic: str | None = None,
        *,
        odom_topic: str | None = None,
        ground_truth_topic: str | None = None,
        max_gap: float = 0.5,
    ) -> None:
        super().__init__(path, topic)
        self.odom_topic = odom_topic
        self.ground_truth_topic = ground_truth_topic
        self.max_gap = max_gap

    # -- provided by the format -------------------------------------------------------------

    @abc.abstractmethod
    def topics(self) -> list[TopicInfo]:
        """Every topic of the log with its (normalised) message type and message count."""

    @abc.abstractmethod
    def _raw_messages(self, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[RawMessage]:
        """Messages of *topics* (all when None) in time order, undecoded; raises LogFormatError
        on a corrupt or truncated container, or, with *on_skip*, reports it and goes on after it
        where the container allows (else ends the messages)."""

    @abc.abstractmethod
    def _decode(self, raw: RawMessage) -> Any:
        """Deserialise one message (raises LogFormatError naming the message)."""

    def _session(self) -> contextlib.AbstractContextManager:
        """Resources kept open across the several passes of one frames()/info() call."""
        return contextlib.nullcontext()

    def _load_meta(self, tolerant: bool = False) -> None:
        """Read topics and message definitions (*tolerant*: as far as a damaged file allows)."""

    # -- topic roles ------------------------------------------------------------------------

    def choose_topics(self) -> TopicChoice:
        """Assign the sensor, odometry, ground-truth and TF roles (raises TopicNotFoundError)."""
        return choose_topics(self.path, self.topics(), self.topic, self.odom_topic, self.ground_truth_topic)

    # -- frames -----------------------------------------------------------------------------

    @contextlib.contextmanager
    def _fields(self, raw: RawMessage) -> Iterator[None]:
        """Read fields of *raw*'s decoded message inside the block: one its type lacks — the log carries its
        own message definitions, and a damaged or unusual one decodes into other fields — is a
        LogFormatError naming the message, as a bad value is."""
        try:
            yield
        except (AttributeError, TypeError) as exc:
            raise LogFormatError(self.path, raw.where, f"{raw.msgtype} on {raw.topic} lacks a standard field of "
                                                       f"its type (its definition in the log differs): {exc}") from None

    def _to_frame(self, raw: RawMessage, msg: Any, scan_index: int, **extra: Any) -> Frame:
        with self._fields(raw):
            if raw.msgtype == LASER_SCAN:
                return scan_to_frame(msg, self.path, raw.where, scan_index, **extra)
            return cloud_to_frame(msg, self.path, raw.where, scan_index, **extra)

    def _scan_head(self, raw: RawMessage, msg: Any) -> tuple[float, str]:
        """The stamp (s) and sensor frame of a sensor message, a LaserScan checked first."""
        with self._fields(raw):
            if raw.msgtype == LASER_SCAN:
                check_scan(msg, self.path, raw.where)  # fail at the bad message, not a batch later
            return header_stamp(msg), strip_frame(msg.header.frame_id)

    def _pose_sample(self, raw: RawMessage, msg: Any) -> tuple[float, Array]:
        with self._fields(raw):
            try:
                vec = pose_msg_vec(msg.pose.pose if raw.msgtype == ODOMETRY else msg.pose)
            except ValueError as exc:
                raise LogFormatError(self.path, raw.where, f"{raw.topic}: {exc}") from None
            return header_stamp(msg), vec

    def _add_tf(self, tf: TfBuffer, raw: RawMessage, static: bool) -> None:
        msg = self._decode(raw)
        with self._fields(raw):
            try:
                tf.add_message(msg, static=static)
            except ValueError as exc:
                raise LogFormatError(self.path, raw.where, f"{raw.topic}: {exc}") from None

    def _first(self, topic: str, skip: SkipHandler | None = None, read: Any = None) -> Any | None:
        """``read(message)`` of the first message of *topic* (the message itself without *read*; None when
        the topic is empty); with *skip*, of the first one that decodes and reads (the bad ones go to *skip*)."""
        it = self._raw_messages({topic}, skip)
        try:
            for raw in it:
                try:
                    msg = self._decode(raw)
                    with self._fields(raw):
                        return msg if read is None else read(msg)
                except LogFormatError as exc:
                    if skip is None:
                        raise
                    skip(exc)
            return None
        finally:
            it.close()  # type: ignore[attr-defined]

    def _tf_odometry_child(self, tf_topics: Sequence[str], probe: int = 200, skip: SkipHandler | None = None) -> str | None:
        """The child of a dynamic ``odom → base`` transform among the first *probe* /tf messages
        (REP-105: the odometry frame is ``odom``), or None. With *skip*, undecodable messages go to it."""
        for name in tf_topics:
            it = self._raw_messages({name}, skip)
            try:
                for k, raw in enumerate(it):
                    if k >= probe:
                        break
                    try:
                        msg = self._decode(raw)
                        with self._fields(raw):
                            child = next((strip_frame(ts.child_frame_id) for ts in msg.transforms
                                          if strip_frame(ts.header.frame_id) == "odom"), None)
                    except LogFormatError as exc:
                        if skip is None:
                            raise
                        skip(exc)
                        continue
                    if child is not None:
                        return child
            finally:
                it.close()  # type: ignore[attr-defined]
        return None

    def scan_count_hint(self) -> int | None:
        """The sensor topic's message count from the container's index (summary / connections)."""
        try:
            return self.choose_topics().sensor.count or None
        except LogFormatError:
            return None

    def has_ground_truth(self) -> bool:
        """Whether a ground-truth topic (named or given) is in the log."""
        return self.choose_topics().ground_truth is not None

    def frames(self, on_skip: SkipHandler | None = None) -> Iterator[Frame]:
        """Every scan of the sensor topic as a Frame (in log order), with ``odom`` /
        ``ground_truth`` interpolated to the scan stamp and ``base_T_sensor`` from TF.

        With *on_skip*, a message that does not decode (or a scan that is malformed) is reported
        and left out; a corrupt container stretch is reported and skipped where the format
        allows (see the readers). The preparatory passes (static TF, first messages) skip bad
        messages silently: the main pass, which reads them again, reports each once.
        """
        quiet: SkipHandler | None = None if on_skip is None else (lambda exc: None)
        with self._session():
            self._load_meta(tolerant=on_skip is not None)
            choice = self.choose_topics()
            if on_skip is not None:
                on_skip = counting(on_skip, choice.sensor.name)
            sources = self._sources(choice, quiet)
            assembly = _Assembly(self, choice, sources, on_skip)
            for raw in self._raw_messages(sources.wanted, on_skip):
                assembly.guarded(assembly.take, raw)
                yield from assembly.after_message()
            yield from assembly.drain()

    def _sources(self, choice: TopicChoice, quiet: SkipHandler | None) -> _Sources:
        """The preparatory passes of :meth:`frames`: the static TF tree, the odometry's child frame, whether the
        dynamic /tf is needed (the static tree may already mount the sensor on the base), odometry from the TF
        edge odom → base when the log has no Odometry topic, and the topics the main pass reads."""
        tf = TfBuffer()
        for name in choice.tf_static:
            for raw in self._raw_messages({name}, quiet):
                try:
                    self._add_tf(tf, raw, static=True)
                except LogFormatError:
                    if quiet is None:
                        raise
        odom_child: str | None = None
        if choice.odom is not None:
            odom_child = self._first(choice.odom.name, quiet, lambda m: strip_frame(m.child_frame_id))
        need_tf = bool(choice.tf)
        sensor0 = self._first(choice.sensor.name, quiet, lambda m: strip_frame(m.header.frame_id))
        if need_tf and sensor0 is not None:
            need_tf = not any(
                b == sensor0 or (b in tf and sensor0 in tf and tf.lookup(b, sensor0, 0.0) is not None)
                for b in base_candidates(odom_child)
            )
        tf_odom: str | None = None
        if choice.odom is None and self.odom_topic is None and choice.tf:
            tf_odom = self._tf_odometry_child(choice.tf, skip=quiet)
            if tf_odom is not None:
                odom_child, need_tf = tf_odom, True
        wanted = {choice.sensor.name, *choice.tf_static}
        if need_tf:
            wanted.update(choice.tf)
        for c in (choice.odom, choice.ground_truth):
            if c is not None:
                wanted.add(c.name)
        return _Sources(tf, odom_child, tf_odom, wanted)

    # -- info -------------------------------------------------------------------------------

    def info(self) -> LogInfo:
        """Summary of the log, read whole: topic counts from the index (summary / connections); every
        message read from the container, and those of the topics a run uses (sensor, odometry, ground
        truth, TF) decoded and checked as a run checks them, so a log it summarises without an error is
        one a run reads; scans, beams and start/end from the sensor topic."""
        choice = self.choose_topics()
        poses = {c.name for c in (choice.odom, choice.ground_truth) if c is not None}
        scratch = TfBuffer()
        scans = 0
        beams: list[int] = []
        start = end = None
        for raw in self._raw_messages(None):
            if raw.topic != choice.sensor.name:
                if raw.topic in poses:
                    self._pose_sample(raw, self._decode(raw))
                elif raw.topic in choice.tf or raw.topic in choice.tf_static:
                    self._add_tf(scratch, raw, static=raw.topic in choice.tf_static)
                continue
            msg = self._decode(raw)
            t, _ = self._scan_head(raw, msg)
            with self._fields(raw):
                if raw.msgtype == LASER_SCAN:
                    beams.append(len(msg.ranges))
                else:
                    try:
                        view = pointcloud2_structured(msg, ("x", "y", "z"))
                    except ValueError as exc:
                        raise LogFormatError(self.path, raw.where, f"bad PointCloud2: {exc}") from None
                    beams.append(int(view.size))
            start = t if start is None else min(start, t)
            end = t if end is None else max(end, t)
            scans += 1
        dim = 2 if choice.sensor.msgtype == LASER_SCAN else 3
        bps = None
        if beams:
            bps = int(max(beams)) if dim == 2 else int(np.median(beams))
        return LogInfo(
            path=str(self.path),
            format=self.format,
            sensor_topic=choice.sensor.name,
            scans=scans,
            beams_per_scan=bps,
            dimension=dim,
            start=start,
            end=end,
            has_odometry=choice.odom is not None
            or (self.odom_topic is None and bool(choice.tf) and self._tf_odometry_child(choice.tf) is not None),
            has_ground_truth=choice.ground_truth is not None,
            topics=self.topics(),
        )


@dataclass
class _Sources:
    """What :meth:`RosLogReader._sources` found before the main pass."""

    tf: TfBuffer  # the static tree so far; the main pass adds the dynamic edges
    odom_child: str | None  # the base frame odometry moves (the Odometry child, or the TF odom → base child)
    tf_odom: str | None  # odometry from that TF edge (no Odometry topic), else None
    wanted: set[str]  # the topics the main pass reads


class _Assembly:
    """The main pass of :meth:`RosLogReader.frames`: each scan waits (in *pending*) until odometry and ground
    truth have a sample at or after its stamp, or too many scans wait; then it goes into a batch whose
    poses are interpolated in one call, and comes out as a Frame. Pose history older than the oldest
    waiting scan (less a margin) is dropped, so memory stays constant in the log length."""

    def __init__(self, reader: RosLogReader, choice: TopicChoice, sources: _Sources, on_skip: SkipHandler | None) -> None:
        self.reader, self.choice, self.on_skip = reader, choice, on_skip
        self.tf, self.odom_child, self.tf_odom = sources.tf, sources.odom_child, sources.tf_odom
        self.odom = PoseTrack(reader.max_gap) if choice.odom else None
        self.gt = PoseTrack(reader.max_gap) if choice.ground_truth else None
        laser = choice.sensor.msgtype == LASER_SCAN
        self.batch_size = 64 if laser else 1
        self.max_pending = reader.max_pending if laser else 16
        self.pending: deque[tuple[RawMessage, Any, int, float, str]] = deque()
        self.batch: list[tuple[RawMessage, Any, int, float, str]] = []
        self.scan_index = 0

    def guarded(self, fn: Any, raw: RawMessage, *args: Any, **kwargs: Any) -> Any:
        """``fn(raw, *args, **kwargs)``; with *on_skip*, a LogFormatError is reported (costing that one message)
        and None returned."""
        try:
            return fn(raw, *args, **kwargs)
        except LogFormatError as exc:
            if self.on_skip is None:
                raise
            self.on_skip(lost(exc, {raw.topic: 1}))
            return None

    def take(self, raw: RawMessage) -> None:
        """Decode one message and file it (a scan into *pending*, a pose into its track, a transform into TF)."""
        r, c, topic = self.reader, self.choice, raw.topic
        if topic == c.sensor.name:
            msg = r._decode(raw)
            self.pending.append((raw, msg, self.scan_index, *r._scan_head(raw, msg)))
            self.scan_index += 1
        elif c.odom is not None and topic == c.odom.name:
            assert self.odom is not None
            self.odom.add(*r._pose_sample(raw, r._decode(raw)))
        elif c.ground_truth is not None and topic == c.ground_truth.name:
            assert self.gt is not None
            self.gt.add(*r._pose_sample(raw, r._decode(raw)))
        elif topic in c.tf_static:
            r._add_tf(self.tf, raw, static=True)
        elif topic in c.tf:
            r._add_tf(self.tf, raw, static=False)

    def _ready(self, t: float) -> bool:
        return ((self.odom is None or self.odom.latest >= t) and (self.gt is None or self.gt.latest >= t)
                and (self.tf_odom is None or self.tf.latest_dynamic >= t))

    def after_message(self) -> Iterator[Frame]:
        """The frames a message made ready, then the pose history no waiting scan needs dropped."""
        pending, batch = self.pending, self.batch
        while pending and (self._ready(pending[0][3]) or len(pending) > self.max_pending):
            batch.append(pending.popleft())
        if len(batch) >= self.batch_size:
            yield from self._flush()
        # Keep trim_margin seconds of pose history before the oldest waiting scan (or the newest sample):
        # scans may be logged after odometry with later stamps.
        oldest = batch[0][3] if batch else (pending[0][3] if pending else math.inf)
        for track in (self.odom, self.gt):
            if track is not None and track.stamps:
                track.trim(min(oldest, track.latest) - self.reader.trim_margin)

    def drain(self) -> Iterator[Frame]:
        """After the last message: every scan still waiting."""
        self.batch.extend(self.pending)
        self.pending.clear()
        if self.batch:
            yield from self._flush()

    def _flush(self) -> Iterator[Frame]:
        r, batch = self.reader, self.batch
        stamps = [b[3] for b in batch]
        od = self.odom.query_many(stamps) if self.odom is not None else [None] * len(batch)
        gp = self.gt.query_many(stamps) if self.gt is not None else [None] * len(batch)
        if self.tf_odom is not None:
            od = tf_odometry(self.tf, self.tf_odom, stamps, r.max_gap)
        for (raw, msg, k, t, sframe), o, g in zip(batch, od, gp):
            extra: dict[str, Any] = {"base_T_sensor": base_T_sensor(self.tf, self.odom_child, sframe, t)}
            if self.odom is not None or self.tf_odom is not None:
                extra["odom"] = o
            if self.gt is not None:
                extra["ground_truth"] = g
            frame = self.guarded(r._to_frame, raw, msg, k, **extra)
            if frame is not None:
                yield frame
        batch.clear()
