"""Where the front end runs: inline, or in its own process beside loop closure, the back end and mapping.

The front end (per-scan odometry, keyframe selection, odometry edges) never looks at the back end, so
it can run ahead in a second process while this one closes loops, updates iSAM2 and maps — the split
of tracking from loop closing in PTAM (Klein & Murray, ISMAR 2007, §4) and ORB-SLAM (Mur-Artal et al.,
T-RO 2015, §III), and of Cartographer's local from its global SLAM. Keyframes come back in order and
the back half consumes them in the same order as inline, so both give identical results; on Intel
the ~50 s of odometry then overlap the loop closure instead of adding to it.

Both kinds share one interface: :meth:`submit` a frame, take the keyframes :meth:`ready` so far,
:meth:`finish` for the rest and a :class:`FrontEndSummary`.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import resource
import time
from dataclasses import dataclass, field
from typing import Iterator

from registration.errors import GpslamError
from registration.frame import Frame

from .config import SlamConfig
from .frontend import FrontEnd, Keyframe, OdometryEdge, ScanTrack, WheelEdge

Ready = tuple[Keyframe, OdometryEdge | None, WheelEdge | None]


@dataclass
class FrontEndSummary:
    """What the back half needs of the front end once every frame is in."""

    track: ScanTrack
    odometry_s: float  # seconds spent in the front end (in its own process, overlapping the rest)
    stats: dict = field(default_factory=dict)  # alternative ICP starts taken, wheel edges kept and left out
    peak_memory_mb: float = 0.0  # of the front-end process, when it is one (0 inline: it is the caller's)


def _summary(front: FrontEnd, odometry_s: float) -> FrontEndSummary:
    return FrontEndSummary(front.track, odometry_s,
                           {"alternative_starts": getattr(front.odometry, "alternative_starts", 0),
                            "wheel_edges": len(front.wheel_edges), "wheel_edges_dropped": front.wheel_edges_dropped})


def _new_front_end(config: SlamConfig, planar: bool) -> FrontEnd:
    """A front end keeping only its latest keyframe: the caller keeps those it takes from ``ready``."""
    from .run import make_odometry

    return FrontEnd(config, make_odometry(config, planar), keep_keyframes=False)


class InlineFrontEnd:
    """The front end in this process: each submitted frame is processed at once."""

    def __init__(self, config: SlamConfig, planar: bool) -> None:
        self._front = _new_front_end(config, planar)
        self._ready: list[Ready] = []
        self._time_s = 0.0

    def submit(self, frame: Frame) -> None:
        t0 = time.perf_counter()
        kf, edge, _ = self._front.process(frame)
        self._time_s += time.perf_counter() - t0
        if kf is not None:
            self._ready.append((kf, edge, self._front.latest_wheel_edge(kf)))

    def ready(self) -> Iterator[Ready]:
        out, self._ready = self._ready, []
        yield from out

    def finish(self) -> tuple[list[Ready], FrontEndSummary]:
        return list(self.ready()), _summary(self._front, self._time_s)

    def close(self) -> None:
        pass


def _serve(config: SlamConfig, planar: bool, inbox, outbox) -> None:  # type: ignore[no-untyped-def]
    """Child process: frames from *inbox* (None ends), ("keyframe", kf, edge, wheel) to *outbox*, then
    ("done", summary); on an error ("error", message, is_input_error)."""
    from slam.blas import single_blas_thread

    try:
        with single_blas_thread():
            front = InlineFrontEnd(config, planar)
            while (frame := inbox.get()) is not None:
                front.submit(frame)
                for item in front.ready():
                    outbox.put(("keyframe", *item))
            ready, summary = front.finish()
            summary.peak_memory_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            for item in ready:
                outbox.put(("keyframe", *item))
            outbox.put(("done", summary))
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group; the parent reports it
        pass
    except BaseException as e:  # noqa: BLE001 — every failure is reported to the parent, which raises it
        outbox.put(("error", f"{type(e).__name__}: {e}" if not isinstance(e, GpslamError) else str(e),
                    isinstance(e, GpslamError)))
    finally:
        outbox.close()
        outbox.join_thread()


class FrontEndProcess:
    """The front end in a child process (forkserver start: no threads of this one are inherited).

    Args:
        config: the run's configuration.
        planar: 2D laser log or 3D.
        max_queued: frames in flight before :meth:`submit` waits for the child (bounds memory on 3D logs).
    """

    _POLL_S = 0.5

    def __init__(self, config: SlamConfig, planar: bool, max_queued: int = 64) -> None:
        ctx = mp.get_context("forkserver")
        self._inbox = ctx.Queue(maxsize=max_queued)
        self._outbox = ctx.Queue()
        self._proc = ctx.Process(target=_serve, args=(config, planar, self._inbox, self._outbox),
                                 name="gpslam-front-end", daemon=True)
        self._proc.start()
        self._summary: FrontEndSummary | None = None

    def _check_alive(self) -> None:
        if not self._proc.is_alive():
            raise GpslamError(f"the front-end process stopped unexpectedly (exit code {self._proc.exitcode})")

    def submit(self, frame: Frame) -> None:
        """Queue *frame*; waits while the child is ``max_queued`` frames behind."""
        while True:
            try:
                self._inbox.put(frame, timeout=self._POLL_S)
                return
            except queue.Full:
                self._check_alive()

    def _handle(self, msg: tuple) -> Ready | None:
        kind = msg[0]
        if kind == "keyframe":
            return msg[1], msg[2], msg[3]
        if kind == "done":
            self._summary = msg[1]
            return None
        _, text, input_error = msg
        raise GpslamError(text) if input_error else RuntimeError(f"front-end process: {text}")

    def ready(self) -> Iterator[Ready]:
        """Keyframes the child has finished so far (does not wait)."""
        while True:
            try:
                msg = self._outbox.get_nowait()
            except queue.Empty:
                return
            item = self._handle(msg)
            if item is not None:
                yield item

    def finish(self) -> tuple[list[Ready], FrontEndSummary]:
        """Waits for the child to process every submitted frame: the remaining keyframes and the summary."""
        self.submit(None)  # type: ignore[arg-type]
        out: list[Ready] = []
        while self._summary is None:
            try:
                msg = self._outbox.get(timeout=self._POLL_S)
            except queue.Empty:
                self._check_alive()
                continue
            item = self._handle(msg)
            if item is not None:
                out.append(item)
        self._proc.join()
        return out, self._summary

    def close(self) -> None:
        """Stop the child (also after an error or Ctrl-C); idempotent."""
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join(timeout=5)
        for q in (self._inbox, self._outbox):
            q.cancel_join_thread()
            q.close()


def start_front_end(config: SlamConfig, planar: bool) -> InlineFrontEnd | FrontEndProcess:
    """The front end as ``config.front_end_process`` asks: in a child process or inline."""
    return FrontEndProcess(config, planar) if config.front_end_process else InlineFrontEnd(config, planar)
