"""A pipeline stage in a child process, fed through one queue and answering through another.

Children start from a forkserver (no thread of the caller is inherited) and run their stage with BLAS
on one thread. A failure in the child reaches the caller as an exception on its next receive: the
child's :class:`GpslamError` message as a GpslamError (bad input stays a one-line error), anything else
as a RuntimeError naming the stage. A child that dies without a word (killed, out of memory) is noticed
within half a second. :meth:`ChildProcess.close` stops it, also after an error or Ctrl-C.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import resource
import tempfile
from typing import Any, Callable, Iterator

from core.errors import GpslamError

Reply = Callable[[tuple], None]


def peak_memory_mb() -> float:
    """Peak resident memory of the calling process (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _child_main(serve: Callable[..., None], args: tuple, inbox, outbox) -> None:  # type: ignore[no-untyped-def]
    """``serve(*args, messages, reply)``: messages until the caller sends None; failures are replied as
    ("error", text, is_input_error)."""
    from slam.blas import single_blas_thread

    try:
        with single_blas_thread():
            serve(*args, iter(inbox.get, None), outbox.put)
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group; the caller reports it
        pass
    except BaseException as e:  # noqa: BLE001 — every failure is reported to the caller, which raises it
        input_error = isinstance(e, GpslamError)
        outbox.put(("error", str(e) if input_error else f"{type(e).__name__}: {e}", input_error))
    finally:
        outbox.close()
        outbox.join_thread()


class ChildProcess:
    """Runs ``serve(*args, messages: Iterator, reply: Reply)`` (a module-level function) in a child.

    Args:
        name: the stage, for error messages ("front end", "mapping").
        max_queued: messages in flight before :meth:`send` waits (0: unbounded).
    """

    _POLL_S = 0.5

    def __init__(self, serve: Callable[..., None], args: tuple, name: str, max_queued: int = 0) -> None:
        ctx = mp.get_context("forkserver")
        self.name = name
        self._inbox = ctx.Queue(maxsize=max_queued)
        self._outbox = ctx.Queue()
        self._proc = ctx.Process(target=_child_main, args=(serve, args, self._inbox, self._outbox),
                                 name=f"gpslam-{name.replace(' ', '-')}", daemon=True)
        try:
            self._proc.start()
        except OSError as exc:  # the forkserver's socket lives under TMPDIR, and AF_UNIX paths are short (108 bytes)
            if "AF_UNIX path too long" not in str(exc):
                raise
            raise GpslamError(f"the temporary folder {tempfile.gettempdir()} has too long a path for the {name} "
                              "process's socket: set TMPDIR to a shorter folder (or stage_processes: false in the "
                              "config)") from None

    def _check_alive(self) -> None:
        if not self._proc.is_alive():
            raise GpslamError(f"the {self.name} process stopped unexpectedly (exit code {self._proc.exitcode})")

    def send(self, message: Any) -> None:
        """Queue *message* (None ends the child's messages); waits while ``max_queued`` are in flight."""
        while True:
            try:
                self._inbox.put(message, timeout=self._POLL_S)
                return
            except queue.Full:
                self._check_alive()

    def receive(self, wait: bool) -> tuple | None:
        """The child's next reply; None when there is none yet and not *wait*. Raises the child's failure."""
        while True:
            try:
                msg = self._outbox.get(timeout=self._POLL_S) if wait else self._outbox.get_nowait()
                break
            except queue.Empty:
                if not wait:
                    return None
                self._check_alive()
        if msg[0] == "error":
            _, text, input_error = msg
            raise GpslamError(text) if input_error else RuntimeError(f"{self.name} process: {text}")
        return msg

    def replies(self) -> Iterator[tuple]:
        """Every reply available now (does not wait)."""
        while (msg := self.receive(wait=False)) is not None:
            yield msg

    def join(self) -> None:
        self._proc.join()

    def close(self) -> None:
        """Stop the child; idempotent."""
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join(timeout=5)
        for q in (self._inbox, self._outbox):
            q.cancel_join_thread()
            q.close()
