"""Indexed MCAP chunk reading: the file memory-mapped, chunks located through the summary's chunk
indexes, messages handed out as zero-copy ``memoryview`` slices of the decompressed chunk.

Record layout per the MCAP specification (https://mcap.dev/spec): a record is ``opcode u8,
length u64, content``. A Chunk (opcode 0x06) holds ``message_start_time u64, message_end_time u64,
uncompressed_size u64, uncompressed_crc u32, compression string (u32 length + UTF-8), records
(u64 length + bytes)``; the records inside are Schema / Channel / Message records, a Message
(0x05) being ``channel_id u16, sequence u32, log_time u64, publish_time u64, data``.

Why not ``mcap.reader.SeekingReader``: it reads each chunk into a ``bytes`` object, reads every
message payload out of a ``BytesIO`` over the decompressed records into another one — two copies
of every byte besides the decompression — and builds Python objects per record through a
field-by-field stream reader. Here the compressed bytes come straight from the page cache
(``mmap``), are decompressed once, and the payloads are views.

Message order is exactly the library's ``log_time_order=True`` order: sorted by ``(log_time,
chunk_start_offset, position in the chunk)``, chunks being opened lazily in ``(message_start_time,
chunk_start_offset)`` order, so memory holds only the chunks whose time range overlaps the current
message (one chunk for a file written in time order). Because that opening order is known in
advance, the next chunks can be decompressed by worker threads while the caller checks and
decodes the current one (zstd, lz4, zlib and numpy's casts release the GIL): at most
``prefetch`` chunks beyond the open ones are held, so memory stays constant in the log length.
"""

from __future__ import annotations

import heapq
import mmap
import struct
import threading
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["ChunkError", "SUPPORTED_COMPRESSIONS", "check_crc", "chunk_messages", "indexed_messages", "load_chunk", "read_chunk",
           "message_counts"]

SUPPORTED_COMPRESSIONS = ("", "zstd", "lz4")

_OP_MESSAGE = 0x05
_OP_CHUNK = 0x06
_RECORD = struct.Struct("<BQ")  # opcode, content length
_MESSAGE = struct.Struct("<BQHIQ")  # opcode, length, channel_id, sequence, log_time
_CHUNK_HEAD = struct.Struct("<BQQQQII")  # opcode, length, start, end, uncompressed_size, crc, compression length
_MESSAGE_HEAD = 22  # channel_id u16 + sequence u32 + log_time u64 + publish_time u64


class ChunkError(Exception):
    """A chunk that cannot be read; ``offset`` is its byte offset in the file."""

    def __init__(self, offset: int, what: str) -> None:
        super().__init__(what)
        self.offset = offset


_local = threading.local()
_OP_MESSAGE_INDEX = 0x07
_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, length, channel_id, byte length of the (log_time, offset) pairs


def message_counts(path: str | Path, chunk_index: Any) -> dict[int, int] | None:
    """Messages per channel id in a chunk, from its Message Index records (16 bytes per message), which
    follow the chunk: what a damaged chunk held. None when those records cannot be read either."""
    out: dict[int, int] = {}
    try:
        with open(path, "rb") as fh:
            for cid, offset in chunk_index.message_index_offsets.items():
                fh.seek(offset)
                op, _, rec_cid, nbytes = _INDEX_HEAD.unpack(fh.read(_INDEX_HEAD.size))
                if op != _OP_MESSAGE_INDEX or rec_cid != cid or nbytes % 16:
                    return None
                out[cid] = nbytes // 16
    except (OSError, struct.error):
        return None
    return out


def _zstd_decompress(data: memoryview, size: int) -> bytes:
    dctx = getattr(_local, "zstd", None)
    if dctx is None:  # a ZstdDecompressor must not be shared between threads
        import zstandard

        dctx = _local.zstd = zstandard.ZstdDecompressor()
    return dctx.decompress(data, max_output_size=size)


def _lz4_decompress(data: memoryview, size: int) -> bytes:
    import lz4.frame

    return lz4.frame.decompress(data)


_DECOMPRESS: dict[str, Callable[[memoryview, int], Any]] = {"zstd": _zstd_decompress, "lz4": _lz4_decompress}


