"""MCAP reader for ROS 2 (CDR) — and ROS 1 — messages: LaserScan / PointCloud2 frames with
odometry, ground truth and TF.

The container is read streaming, through the ``mcap`` library. With a summary section (chunk
indexes) the chunks are read one by one in the library's log-time order (:mod:`slam.logs.mcap_indexed`:
the library's records and message queue, each chunk on its own so that a damaged one is named by its
byte offset), holding one or a few chunks at a time. Without one (a file written by a streaming
recorder, or a truncated file) the library reads the file linearly, in file order (recorders write
in arrival order).
Messages are decoded with types built from the schemas carried in the file
(``ros2msg`` / ``ros2idl`` / ``ros1msg``), registered with rosbags' ``get_types_from_msg`` /
``get_types_from_idl``, so files written by any ROS 2 tool decode, not only our own. Chunk
CRCs are checked, so flipped bytes surface as an error naming the message, not as garbage.

Skipping (``frames(on_skip=...)``): a message that does not decode is left out; with a summary
section, a corrupt chunk (header, decompression, CRC or record layout) is reported with its byte
offset and left out, and the next chunks are read in the same log-time order; without one, the
linear read cannot find the next record after a corrupt or cut one, so the messages end there (as
they do with ``indexed=False``, the library's own seeking reader).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterator

from core.errors import LogFormatError

from .base import SkipHandler, TopicInfo, lost
from .mcap_indexed import ChunkError, indexed_messages, message_counts
from .ros_msgs import RawMessage, cached_typestore, normalize_msgtype
from .ros_reader import RosLogReader

__all__ = ["McapReader"]

_SCHEMA_ENCODINGS = {"ros2msg": "msg", "ros1msg": "msg", "ros2idl": "idl"}
_MESSAGE_ENCODINGS = {"cdr", "ros1"}


class McapReader(RosLogReader):
    """Stream an MCAP file as Frames (see :class:`~slam.logs.ros_reader.RosLogReader` for the arguments).

    Args:
        validate_crcs: check chunk CRCs (catches flipped bytes in uncompressed chunks).
        indexed: read a chunk-indexed file chunk by chunk (:mod:`slam.logs.mcap_indexed`; False: the
            library's ``SeekingReader`` in one go — the same messages in the same order, but an error
            does not name the chunk, and with ``on_skip`` the messages end at the first corrupt chunk).
    """

    format = "mcap"

    def __init__(
        self,
        path: str | Path,
        topic: str | None = None,
        *,
        validate_crcs: bool = True,
        indexed: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(path, topic, **kwargs)
        self.validate_crcs = validate_crcs
        self.indexed = indexed
        self._topics: list[TopicInfo] | None = None
        self._store: Any = None
        self._encoding: dict[str, str] = {}  # topic -> message encoding
        self._bad_schema: dict[str, str] = {}  # topic -> why its schema cannot be used
        self._summary_cache: tuple[Any] | None = None  # (summary or None,) once read

    # -- container ----------------------------------------------------------------------------

    def _summary(self) -> Any:
        """The summary section (read once per reader), or None when the file has none or its
        footer is unreadable."""
        if self._summary_cache is None:
            from mcap.reader import SeekingReader

            with self._open() as fh:
                try:
                    summary = SeekingReader(fh).get_summary()
                except Exception:  # truncated / corrupt footer: fall back to a linear read
                    summary = None
            self._summary_cache = (summary,)
        return self._summary_cache[0]

    def _use_index(self) -> bool:
        """Whether the file is read chunk by chunk: it has chunk indexes and ``indexed`` is on."""
        summary = self._summary()
        return self.indexed and summary is not None and bool(summary.chunk_indexes)

    def _library_records(self, fh, topics: set[str] | None) -> Iterator[tuple[Any, Any, Any]]:
        """(schema, channel, message) from the ``mcap`` library: in log-time order when the file is
        chunk-indexed, else in file order."""
        from mcap.reader import NonSeekingReader, SeekingReader

        summary = self._summary()
        fh.seek(0)
        if summary is not None and summary.chunk_indexes:
            return SeekingReader(fh, validate_crcs=self.validate_crcs).iter_messages(topics=topics, log_time_order=True)
        # File order: log_time_order=True would make the mcap library load the whole file to sort it.
        return NonSeekingReader(fh, validate_crcs=self.validate_crcs).iter_messages(topics=topics, log_time_order=False)

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
        summary = self._summary()
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        counts: dict[int, int] = {}
        if summary is not None and summary.statistics is not None:
            schemas, channels = dict(summary.schemas), dict(summary.channels)
            counts = dict(summary.statistics.channel_message_counts)
        else:
            with self._open() as fh:
                try:
                    for schema, channel, _msg in self._guard(self._library_records(fh, None), fh.tell, {}):
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
            self._store = cached_typestore(tuple(defs.values()))
        except Exception as exc:  # rosbags raises several types for malformed definitions
            raise LogFormatError(self.path, "schema records", f"bad message definition: {exc}") from None
        self._topics = [TopicInfo(name, mt, n) for name, (mt, n) in sorted(per_topic.items())]

    def _guard(
        self,
        it: Iterator,
        tell: Callable[[], int],
        counts: dict[str, int] | None = None,
        topic_of: Callable[[Any], str] | None = None,
        on_skip: SkipHandler | None = None,
    ) -> Iterator:
        """Re-raise container errors as LogFormatError with the byte offset and last good message
        (with *on_skip*: report it there and end the messages, the stream cannot be resumed).

        *tell* gives the file position when the error carries none; *topic_of(item)* the topic of
        an item (default ``item[1].topic``), counted into *counts*."""
        last = "before the first message"
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception as exc:  # mcap raises McapError, EndOfFile, struct.error, zstd errors, ...
                pos = getattr(exc, "offset", None)
                if pos is None:
                    try:
                        pos = tell()
                    except (OSError, ValueError):
                        pos = -1
                why = str(exc) if isinstance(exc, ChunkError) else f"{type(exc).__name__}: {exc}".rstrip(": ")
                error = LogFormatError(self.path, f"byte offset {pos} ({last})", f"corrupt or truncated MCAP: {why}")
                if on_skip is None:
                    raise error from None
                on_skip(lost(error, None))  # the stream cannot resume: what followed is not known
                return
            if counts is not None:
                topic = item[1].topic if topic_of is None else topic_of(item)
                counts[topic] = counts.get(topic, -1) + 1
                last = f"after {topic} message {counts[topic]}"
            yield item

    def topics(self) -> list[TopicInfo]:
        self._load_meta()
        assert self._topics is not None
        return list(self._topics)

    def _raw_messages(self, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[RawMessage]:
        self._load_meta()
        counts: dict[str, int] = {}
        if self._use_index():
            yield from self._indexed_raw_messages(topics, counts, on_skip)
            return
        with self._open() as fh:
            records = self._library_records(fh, topics)
            for schema, channel, message in self._guard(records, fh.tell, counts, on_skip=on_skip):
                topic = channel.topic
                mt = normalize_msgtype(schema.name) if schema is not None else "(no schema)"
                k = counts[topic]
                yield RawMessage(k, topic, mt, int(message.log_time), message.data, f"{topic} message {k}")

    def _indexed_raw_messages(
        self, topics: set[str] | None, counts: dict[str, int], on_skip: SkipHandler | None
    ) -> Iterator[RawMessage]:
        """Chunk by chunk (:func:`slam.logs.mcap_indexed.indexed_messages`). With *on_skip*, a chunk that
        cannot be read is reported (``byte offset N``, with the messages its index says it held) and left out."""
        summary = self._summary()

        def chunk_skipped(exc: ChunkError, index: Any) -> None:
            assert on_skip is not None
            span = f"log time {index.message_start_time / 1e9:.9f}–{index.message_end_time / 1e9:.9f} s"
            what = f"corrupt MCAP chunk ({span}) skipped: {exc}"
            with self._open() as idx:
                held = message_counts(idx, index)
            per_topic = None if held is None else {}
            for cid, n in (held or {}).items():
                ch = summary.channels.get(cid)
                if ch is not None and (topics is None or ch.topic in topics):
                    per_topic[ch.topic] = per_topic.get(ch.topic, 0) + n  # type: ignore[index]
            on_skip(lost(LogFormatError(self.path, f"byte offset {exc.offset}", what), per_topic))

        with self._open() as fh:
            it = indexed_messages(fh, summary, topics, validate_crcs=self.validate_crcs,
                                  on_error=None if on_skip is None else chunk_skipped)
            for schema, channel, message in self._guard(it, lambda: -1, counts, on_skip=on_skip):
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
