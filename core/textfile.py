"""Lines of a text data file (g2o, TORO, TUM, KITTI, relations, stamp lists), decoded as UTF-8.

Every failure is a project error naming the file and, for a byte that is not UTF-8, the line and
column, so a binary or damaged file gives one line instead of a ``UnicodeDecodeError`` traceback.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

from .errors import InputFileError, LogFormatError

__all__ = ["text_lines"]


def text_lines(path: str | os.PathLike[str], error: type[InputFileError] = LogFormatError,
               expected: str = "a text file") -> Iterator[tuple[int, str]]:
    """``(line number from 1, line without its end-of-line)`` of every line of *path*.

    Raises *error* ``(path, where, what)``: the file is missing, a directory (*expected* says what
    should have been given), unreadable, or has a byte that is not UTF-8 (``line N``, with the column).
    """
    p = Path(path)
    try:
        fh = open(p, "rb")
    except FileNotFoundError:
        raise error(p, None, "no such file") from None
    except IsADirectoryError:
        raise error(p, None, f"is a directory, expected {expected}") from None
    except OSError as exc:
        raise error(p, None, f"cannot read: {exc.strerror or exc}") from None
    with fh:
        lineno = 0
        try:
            for lineno, raw in enumerate(fh, 1):
                try:
                    line = raw.decode("utf-8")
                except UnicodeDecodeError as exc:
                    raise error(p, f"line {lineno}", f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at column "
                                                     f"{exc.start + 1}") from None
                yield lineno, line.rstrip("\r\n")
        except OSError as exc:
            raise error(p, f"line {lineno + 1}", f"cannot read: {exc.strerror or exc}") from None
