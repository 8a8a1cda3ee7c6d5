"""SIGINT, SIGTERM and SIGHUP end a command the same way.

Python's default for SIGTERM and SIGHUP is to die at once: no ``finally`` runs, so the stage processes,
multiprocessing's resource tracker and forkserver, its ``/tmp/pymp-*`` folder and a half-written
``.<out>.*.part`` folder were left behind. Inside :func:`terminations` both signals raise
:class:`Terminated`, a ``KeyboardInterrupt``, in the main thread instead: every clean-up written for
Ctrl-C (closing the stage processes, removing temporaries, holding the signal back while a finished
folder is moved in) then runs for them too, and the command exits with 128 + the signal number
(130 SIGINT, 143 SIGTERM, 129 SIGHUP), as a shell reports a process killed by it. SIGINT raises
KeyboardInterrupt as Python's own handler does, but through the same handler, so that every signal is also
recorded in :mod:`core.interrupts`: a KeyboardInterrupt that C code swallowed is raised again at the
pipeline's next frame.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

from core import interrupts
from core.atomic import HELD_SIGNALS

__all__ = ["Terminated", "terminations", "ignore_held_signals", "exit_code", "message"]

_TERMINATING = (signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread (:attr:`signum`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextlib.contextmanager
def terminations() -> Iterator[list[int]]:
    """Within the block SIGINT raises KeyboardInterrupt and SIGTERM and SIGHUP raise :class:`Terminated`, each
    recorded (:mod:`core.interrupts`); yields the list of the signals that did (the first one decides the exit
    code). Outside the main thread nothing changes."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def handler(signum: int, frame) -> None:  # type: ignore[no-untyped-def]
        received.append(signum)
        interrupts.record(signum)
        if len(received) == 1:  # once: a second signal must not interrupt the clean-up of the first
            raise KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)

    previous = {}
    for s in (signal.SIGINT, *_TERMINATING):
        if signal.getsignal(s) is not signal.SIG_IGN:  # nohup's ignored SIGHUP stays ignored
            previous[s] = signal.signal(s, handler)
    try:
        with interrupts.watching():
            yield received
    finally:
        for s, h in previous.items():
            if signal.getsignal(s) is handler:  # not when ignore_held_signals has taken over meanwhile
                signal.signal(s, h)


def ignore_held_signals() -> None:
    """Ignore SIGINT, SIGTERM and SIGHUP for the rest of the process: once a command has finished (or printed
    its error), a late signal can neither raise in an atexit hook nor, once the interpreter's shutdown has
    put the default handlers back (it leaves ignored ones alone), kill it as a silent exit -2 or -15.
    (Ignored, not blocked: a signal mask is per thread, and other threads would still take the signal.)"""
    for s in HELD_SIGNALS:
        signal.signal(s, signal.SIG_IGN)


def exit_code(received: list[int]) -> int:
    """128 + the signal that ended the command (SIGINT when none was recorded)."""
    return 128 + int(received[0] if received else signal.SIGINT)


def message(received: list[int]) -> str:
    """The one line that says why the command stopped."""
    if not received or received[0] == signal.SIGINT:
        return "interrupted"
    return f"terminated ({signal.Signals(received[0]).name})"
