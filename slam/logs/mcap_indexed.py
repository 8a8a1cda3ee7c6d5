"""A chunk-indexed MCAP read chunk by chunk through the ``mcap`` library, so that a damaged chunk is
named (its byte offset) and, when the caller asks, left out while the rest is read.

``mcap.reader.SeekingReader.iter_messages`` stops at the first chunk it cannot read, with an error
that does not say which. This is the same loop over the same library parts — the chunk indexes of
the summary, ``Chunk.read``, ``breakup_chunk`` (decompression and CRC), ``make_message_queue`` (the
library's log-time order: chunks keyed ``(message_start_time, chunk_start_offset)``, messages
``(log_time, chunk_start_offset, position)``) — with each chunk read on its own: one that fails is
a :class:`ChunkError`, raised when its turn comes or, with ``on_error``, reported and skipped. A chunk
whose header disagrees with its index (compression, sizes: damage that zeroed the CRC, which the spec
reads as "no CRC") counts as damaged too. Memory holds the chunks whose time range overlaps the
current message (one for a file written in time order).
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from typing import Any, BinaryIO

from mcap.reader import make_message_queue
from mcap.records import Chunk, ChunkIndex, Message, MessageIndex, Opcode
from mcap.stream_reader import ReadDataStream, breakup_chunk

__all__ = ["ChunkError", "indexed_messages", "message_counts"]

_RECORD_HEAD = 9  # opcode u8 + content length u64


class ChunkError(Exception):
    """A chunk that cannot be read; ``offset`` is its byte offset in the file."""

    def __init__(self, offset: int, what: str) -> None:
        super().__init__(what)
        self.offset = offset


def _records(fh: BinaryIO, index: ChunkIndex, validate_crc: bool) -> list[Any]:
    """The records of the chunk *index* describes, read from its indexed bytes only."""
    start, length = int(index.chunk_start_offset), int(index.chunk_length)
    fh.seek(start)
    raw = fh.read(length)
    if length <= _RECORD_HEAD or len(raw) != length:
        raise ChunkError(start, f"indexed chunk [{start}, {start + length}) is not in the file")
    stream = ReadDataStream(io.BytesIO(raw))
    op, content = stream.read1(), stream.read8()
    if op != Opcode.CHUNK or content != length - _RECORD_HEAD:
        raise ChunkError(start, f"no chunk record at the indexed offset (opcode {op:#04x}, length {content}, "
                                f"index says {length - _RECORD_HEAD})")
    try:
        chunk = Chunk.read(stream)
        declared = (chunk.compression, len(chunk.data), chunk.uncompressed_size)
        indexed = (index.compression, int(index.compressed_size), int(index.uncompressed_size))
        if declared != indexed:
            raise ChunkError(start, f"chunk header (compression, compressed size, size) {declared} differs from its index {indexed}")
        return breakup_chunk(chunk, validate_crc=validate_crc)
    except ChunkError:
        raise
    except Exception as exc:  # EndOfFile, CRC, zstd / lz4 errors, an unknown compression, a bad record
        raise ChunkError(start, f"{type(exc).__name__}: {exc}".rstrip(": ")) from None


def indexed_messages(
    fh: BinaryIO,
    summary: Any,
    topics: set[str] | None = None,
    *,
    validate_crcs: bool = True,
    on_error: Callable[[ChunkError, ChunkIndex], None] | None = None,
) -> Iterator[tuple[Any, Any, Message]]:
    """``(schema or None, channel, message)`` of every message on *topics* (all when None) in the
    library's log-time order, read through the chunk indexes of *summary* (``mcap.summary.Summary``).

    A chunk that cannot be read — or holds a message on a channel the summary does not list — raises
    :class:`ChunkError` when its turn comes, after every message that sorts before it; with *on_error*
    it is passed to ``on_error(error, chunk_index)`` and left out, the others merged as without it."""
    channels, schemas = summary.channels, summary.schemas
    queue = make_message_queue(log_time_order=True)
    for ci in summary.chunk_indexes:
        ids = ci.message_index_offsets
        if topics is None or not ids or any(c not in channels or channels[c].topic in topics for c in ids):
            queue.push(ci)
    while queue:
        item = queue.pop()
        if not isinstance(item, ChunkIndex):
            yield item[0]
            continue
        offset = int(item.chunk_start_offset)
        try:
            msgs = []
            for position, record in enumerate(_records(fh, item, validate_crcs)):
                if isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        raise ChunkError(offset, f"message on channel {record.channel_id}, which the summary does not list")
                    if topics is None or channel.topic in topics:
                        msgs.append(((schemas.get(channel.schema_id), channel, record), offset, position))
        except ChunkError as exc:
            if on_error is None:
                raise
            on_error(exc, item)
            continue
        for m in msgs:
            queue.push(m)


def message_counts(fh: BinaryIO, index: ChunkIndex) -> dict[int, int] | None:
    """Messages per channel id in a chunk, from its Message Index records (which follow the chunk): what a
    damaged chunk held. None when those records cannot be read either."""
    out: dict[int, int] = {}
    try:
        for cid, offset in index.message_index_offsets.items():
            fh.seek(offset)
            stream = ReadDataStream(fh)
            if stream.read1() != Opcode.MESSAGE_INDEX:
                return None
            stream.read8()
            found = MessageIndex.read(stream)
            if found.channel_id != cid:
                return None
            out[cid] = len(found.records)
    except Exception:  # EndOfFile, struct errors: the index is damaged too
        return None
    return out
