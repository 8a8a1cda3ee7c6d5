"""MCAP reader for ROS 2 (CDR) — and ROS 1 — messages: LaserScan / PointCloud2 frames with
odometry, ground truth and TF.

The container is read with the ``mcap`` library, streaming: with a summary section (chunk
indexes) the ``SeekingReader`` visits chunks in log-time order holding one or a few chunks at
a time; without one (a file written by a streaming recorder, or a truncated file) the file is read
linearly, in file order (recorders write in arrival order).
Messages are decoded with types built from the schemas carried in the file
(``ros2msg`` / ``ros2idl`` / ``ros1msg``), registered with rosbags' ``get_types_from_msg`` /
``get_types_from_idl``, so files written by any ROS 2 tool decode, not only our own. Chunk
CRCs are checked, so flipped bytes surface as an error naming the message, not as garbage.

Skipping (``frames(on_skip=...)``): a message that does not decode is left out; with a summary
section, a corrupt chunk is left out and the next chunks are read (chunk by chunk from the chunk
index, merged in log-time order as the ``SeekingReader`` does); without one, the linear read
cannot find the next record after a corrupt or cut one, so the messages end there.
"""

from __future__ import annotations

import heapq
import io
import struct
from pathlib import Path
from typing import Any, Iterator

from registration.errors import LogFormatError

from .base import SkipHandler, TopicInfo
from .ros_msgs import RawMessage, RosLogReader, build_typestore, normalize_msgtype

__all__ = ["McapReader"]

_SCHEMA_ENCODINGS = {"ros2msg": "msg", "ros1msg": "msg", "ros2idl": "idl"}
_MESSAGE_ENCODINGS = {"cdr", "ros1"}


