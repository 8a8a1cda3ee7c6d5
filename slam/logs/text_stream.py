"""A text log (plain, bz2 or gzip by its magic number) as numbered lines, read in blocks of about 1 MiB that a
background thread decompresses ahead (bz2 and zlib release the GIL, so decompression overlaps parsing); a
truncated or corrupt stream is a LogFormatError naming the line reached."""

from __future__ import annotations

import bz2
import gzip
import queue
import threading
import zlib
from pathlib import Path
from typing import IO, Iterator


from core.errors import LogFormatError

BLOCK_BYTES = 1 << 20


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


def line_blocks(path: Path, limit_bytes: int | None = None) -> Iterator[tuple[int, list[bytes]]]:
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
            chunk = read(BLOCK_BYTES - size)
        except Exception as exc:  # noqa: BLE001 - handed to the caller, which classifies it
            if parts:
                yield b"".join(parts)
            yield exc
            return
        if chunk:
            parts.append(chunk)
            size += len(chunk)
        if size >= BLOCK_BYTES or (not chunk and parts):
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

    def put(item: bytes | BaseException | None) -> bool:
        """Queue *item*, waiting while the queue is full; False once the consumer has stopped."""
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        for item in _plain_blocks(fh):
            if not put(item):
                return
        put(None)

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


def numbered_lines(path: Path, limit_bytes: int | None = None) -> Iterator[tuple[int, bytes]]:
    """Yield ``(line_number, line)`` one by one (see :func:`line_blocks`)."""
    for first, lines in line_blocks(path, limit_bytes):
        yield from zip(range(first, first + len(lines)), lines)
