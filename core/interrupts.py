"""Interrupts that C code swallowed, raised again at a safe point.

A signal handler's KeyboardInterrupt is raised in whatever Python code the main thread runs at that
moment; when that is a callback from C (numba's LLVM object cache during a compilation, for one), C
prints "Exception ignored …" and goes on, and the command would run to its end instead of stopping.
The command-line handlers record every signal here as well (:func:`record`); long loops call
:func:`check` at safe points, which raises again for a signal recorded within :func:`watching`. A signal
whose first KeyboardInterrupt did get through never meets a check: the loop it interrupted is gone.
"""

from __future__ import annotations

import contextlib
import signal
from typing import Iterator

__all__ = ["record", "check", "watching"]

_pending: list[int] = []


def record(signum: int) -> None:
    """A signal arrived (called by the command's signal handlers, before they raise)."""
    _pending.append(signum)


def check() -> None:
    """Raise KeyboardInterrupt when a recorded signal has not stopped the command yet."""
    if _pending:
        raise KeyboardInterrupt(signal.Signals(_pending[0]).name)


@contextlib.contextmanager
def watching() -> Iterator[None]:
    """The span of one command: what is recorded inside is forgotten after it."""
    _pending.clear()
    try:
        yield
    finally:
        _pending.clear()
