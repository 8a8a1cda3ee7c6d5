"""ROS 1 bag (format 2.0) reader: LaserScan / PointCloud2 frames with odometry, ground truth and TF.

The container is read by ``rosbags.rosbag1.Reader``; messages are decoded with types built from
the message definitions stored in the bag's connection records, so bags with any message set
(e.g. ``tf2_msgs/TFMessage``, which the Noetic store of rosbags lacks) decode without ROS. The
conversions to :class:`~registration.frame.Frame` are shared with the MCAP reader
(:mod:`slam.logs.ros_msgs`). Stamps are the header stamps (float seconds).

Memory: rosbags keeps the bag's index (one small entry per message) in memory and one
decompressed chunk at a time; the frame assembly itself is streaming (see
:class:`~slam.logs.ros_msgs.RosLogReader`).
"""

from __future__ import annotations

import contextlib
import heapq
from pathlib import Path
from typing import Any, Iterator

from registration.errors import LogFormatError

from .base import SkipHandler, TopicInfo
from .ros_msgs import RawMessage, RosLogReader, build_typestore, normalize_msgtype

__all__ = ["Ros1BagReader"]


class Ros1BagReader(RosLogReader):
    """Stream a ROS 1 ``.bag`` file as Frames (see :class:`RosLogReader` for the arguments)."""

    format = "ros1"

    def __init__(self, path: str | Path, topic: str | None = None, **kwargs: Any) -> None:
        super().__init__(path, topic, **kwargs)
        self._topics: list[TopicInfo] | None = None
        self._store = None
        self._shared: Any = None  # an open rosbags Reader during one frames() call

    @contextlib.contextmanager
    def _session(self) -> Iterator[None]:
        """Open the bag (and parse its index) once for all passes of a frames() call."""
        if self._shared is not None:
            yield
            return
        self._shared = self._open()
        try:
            yield
        finally:
            reader, self._shared = self._shared, None
            reader.close()

    def _open(self):
        from rosbags.rosbag1 import Reader, ReaderError

        try:
            reader = Reader(self.path)
            reader.open()
        except (ReaderError, OSError, ValueError, KeyError, IndexError) as exc:
            raise LogFormatError(self.path, None, f"not a readable ROS 1 bag: {exc}") from None
        return reader

    def _load_meta(self, tolerant: bool = False) -> None:
        """Topics and message definitions from the bag's connection records (the index must be
        readable, *tolerant* or not: rosbags reads it before any message)."""
        if self._topics is not None:
            return
        reader = self._open()
        try:
            counts: dict[str, list] = {}
            defs = {}
            for c in reader.connections:
                mt = normalize_msgtype(c.msgtype)
                entry = counts.setdefault(c.topic, [mt, 0])
                entry[1] += c.msgcount
                if c.msgdef.data:
                    defs[mt] = (mt, "msg", c.msgdef.data)
            try:
                self._store = build_typestore(defs.values())
            except Exception as exc:  # rosbags raises several types for bad definitions
                raise LogFormatError(self.path, "connection records", f"bad message definition: {exc}") from None
            self._topics = [TopicInfo(name, mt, n) for name, (mt, n) in sorted(counts.items())]
        finally:
            reader.close()

    def topics(self) -> list[TopicInfo]:
        self._load_meta()
        assert self._topics is not None
        return list(self._topics)

    def _raw_messages(self, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[RawMessage]:
        """Messages in time order; with *on_skip*, a message rosbags cannot read (corrupt chunk or
        record) is reported and reading resumes after its stamp.

        rosbags' message generator dies with its first error, so resuming restarts it at
        ``stamp + 1 ns`` of the failing index entry (found in ``Reader.indexes``, merged in the
        same order as rosbags merges them); entries sharing that nanosecond are reported too.
        """
        from rosbags.rosbag1 import ReaderError

        self._load_meta()
        own = self._shared is None
        reader = self._open() if own else self._shared
        counts: dict[str, int] = {}
        last = "the first message"
        try:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            if not conns:
                return
            index = None  # (stamp ns, topic) of every message in rosbags' order, built on the first error
            done = 0  # messages handed out or skipped so far, in that order
            start: int | None = None
            while True:
                it = reader.messages(connections=conns, start=start)
                try:
                    for conn, t_ns, data in it:
                        k = counts.get(conn.topic, 0)
                        counts[conn.topic] = k + 1
                        last = f"{conn.topic} message {k}"
                        done += 1
                        yield RawMessage(k, conn.topic, normalize_msgtype(conn.msgtype), int(t_ns), data, last)
                    return
                except (ReaderError, OSError, ValueError, KeyError, IndexError, EOFError, AssertionError) as exc:
                    error = LogFormatError(self.path, f"after {last}", f"corrupt or truncated bag: {exc}")
                    if on_skip is None:
                        raise error from None
                if index is None:
                    index = [(e.time, c.topic) for e, c in heapq.merge(
                        *[[(e, c) for e in reader.indexes[c.id]] for c in conns], key=lambda ec: ec[0].time)]
                if done >= len(index):
                    on_skip(error)
                    return
                t_bad = index[done][0]
                while done < len(index) and index[done][0] == t_bad:
                    topic = index[done][1]
                    k = counts.get(topic, 0)
                    counts[topic] = k + 1
                    on_skip(LogFormatError(self.path, f"{topic} message {k}", f"unreadable in the bag, skipped: {error.what}"))
                    done += 1
                start = t_bad + 1
        finally:
            if own:
                reader.close()

    def _decode(self, raw: RawMessage) -> Any:
        assert self._store is not None
        try:
            return self._store.deserialize_ros1(raw.data, raw.msgtype)
        except Exception as exc:  # rosbags raises SerdeError, struct.error, KeyError, ...
            raise LogFormatError(self.path, raw.where, f"cannot decode {raw.msgtype} on {raw.topic}: {exc}") from None
