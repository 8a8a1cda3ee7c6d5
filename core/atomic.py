"""Atomic file output: write to a temporary sibling, rename on success.

A failed or interrupted run therefore never leaves a half-written file under its final name.
``os.replace`` is atomic on POSIX when source and target are on the same file system, which
is why the temporary file is created in the target's own directory. Ctrl-C (SIGINT), SIGTERM and
SIGHUP are held back while a finished directory is moved into place and while temporaries are removed,
so a signal leaves either the complete new outputs or the previous ones, and no temporary.

Output paths are checked before any work (:func:`check_output_file`, :func:`check_output_dir`), and a
failure to write (a full disk, a read-only file system) is an :class:`~core.errors.OutputError`
naming the target, so the CLI prints one line.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import secrets
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import IO, Iterator, Sequence

from .errors import OutputError

#: The signals that end a run cleanly (as Ctrl-C does) and that a move into place holds back.
HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: A write failure that is the output's fault (the OSError may carry no file name).
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG, errno.EACCES, errno.EPERM})


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold SIGINT (Ctrl-C), SIGTERM and SIGHUP back for the duration of the block, then deliver them.

    A signal that arrives inside the block is recorded and re-delivered to its previous handler once the
    block is done (Python's default SIGINT handler then raises KeyboardInterrupt there; the CLI's handler
    of SIGTERM and SIGHUP does the same). Outside the main thread signal handlers cannot be changed; the
    block then runs unprotected.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: received.append(signum)) for s in HELD_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(received):
            handler = previous[s]
            if callable(handler):
                handler(s, None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), s)


def _remove(path: Path) -> None:
    """Delete a temporary file or folder (missing is fine), not interruptible by a signal."""
    with sigint_deferred():
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()


def _output_error(exc: OSError, target: Path, tmp: Path | None = None) -> OutputError | None:
    """The OutputError for a write failure of *target* (through its temporary *tmp*), or None when *exc*
    is not about the output."""
    name = str(exc.filename) if exc.filename is not None else ""
    ours = exc.errno in _WRITE_ERRNOS or name == str(target) or (tmp is not None and name.startswith(str(tmp)))
    return OutputError(target, None, f"cannot write: {exc.strerror or exc}") if ours else None


def _writable_ancestor(target: Path) -> None:
    """Raise OutputError unless the nearest existing ancestor folder of *target* is a folder in which a new
    entry can be created (tried, not guessed from permission bits: root ignores them, a read-only file system
    does not)."""
    a = target.parent
    while not a.exists() and a != a.parent:
        a = a.parent
    if not a.is_dir():
        raise OutputError(target, None, f"{a} is a file, not a folder")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".gpslam-check.", dir=a))
    except OSError as exc:
        raise OutputError(target, None, f"cannot write in {a}: {exc.strerror or exc}") from None


def check_output_file(path: str | os.PathLike[str]) -> None:
    """Raise OutputError unless *path* can be written as a regular file (new, or replacing a regular file)."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(p, None, "is a folder, expected a file name")
    if p.exists() and not p.is_file():
        raise OutputError(p, None, "exists and is not a regular file")
    _writable_ancestor(p)


def _check_replaceable(p: Path, marker: Sequence[str]) -> None:
    """An existing folder may be replaced only when it is empty or holds every *marker* file (an earlier
    output of the same command): a folder of other things is never deleted."""
    if not p.is_dir():
        raise OutputError(p, None, "exists and is not a folder")
    if any(p.iterdir()) and not all((p / m).is_file() for m in marker):
        raise OutputError(p, None, f"exists and is not an earlier output of this command (it has no "
                                   f"{' or '.join(marker)}); not replacing it: choose another folder or remove it")


def check_output_dir(path: str | os.PathLike[str], marker: Sequence[str]) -> None:
    """Raise OutputError unless *path* can become an output folder: new, empty, or an earlier output holding
    every *marker* file (it will be replaced whole), with a writable parent."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        _check_replaceable(p, marker)
    _writable_ancestor(p)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside *path*; on normal exit rename it to *path*, else delete it.

    Raises OutputError when the temporary cannot be created or written (full disk, read-only)."""
    target = Path(path)
    tmp_path: Path | None = None
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
        os.close(fd)
        tmp_path = Path(tmp)
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
        yield tmp_path
        os.replace(tmp_path, target)
    except OSError as exc:
        if tmp_path is not None:
            _remove(tmp_path)
        err = _output_error(exc, target, tmp_path)
        if err is None:
            raise
        raise err from None
    except BaseException:
        if tmp_path is not None:
            _remove(tmp_path)
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "w", **kwargs) -> Iterator[IO]:
    """``open()`` that only creates *path* once the ``with`` block finished without an exception."""
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as fh:
        yield fh


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the system
    or file system has no such call."""
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _replace_folder(new: Path, target: Path) -> Path:
    """Put folder *new* in the place of the existing folder *target*; return where the old one now is (to be
    removed). One atomic exchange where the system has it, else two renames (the old folder is moved back
    if the second fails)."""
    if _exchange(new, target):
        return new
    old = target.with_name(f".{target.name}.{secrets.token_hex(4)}.old")
    os.rename(target, old)
    try:
        os.rename(new, target)
    except OSError:
        os.rename(old, target)
        raise
    return old


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike[str], marker: Sequence[str] | None = None) -> Iterator[Path]:
    """Yield a temporary directory beside *path*; on success it becomes *path*, replacing it whole.

    A new *path* is the temporary directory renamed (one atomic step). An existing *path* is replaced in one
    atomic exchange (nothing of the earlier output survives: a rerun never merges into it), but only when it
    is empty or holds every *marker* file (default: every top-level name of the new output), i.e. is an
    earlier output of the same command; anything else raises OutputError and stays as it was. Signals are
    held back while the folder is moved into place; the old folder and any temporary are removed.
    """
    target = Path(path)
    tmp: Path | None = None
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent))
        os.chmod(tmp, 0o777 & ~_umask())
        yield tmp
        with sigint_deferred():
            if target.exists() or target.is_symlink():
                _check_replaceable(target, marker if marker is not None else [p.name for p in tmp.iterdir()])
                tmp = _replace_folder(tmp, target)
            else:
                os.rename(tmp, target)
                tmp = None
    except OSError as exc:
        err = _output_error(exc, target, tmp)
        if err is None:
            raise
        raise err from None
    finally:
        if tmp is not None:
            _remove(tmp)
