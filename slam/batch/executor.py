"""Independent tasks on Ray: a local Ray instance by default, an existing cluster with an address.

The one executor of ``slam batch`` (a task per log × setting) and ``slam loops --parallel`` (a task per
loop-closure setting); no process pool, queue or scheduler of our own. Ray is imported here, when an
executor is entered, and nowhere else.

* :class:`RayExecutor` connects on ``__enter__``: to ``address`` when given (``"auto"``, ``host:6379``,
  ``ray://host:10001``), else to a Ray this process is already connected to (a test, a notebook),
  else it starts a local instance (as many CPUs as the machine has, no dashboard, usage statistics
  off: nothing leaves the machine) and stops it again on ``__exit__``.
* :meth:`RayExecutor.map` runs ``fn(*shared, *item)`` for every item as a task of ``cpus_per_task``
  CPUs, the *shared* arguments put into the object store once. Results come back in item order.
  A task that raised or whose worker died (killed, out of memory) is a :class:`TaskFailure` there,
  or raised again here (``failures="raise"``, the exception the task raised).
* Ctrl-C in :meth:`map` cancels every outstanding task (queued ones never start, running ones get a
  KeyboardInterrupt so that their atomic writes clean up), waits up to ``cancel_grace_s`` for them, and
  re-raises. Tasks are not retried: a run that fails, fails once.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from core.errors import ConfigError

__all__ = ["TaskFailure", "RayExecutor"]

_CONNECT_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class TaskFailure:
    """A task that raised, or whose worker died: one line saying why."""

    message: str


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _check_reachable(address: str) -> None:
    """ConfigError unless something listens at ``HOST:PORT`` (or ``ray://HOST:PORT``) within a few seconds:
    Ray itself retries an unreachable address for minutes and then exits the process."""
    if address == "auto":
        return
    hostport = address.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ConfigError(f"--address {address}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=_CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise ConfigError(f"--address {address}: no Ray cluster answers there ({exc.strerror or exc})") from None


class RayExecutor:
    """Runs tasks on Ray (module docstring). Use as a context manager.

    Args:
        address: a running cluster to connect to; None for the one this process is connected to, else a
            local instance started here.
        cancel_grace_s: on Ctrl-C, how long running tasks may take to stop and clean up.
    """

    def __init__(self, address: str | None = None, cancel_grace_s: float = 20.0) -> None:
        self.address = address
        self.cancel_grace_s = cancel_grace_s
        self.submitted = 0  # tasks submitted through this executor
        self.start_s = 0.0  # seconds spent connecting (starting a local instance included)
        self.stop_s = 0.0  # seconds spent disconnecting (stopping a local instance included)
        self._owned = False
        self._ray: Any = None

    def __enter__(self) -> "RayExecutor":
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing is sent anywhere
        t0 = time.perf_counter()
        import ray

        self._ray = ray
        if self.address is None and ray.is_initialized():
            self._owned = False
        else:
            kwargs: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.ERROR}
            if self.address is None:
                kwargs["include_dashboard"] = False
            else:
                _check_reachable(self.address)
            try:
                ray.init(address=self.address, **kwargs)
            except (Exception, SystemExit) as exc:  # Ray exits the process when it cannot reach its cluster
                where = "a local Ray" if self.address is None else f"--address {self.address}"
                raise ConfigError(f"{where}: Ray did not start: {_one_line(f'{type(exc).__name__}: {exc}')}") from None
            self._owned = True
        self.start_s = time.perf_counter() - t0
        return self

    def __exit__(self, *exc: object) -> None:
        t0 = time.perf_counter()
        if self._owned and self._ray is not None:
            self._ray.shutdown()
        self._ray = None
        self.stop_s = time.perf_counter() - t0

    @property
    def cluster_cpus(self) -> float:
        """CPUs of the whole cluster."""
        return float(self._ray.cluster_resources().get("CPU", 0.0))

    def busy_cpus(self) -> float:
        """CPUs in use by tasks right now (this batch's and any other work on the cluster)."""
        total = self._ray.cluster_resources().get("CPU", 0.0)
        return float(total - self._ray.available_resources().get("CPU", 0.0))

    def map(self, fn: Callable[..., Any], shared: tuple = (), items: Sequence[tuple] = (),
            on_done: Callable[[int, Any], None] | None = None, *, cpus_per_task: float = 1.0,
            on_tick: Callable[[int], None] | None = None, failures: str = "return") -> list[Any]:
        """``[fn(*shared, *item) for item in items]`` as Ray tasks, in item order (module docstring).

        Args:
            fn: a module-level function (the workers import it by name).
            on_done: called here with (item index, result) as each task finishes.
            cpus_per_task: the CPUs Ray reserves for each task.
            on_tick: called about twice a second with the number of outstanding tasks.
            failures: ``"return"`` a :class:`TaskFailure` in the failed item's place, or ``"raise"`` the
                task's exception (a worker that died: RuntimeError) after cancelling the rest.
        """
        if self._ray is None:
            raise RuntimeError("RayExecutor.map outside its with block")
        ray = self._ray
        if not items:
            return []
        remote = ray.remote(num_cpus=cpus_per_task, max_retries=0)(fn)
        shared_refs = tuple(ray.put(x) for x in shared)
        refs = [remote.remote(*shared_refs, *item) for item in items]
        self.submitted += len(refs)
        index = {ref: i for i, ref in enumerate(refs)}
        results: list[Any] = [None] * len(refs)
        pending = list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
                for ref in done:
                    i = index[ref]
                    results[i] = self._result(ref)
                    if isinstance(results[i], TaskFailure) and failures == "raise":
                        self._raise(ref, pending)
                    if on_done is not None:
                        on_done(i, results[i])
                if on_tick is not None:
                    on_tick(len(pending))
        except KeyboardInterrupt:
            self._cancel(pending)
            raise
        return results

    def _result(self, ref: Any) -> Any:
        from ray.exceptions import RayError, RayTaskError

        try:
            return self._ray.get(ref)
        except RayTaskError as exc:
            cause = exc.cause if exc.cause is not None else exc
            return TaskFailure(_one_line(f"{type(cause).__name__}: {cause}"))
        except RayError as exc:  # the worker died (killed, out of memory), the node was lost, ...
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            return TaskFailure(_one_line(f"{type(exc).__name__}: {first}"))

    def _raise(self, ref: Any, pending: list[Any]) -> None:
        from ray.exceptions import RayTaskError

        self._cancel(pending)
        try:
            self._ray.get(ref)
        except RayTaskError as exc:
            if exc.cause is not None:
                raise exc.cause from None
            raise RuntimeError(_one_line(str(exc))) from None
        except Exception as exc:  # noqa: BLE001 — a lost worker: say what Ray said, in one line
            raise RuntimeError(_one_line(str(exc).strip().splitlines()[0] if str(exc).strip() else repr(exc))) from None

    def _cancel(self, pending: list[Any]) -> None:
        """Cancel *pending* tasks and give the running ones ``cancel_grace_s`` to unwind."""
        if not pending:
            return
        # Only tasks still running: a cancel that races with the task's own completion reply aborts the driver
        # (Ray 2.60: "Check failed: ... Tried to complete task that was not pending"; the race of
        # ray-project/ray#54798), so the finished ones are left alone and the window shrinks to the time
        # between this wait and the cancel.
        try:
            _, running = self._ray.wait(pending, num_returns=len(pending), timeout=0)
        except BaseException:  # noqa: BLE001 — a second Ctrl-C: cancel them all
            running = pending
        for ref in running:
            try:
                self._ray.cancel(ref, force=False)
            except Exception:  # noqa: BLE001 — already finished or gone
                pass
        try:
            self._ray.wait(pending, num_returns=len(pending), timeout=self.cancel_grace_s)
        except BaseException:  # noqa: BLE001 — a second Ctrl-C while waiting: stop waiting
            pass