def load_chunk(view: memoryview, index: Any) -> tuple[memoryview, int]:
    """The decompressed records of the chunk described by the ``ChunkIndex`` *index* and the CRC-32
    its header declares for them (0: none), not yet checked (:func:`check_crc`).

    Args:
        view: the whole file (a ``memoryview`` of its ``mmap``).
        index: ``mcap.records.ChunkIndex`` (``chunk_start_offset``, ``chunk_length``,
            ``compression``, ``compressed_size``, ``uncompressed_size``).

    The records are a view into *view* for an uncompressed chunk, else into a fresh buffer.
    Raises :class:`ChunkError` (with the chunk's offset) on any inconsistency, including a chunk
    header whose compression or sizes differ from its index (the spec's ChunkIndex repeats them):
    damage that zeroes the CRC (0: "no CRC") and the sizes would otherwise pass as an empty chunk.
    """
    start, length = int(index.chunk_start_offset), int(index.chunk_length)
    end = start + length
    if length < _CHUNK_HEAD.size:
        raise ChunkError(start, f"indexed chunk length {length} is shorter than a chunk header")
    if start < 0 or end > len(view):
        raise ChunkError(start, f"chunk [{start}, {end}) lies outside the file ({len(view)} bytes)")
    op, rec_len, _t0, _t1, usize, crc, clen = _CHUNK_HEAD.unpack_from(view, start)
    if op != _OP_CHUNK or rec_len != length - 9:
        raise ChunkError(start, f"no chunk record at the indexed offset (opcode {op:#04x}, length {rec_len}, index says {length - 9})")
    pos = start + _CHUNK_HEAD.size
    if pos + clen + 8 > end:
        raise ChunkError(start, f"chunk compression name of {clen} bytes runs past the chunk")
    compression = bytes(view[pos : pos + clen]).decode("utf-8", "replace")
    pos += clen
    (data_len,) = struct.unpack_from("<Q", view, pos)
    pos += 8
    if pos + data_len > end:
        raise ChunkError(start, f"chunk data of {data_len} bytes runs past the chunk end")
    declared = (compression, data_len, usize)
    indexed = (index.compression, int(index.compressed_size), int(index.uncompressed_size))
    if declared != indexed:
        raise ChunkError(start, f"chunk header (compression, compressed size, size) {declared} differs from its index {indexed}")
    data = view[pos : pos + data_len]
    if compression:
        dec = _DECOMPRESS.get(compression)
        if dec is None:
            raise ChunkError(start, f"unsupported chunk compression {compression!r}")
        try:
            out = memoryview(dec(data, usize))
        except Exception as exc:  # zstd.ZstdError, RuntimeError from lz4, MemoryError on absurd sizes
            raise ChunkError(start, f"{compression} decompression failed: {type(exc).__name__}: {exc}") from None
    else:
        out = data
    if len(out) != usize:
        raise ChunkError(start, f"chunk holds {len(out)} bytes of records, its header says {usize}")
    return out, crc


def check_crc(records: memoryview, crc: int, offset: int) -> None:
    """Raise :class:`ChunkError` when *crc* (nonzero: the spec's "CRC present") is not the CRC-32
    of the decompressed *records* of the chunk at *offset*."""
    if crc != 0:
        got = zlib.crc32(records)
        if got != crc:
            raise ChunkError(offset, f"chunk CRC mismatch (expected {crc:#010x}, computed {got:#010x})")


def read_chunk(view: memoryview, index: Any, validate_crc: bool = True) -> memoryview:
    """:func:`load_chunk` followed by :func:`check_crc` (when *validate_crc*): the checked records."""
    records, crc = load_chunk(view, index)
    if validate_crc:
        check_crc(records, crc, int(index.chunk_start_offset))
    return records


def chunk_messages(records: memoryview, offset: int, channels: Any, wanted: Any) -> list[tuple[int, int, int, int, memoryview]]:
    """``(log_time, offset, position, channel_id, payload view)`` of the Message records of one
    chunk whose channel is in *wanted* (all when None); *channels* is the set of known channel
    ids. One Python step per record, no per-byte work."""
    out = []
    n = len(records)
    pos = 0
    unpack_msg, unpack_rec = _MESSAGE.unpack_from, _RECORD.unpack_from
    while pos < n:
        if pos + 9 > n:
            raise ChunkError(offset, f"record header at chunk byte {pos} runs past the chunk records ({n} bytes)")
        if records[pos] == _OP_MESSAGE:
            if pos + 9 + _MESSAGE_HEAD > n:
                raise ChunkError(offset, f"message record at chunk byte {pos} runs past the chunk records")
            _op, length, cid, _seq, log_time = unpack_msg(records, pos)
            if length < _MESSAGE_HEAD:
                raise ChunkError(offset, f"message record at chunk byte {pos} is {length} bytes long (< {_MESSAGE_HEAD})")
        else:
            _op, length = unpack_rec(records, pos)
            cid = -1
        stop = pos + 9 + length
        if stop > n:
            raise ChunkError(offset, f"record at chunk byte {pos} ({length} bytes) runs past the chunk records ({n} bytes)")
        if cid >= 0:
            if cid not in channels:
                raise ChunkError(offset, f"message at chunk byte {pos} is on channel {cid}, which the summary does not list")
            if wanted is None or cid in wanted:
                out.append((log_time, offset, pos, cid, records[pos + 9 + _MESSAGE_HEAD : stop]))
        pos = stop
    return out


