"""ROS 1 bag (format 2.0) reader: LaserScan / PointCloud2 frames with odometry, ground truth and TF.

The container is read by ``rosbags.rosbag1.Reader``; messages are decoded with types built from
the message definitions stored in the bag's connection records, so bags with any message set
(e.g. ``tf2_msgs/TFMessage``, which the Noetic store of rosbags lacks) decode without ROS. The
conversions to :class:`~core.frame.Frame` are shared with the MCAP reader
(:mod:`slam.logs.ros_msgs`). Stamps are the header stamps (float seconds).

Memory: rosbags keeps the bag's index (one small entry per message) in memory and one
decompressed chunk at a time; the frame assembly itself is streaming (see
:class:`~slam.logs.ros_reader.RosLogReader`).
"""

from __future__ import annotations

import heapq
from typing import Any, Iterator

from core.errors import LogFormatError

from .base import SkipHandler, TopicInfo, lost
from .ros_msgs import RawMessage, build_typestore, normalize_msgtype
from .rosbags_container import RosbagsReader

__all__ = ["Ros1BagReader"]


class Ros1BagReader(RosbagsReader):
    """Stream a ROS 1 ``.bag`` file as Frames (see :class:`RosLogReader` for the arguments)."""

    format = "ros1"

    def _open(self):
        from rosbags.rosbag1 import Reader

        try:
            reader = Reader(self.path)
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises ReaderError, and struct/decoder errors on garbage
            raise LogFormatError(self.path, None, f"not a readable ROS 1 bag: {type(exc).__name__}: {exc}") from None
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

    def _raw_messages(self, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[RawMessage]:
        """Messages in time order. A chunk rosbags cannot read (corrupt, truncated: no checksum guards a
        ROS 1 bag, so this is what flipped bytes in a compressed chunk give) is an error naming the chunk,
        its byte offset and the reason; with *on_skip* it is reported once, with the messages it held
        (from the bag's index, which is read before any chunk), and reading resumes after them.

        rosbags' message generator dies with its first error, so resuming restarts it after the last
        nanosecond skipped: the failing index entry's, and those of the entries after it that belong to
        a bad chunk or share that stamp (such an entry of a good chunk is lost too and reported alone).
        """
        self._load_meta()
        own = self._shared is None
        reader = self._open() if own else self._shared
        counts: dict[str, int] = {}
        try:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            if not conns:
                return
            index = None  # (stamp ns, topic, chunk position) of every message in rosbags' order, on the first error
            done = 0  # messages handed out or skipped so far, in that order
            bad: set[int] = set()  # chunks found unreadable
            start: int | None = None
            while True:
                it = reader.messages(connections=conns, start=start)
                try:
                    for conn, t_ns, data in it:
                        k = counts.get(conn.topic, 0)
                        counts[conn.topic] = k + 1
                        done += 1
                        where = f"{conn.topic} message {k}"
                        yield RawMessage(k, conn.topic, normalize_msgtype(conn.msgtype), int(t_ns), data, where)
                    return
                except Exception as exc:  # noqa: BLE001 - rosbags' ReaderError, and its decompressors' OSError, lz4's RuntimeError, ...
                    why = f"{type(exc).__name__}: {exc}".rstrip(": ")
                if index is None:
                    index = [(e.time, c.topic, e.chunk_pos) for e, c in heapq.merge(
                        *[[(e, c) for e in reader.indexes[c.id]] for c in conns], key=lambda ec: ec[0].time)]
                if done >= len(index):  # past the last indexed message: nothing more to resume at
                    error = lost(LogFormatError(self.path, "after the last indexed message",
                                                f"corrupt or truncated bag: {why}"), None)
                    if on_skip is None:
                        raise error
                    on_skip(error)
                    return
                pos = index[done][2]
                error = self._chunk_error(reader, pos, why)
                if on_skip is None:
                    raise error
                if pos not in bad:
                    bad.add(pos)
                    held: dict[str, int] = {}
                    for _, topic, p in index[done:]:
                        if p == pos:
                            held[topic] = held.get(topic, 0) + 1
                    on_skip(lost(error, held))
                t_skip = None
                while done < len(index) and (index[done][2] in bad or index[done][0] == t_skip):
                    t_skip, topic, p = index[done]
                    k = counts.get(topic, 0)
                    counts[topic] = k + 1
                    if p not in bad:
                        on_skip(lost(LogFormatError(self.path, f"{topic} message {k}", f"lost with {error.where} (it "
                                                    f"shares the stamp it stopped at): {error.what}"), {topic: 1}))
                    done += 1
                if done >= len(index):
                    return
                start = int(t_skip) + 1
        finally:
            if own:
                reader.close()

    def _chunk_error(self, reader: Any, pos: int, why: str) -> LogFormatError:
        """The error of the chunk at byte offset *pos*: its number (from 1), offset, log time span, reason."""
        infos = sorted(reader.chunk_infos, key=lambda c: c.pos)
        number = next((n for n, c in enumerate(infos, 1) if c.pos == pos), None)
        info = infos[number - 1] if number is not None else None
        span = f"log time {info.start_time / 1e9:.3f}–{info.end_time / 1e9:.3f} s, " if info is not None else ""
        return LogFormatError(self.path, f"chunk {number} at byte offset {pos}",
                              f"corrupt or truncated bag chunk ({span}{why})")

    def _decode(self, raw: RawMessage) -> Any:
        assert self._store is not None
        try:
            return self._store.deserialize_ros1(raw.data, raw.msgtype)
        except Exception as exc:  # rosbags raises SerdeError, struct.error, KeyError, ...
            raise LogFormatError(self.path, raw.where, f"cannot decode {raw.msgtype} on {raw.topic}: {exc}") from None