class McapReader(RosLogReader):
    """Stream an MCAP file as Frames (see :class:`~slam.logs.ros_msgs.RosLogReader` for the arguments)."""

    format = "mcap"

    def __init__(self, path: str | Path, topic: str | None = None, *, validate_crcs: bool = True, **kwargs: Any) -> None:
        super().__init__(path, topic, **kwargs)
        self.validate_crcs = validate_crcs  # chunk CRCs: catches flipped bytes in uncompressed chunks
        self._topics: list[TopicInfo] | None = None
        self._store: Any = None
        self._encoding: dict[str, str] = {}  # topic -> message encoding
        self._bad_schema: dict[str, str] = {}  # topic -> why its schema cannot be used

    # -- container ----------------------------------------------------------------------------

    def _summary(self, fh) -> Any:
        """The summary section, or None when the file has none or its footer is unreadable."""
        from mcap.reader import SeekingReader

        try:
            return SeekingReader(fh).get_summary()
        except Exception:  # truncated / corrupt footer: fall back to a linear read
            return None

    def _records(self, fh, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[tuple[Any, Any, Any]]:
        """(schema, channel, message) in log-time order; chunk-indexed when possible. With *on_skip*
        and a chunk index, corrupt chunks are reported and skipped."""
        from mcap.reader import NonSeekingReader, SeekingReader

        summary = self._summary(fh)
        fh.seek(0)
        if summary is not None and summary.chunk_indexes:
            if on_skip is not None:
                return self._chunked_records(fh, summary, topics, on_skip)
            return SeekingReader(fh, validate_crcs=self.validate_crcs).iter_messages(topics=topics, log_time_order=True)
        # File order: log_time_order=True would make the mcap library load the whole file to sort it.
        return NonSeekingReader(fh, validate_crcs=self.validate_crcs).iter_messages(topics=topics, log_time_order=False)

    def _chunk_messages(self, fh, index: Any, summary: Any, topics: set[str] | None) -> list[tuple[Any, Any, Any]]:
        """(schema, channel, message) of one chunk (file order); raises whatever a corrupt chunk raises."""
        from mcap.data_stream import ReadDataStream
        from mcap.opcode import Opcode
        from mcap.records import Chunk, Message
        from mcap.stream_reader import breakup_chunk

        fh.seek(index.chunk_start_offset)
        raw = fh.read(index.chunk_length)  # opcode (1 byte), record length (uint64), Chunk record
        if len(raw) != index.chunk_length or raw[0] != Opcode.CHUNK:
            raise ValueError(f"no chunk record of {index.chunk_length} bytes at byte offset {index.chunk_start_offset}")
        (length,) = struct.unpack_from("<Q", raw, 1)
        if length != index.chunk_length - 9:
            raise ValueError(f"chunk record length {length}, the chunk index says {index.chunk_length - 9}")
        chunk = Chunk.read(ReadDataStream(io.BytesIO(raw[9:])))
        out = []
        for rec in breakup_chunk(chunk, validate_crc=self.validate_crcs):
            if isinstance(rec, Message):
                channel = summary.channels[rec.channel_id]
                if topics is None or channel.topic in topics:
                    out.append((summary.schemas.get(channel.schema_id), channel, rec))
        return out

    def _chunked_records(self, fh, summary: Any, topics: set[str] | None, on_skip: SkipHandler) -> Iterator[tuple[Any, Any, Any]]:
        """Messages of *topics* in log-time order from the chunk index, skipping corrupt chunks.

        The order is the ``SeekingReader``'s: by log time, then by chunk offset, then by position
        in the chunk; a chunk is opened when the merge reaches its first log time.
        """
        heap: list[tuple[int, int, int, Any]] = []  # (log time, chunk offset, index in chunk or -1, item)
        for ci in summary.chunk_indexes:
            ids = ci.message_index_offsets
            if topics is not None and ids and not any(c in summary.channels and summary.channels[c].topic in topics for c in ids):
                continue
            heap.append((ci.message_start_time, ci.chunk_start_offset, -1, ci))
        heapq.heapify(heap)
        while heap:
            t, offset, i, item = heapq.heappop(heap)
            if i >= 0:
                yield item
                continue
            try:
                messages = self._chunk_messages(fh, item, summary, topics)
            except Exception as exc:  # mcap raises CRC, decompression, struct and key errors
                why = f"{type(exc).__name__}: {exc}".rstrip(": ")
                on_skip(LogFormatError(self.path, f"byte offset {offset}",
                                       f"corrupt MCAP chunk (log time {item.message_start_time / 1e9:.9f}–"
                                       f"{item.message_end_time / 1e9:.9f} s) skipped: {why}"))
                continue
            for k, m in enumerate(messages):
                heapq.heappush(heap, (m[2].log_time, offset, k, m))

    def _open(self):
        try:
            fh = open(self.path, "rb")
        except OSError as exc:
            raise LogFormatError(self.path, None, f"cannot open: {exc.strerror}") from None
        try:
            head = fh.read(8)
        except OSError as exc:
            fh.close()
            raise LogFormatError(self.path, "byte 0", f"cannot read: {exc}") from None
        if head != b"\x89MCAP0\r\n":
            fh.close()
            what = "empty file" if not head else f"not an MCAP file (magic {head!r})"
            raise LogFormatError(self.path, "byte 0", what)
        fh.seek(0)
        return fh

    def _load_meta(self, tolerant: bool = False) -> None:
        """Topics, types and counts: from the summary when present, else from one linear pass
        (*tolerant*: up to the first corrupt or cut record, which the message pass then reports)."""
        if self._topics is not None:
            return
        with self._open() as fh:
            summary = self._summary(fh)
            schemas: dict[int, Any] = {}
            channels: dict[int, Any] = {}
            counts: dict[int, int] = {}
            if summary is not None and summary.statistics is not None:
                schemas, channels = dict(summary.schemas), dict(summary.channels)
                counts = dict(summary.statistics.channel_message_counts)
            else:
                fh.seek(0)
                try:
                    for schema, channel, _msg in self._guard(self._records(fh, None), fh, {}):
                        channels[channel.id] = channel
                        if schema is not None:
                            schemas[schema.id] = schema
                        counts[channel.id] = counts.get(channel.id, 0) + 1
                except LogFormatError:
                    if not tolerant or not channels:
                        raise
        per_topic: dict[str, list] = {}
        defs: dict[str, tuple[str, str, str]] = {}
        for cid, ch in channels.items():
            schema = schemas.get(ch.schema_id)
            mt = normalize_msgtype(schema.name) if schema is not None else "(no schema)"
            entry = per_topic.setdefault(ch.topic, [mt, 0])
            entry[1] += counts.get(cid, 0)
            self._encoding[ch.topic] = ch.message_encoding
            if ch.message_encoding not in _MESSAGE_ENCODINGS:
                self._bad_schema[ch.topic] = f"message encoding {ch.message_encoding!r} (expected cdr or ros1)"
            elif schema is None or schema.encoding not in _SCHEMA_ENCODINGS or not schema.data:
                enc = "none" if schema is None else repr(schema.encoding)
                self._bad_schema[ch.topic] = f"schema encoding {enc} (expected ros2msg, ros2idl or ros1msg with a definition)"
            else:
                defs[mt] = (mt, _SCHEMA_ENCODINGS[schema.encoding], schema.data.decode("utf-8", "replace"))
        try:
            self._store = build_typestore(defs.values())
        except Exception as exc:  # rosbags raises several types for malformed definitions
            raise LogFormatError(self.path, "schema records", f"bad message definition: {exc}") from None
        self._topics = [TopicInfo(name, mt, n) for name, (mt, n) in sorted(per_topic.items())]

    def _guard(self, it: Iterator, fh, counts: dict[str, int] | None = None, on_skip: SkipHandler | None = None) -> Iterator:
        """Re-raise container errors as LogFormatError with the byte offset and last good message
        (with *on_skip*: report it there and end the messages)."""
        last = "before the first message"
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception as exc:  # mcap raises McapError, EndOfFile, struct.error, zstd errors, ...
                try:
                    pos = fh.tell()
                except (OSError, ValueError):
                    pos = -1
                why = f"{type(exc).__name__}: {exc}".rstrip(": ")
                error = LogFormatError(self.path, f"byte offset {pos} ({last})", f"corrupt or truncated MCAP: {why}")
                if on_skip is None:
                    raise error from None
                on_skip(error)
                return
            if counts is not None:
                topic = item[1].topic
                counts[topic] = counts.get(topic, -1) + 1
                last = f"after {topic} message {counts[topic]}"
            yield item

    def topics(self) -> list[TopicInfo]:
        self._load_meta()
        assert self._topics is not None
        return list(self._topics)

    def _raw_messages(self, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[RawMessage]:
        self._load_meta()
        with self._open() as fh:
            counts: dict[str, int] = {}
            for schema, channel, message in self._guard(self._records(fh, topics, on_skip), fh, counts, on_skip):
                topic = channel.topic
                mt = normalize_msgtype(schema.name) if schema is not None else "(no schema)"
                k = counts[topic]
                yield RawMessage(k, topic, mt, int(message.log_time), message.data, f"{topic} message {k}")

    def _decode(self, raw: RawMessage) -> Any:
        if raw.topic in self._bad_schema:
            raise LogFormatError(self.path, raw.where, f"cannot decode {raw.topic}: {self._bad_schema[raw.topic]}")
        try:
            if self._encoding.get(raw.topic) == "ros1":
                return self._store.deserialize_ros1(raw.data, raw.msgtype)
            return self._store.deserialize_cdr(raw.data, raw.msgtype)
        except Exception as exc:  # rosbags raises SerdeError, struct.error, IndexError, ...
            raise LogFormatError(self.path, raw.where, f"cannot decode {raw.msgtype}: {type(exc).__name__}: {exc}") from None