def _prefetched(items: list[Any], load: Callable[[Any], Any], prefetch: int) -> Iterator[Any]:
    """``load(item)`` for each item in order. With ``prefetch`` > 0, from the second item on, the
    next ``prefetch`` loads run ahead on (at most two) worker threads; the first runs on the
    calling thread, so a caller that stops after one chunk (a peek at a topic's first message)
    starts no thread and decompresses nothing it does not use. A load's exception is raised
    when its turn comes, never earlier."""
    if not items:
        return
    yield load(items[0])
    if prefetch <= 0 or len(items) < 2:
        for it in items[1:]:
            yield load(it)
        return
    from concurrent.futures import ThreadPoolExecutor

    ex = ThreadPoolExecutor(max_workers=min(prefetch, 2), thread_name_prefix="mcap-chunk")
    queue: deque = deque()
    k = 1
    try:
        while True:
            while k < len(items) and len(queue) <= prefetch:
                queue.append(ex.submit(load, items[k]))
                k += 1
            if not queue:
                return
            yield queue.popleft().result()
    finally:
        for fut in queue:
            fut.cancel()
        ex.shutdown(wait=True)


def indexed_messages(
    path: str | Path,
    summary: Any,
    channel_ids: Iterable[int] | None = None,
    *,
    validate_crcs: bool = True,
    prefetch: int = 0,
    on_error: Callable[[ChunkError, Any], None] | None = None,
) -> Iterator[tuple[int, int, memoryview]]:
    """``(channel_id, log_time_ns, payload)`` of every message of *channel_ids* (all when None), in
    the library's log-time order (see the module docstring), read through the chunk indexes of
    *summary* (an ``mcap.summary.Summary`` with ``chunk_indexes``).

    Payloads are ``memoryview`` slices of the decompressed chunk (or of the file map for an
    uncompressed chunk): valid as long as they are referenced, never copied.

    A chunk that cannot be read (header, decompression, CRC or record layout) raises
    :class:`ChunkError` naming its byte offset when its turn comes, after every message that sorts
    before it — or, with *on_error*, is passed to ``on_error(error, chunk_index)`` and left out:
    the other chunks are read and merged exactly as without it.
    """
    wanted = None if channel_ids is None else set(channel_ids)
    known = set(summary.channels)
    chunks = []
    for ci in summary.chunk_indexes:
        ids = ci.message_index_offsets
        if wanted is None or not ids or any(c in wanted for c in ids):  # no message index: must look inside
            chunks.append(ci)
    if not chunks:
        return
    chunks.sort(key=lambda c: (c.message_start_time, c.chunk_start_offset))
    with open(path, "rb") as fh:
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)  # keeps its own descriptor
    view = memoryview(mm)

    def load(ci: Any) -> tuple[Any, memoryview | ChunkError, int]:
        """First pass over a chunk's bytes, on a worker thread when prefetching (no GIL needed):
        decompression — or, for an uncompressed chunk, the CRC, which also faults its pages in.
        The CRC of a decompressed chunk is left to the consumer, who checks it while the worker
        decompresses the next chunk: the two threads then carry similar loads. A ChunkError is
        returned, not raised, so that the read-ahead goes on past a bad chunk."""
        try:
            records, crc = load_chunk(view, ci)
            if validate_crcs and not ci.compression:
                check_crc(records, crc, int(ci.chunk_start_offset))
                crc = 0
        except ChunkError as exc:
            return ci, exc, 0
        return ci, records, crc

    heap: list[tuple[int, int, int, int, memoryview]] = []
    loaded = _prefetched(chunks, load, prefetch)
    try:
        nxt = 0
        while True:
            # Open every chunk that sorts before the earliest pending message (the library's rule:
            # a chunk is keyed (message_start_time, chunk_start_offset) and precedes its messages).
            while nxt < len(chunks) and (
                not heap or (chunks[nxt].message_start_time, chunks[nxt].chunk_start_offset) < heap[0][:2]
            ):
                ci, records, crc = next(loaded)
                nxt += 1
                try:
                    if isinstance(records, ChunkError):
                        raise records
                    if validate_crcs:
                        check_crc(records, crc, int(ci.chunk_start_offset))
                    msgs = chunk_messages(records, int(ci.chunk_start_offset), known, wanted)
                except ChunkError as exc:
                    if on_error is None:
                        raise
                    on_error(exc, ci)
                    continue
                if not heap and all(msgs[i][:3] <= msgs[i + 1][:3] for i in range(len(msgs) - 1)):
                    heap = msgs  # a sorted list is a heap: the common, time-ordered chunk costs no pushes
                else:
                    for m in msgs:
                        heapq.heappush(heap, m)
            if not heap:
                return
            t, _off, _pos, cid, data = heapq.heappop(heap)
            yield cid, t, data
    finally:
        loaded.close()
        heap.clear()
        try:
            view.release()
            mm.close()
        except BufferError:  # payload views still referenced by the caller: unmapped when they go
            pass
