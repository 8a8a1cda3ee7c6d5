"""Atomic file output: write to a temporary sibling, rename on success.

A failed or interrupted run therefore never leaves a half-written file under its final name.
``os.replace`` is atomic on POSIX when source and target are on the same file system, which
is why the temporary file is created in the target's own directory. Ctrl-C (SIGINT) is held
back while a finished directory is moved into place and while temporaries are removed, so an
interrupt leaves either the complete new outputs or the previous ones, and no temporary.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import IO, Iterator


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold SIGINT (Ctrl-C) back for the duration of the block, then deliver it.

    A SIGINT that arrives inside the block is recorded and re-delivered to the previous handler
    once the block is done (Python's default handler then raises KeyboardInterrupt there).
    Outside the main thread signal handlers cannot be changed; the block then runs unprotected.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if received:
            if callable(previous):
                previous(signal.SIGINT, None)
            elif previous == signal.SIG_DFL:
                os.kill(os.getpid(), signal.SIGINT)


def _remove(path: Path) -> None:
    """Delete a temporary file or folder (missing is fine), not interruptible by Ctrl-C."""
    with sigint_deferred():
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside *path*; on normal exit rename it to *path*, else delete it."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except BaseException:
        _remove(tmp_path)
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "w", **kwargs) -> Iterator[IO]:
    """``open()`` that only creates *path* once the ``with`` block finished without an exception."""
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as fh:
        yield fh


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary directory beside *path*; on success move its files into *path*.

    A new *path* is the temporary directory renamed (one atomic step). Into an existing *path*,
    files with the same names are replaced one by one with ``os.replace`` after everything was
    written, files with other names are kept; Ctrl-C is held back until all are moved.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent))
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
        with sigint_deferred():
            if not target.exists():
                with contextlib.suppress(OSError):  # e.g. created meanwhile: merge below
                    os.rename(tmp, target)
                    return
            target.mkdir(parents=True, exist_ok=True)
            for item in sorted(tmp.rglob("*")):
                rel = item.relative_to(tmp)
                dest = target / rel
                if item.is_dir():
                    dest.mkdir(parents=True, exist_ok=True)
                else:
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(item, dest)
    finally:
        _remove(tmp)
