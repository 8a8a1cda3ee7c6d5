"""Where the front end runs: inline, or in its own process beside loop closure, the back end and mapping.

The front end (per-scan odometry, keyframe selection, odometry edges) never looks at the back end, so
it can run ahead in a second process while this one closes loops, updates iSAM2 and maps — the split
of tracking from mapping and loop closing in PTAM (Klein & Murray, ISMAR 2007) and ORB-SLAM (Mur-Artal et al.,
T-RO 2015, §III), and of Cartographer's local from its global SLAM. Keyframes come back in order and
the back half consumes them in the same order as inline, so both give identical results; the odometry's
time then overlaps the loop closure instead of adding to it.

Both kinds share one interface: :meth:`submit` a frame, take the keyframes :meth:`ready` so far,
:meth:`finish` for the rest and a :class:`FrontEndSummary`. :func:`run_front_end` is the one frame loop
over them, used by ``slam run`` (:func:`slam.pipeline.run.run_slam`), ``slam loops`` and the loop replay
(:func:`slam.pipeline.loop_replay.record_front_end`). Stage processes are the default: on two cores a run
is about a quarter faster with them, with byte-identical outputs (measured in docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

from core import interrupts
from core.errors import GpslamError
from core.frame import Frame

from .beam_times import read_beam_time_order
from .child import ChildProcess, Reply, peak_memory_mb
from .config import SlamConfig
from .frontend import FrontEnd, Keyframe, OdometryEdge, ScanTrack, WheelEdge
from .odometry_source import make_odometry

Ready = tuple[Keyframe, OdometryEdge | None, WheelEdge | None]


@dataclass
class FrontEndSummary:
    """What the back half needs of the front end once every frame is in."""

    track: ScanTrack
    odometry_s: float  # seconds spent in the front end (in its own process, overlapping the rest)
    stats: dict = field(default_factory=dict)  # alternative ICP starts taken, wheel edges kept and left out, slid edges
    peak_memory_mb: float = 0.0  # of the front-end process, when it is one (0 inline: it is the caller's)


def _summary(front: FrontEnd, odometry_s: float) -> FrontEndSummary:
    stats = {"alternative_starts": getattr(front.odometry, "alternative_starts", 0),
             "unguided_escalations": getattr(front.odometry, "unguided_escalations", 0),
             "unguided_contradicted": getattr(front.odometry, "unguided_contradicted", 0),
             "wheel_edges": len(front.wheel_edges), "wheel_edges_dropped": front.wheel_edges_dropped,
             "slid_edges": front.slid_edges, "max_slide_m": round(front.max_slide_m, 4)}
    if front.sweep.pairs:  # the front end read the beam times' order itself (not before the run)
        stats |= {"beam_times": front.sweep.verdict or "undecided", "beam_time_pairs": front.sweep.pairs,
                  "beam_time_costs_m": {k: round(v / max(front.sweep.pairs, 1), 5) for k, v in front.sweep.costs.items()}}
    cal = front.wheel_calibration
    if cal is not None:
        stats |= {"wheel_noise_scale_translation": round(cal.scale_translation, 4),
                  "wheel_noise_scale_rotation": round(cal.scale_rotation, 4), "wheel_calibration_samples": cal.samples}
    return FrontEndSummary(front.track, odometry_s, stats)


def _new_front_end(config: SlamConfig, planar: bool) -> FrontEnd:
    """A front end keeping only its latest keyframe: the caller keeps those it takes from ``ready``."""
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


def _serve(config: SlamConfig, planar: bool, batches: Iterator[list[Frame]], reply: Reply) -> None:
    """Child: ("keyframe", kf, edge, wheel) for each keyframe of the frames of *batches*, then ("done", summary)."""
    front = InlineFrontEnd(config, planar)
    for batch in batches:
        for frame in batch:
            front.submit(frame)
            for item in front.ready():
                reply(("keyframe", *item))
    ready, summary = front.finish()
    summary.peak_memory_mb = peak_memory_mb()
    for item in ready:
        reply(("keyframe", *item))
    reply(("done", summary))


class FrontEndProcess:
    """The front end in a child process (:class:`~slam.pipeline.child.ChildProcess`).

    Args:
        config: the run's configuration.
        planar: 2D laser log or 3D.
        max_queued: batches of frames in flight before :meth:`submit` waits for the child (bounds memory on
            3D logs, where a scan of ≥ ``BATCH_POINTS`` points is a batch of its own).
    """

    #: frames sent to the child in one message: a planar scan is ~7 kB, and each message costs the caller a
    #: lock and a wake-up of its queue's feeder thread (~0.15 ms, 2 s of a 13,631-scan run on the critical path)
    BATCH_FRAMES = 8
    BATCH_POINTS = 50_000

    def __init__(self, config: SlamConfig, planar: bool, max_queued: int = 64) -> None:
        self._child = ChildProcess(_serve, (config, planar), "front-end", max_queued)
        self._summary: FrontEndSummary | None = None
        self._batch: list[Frame] = []
        self._batch_points = 0
        self._sent = False  # a batch went out since ready() last looked at the replies

    def submit(self, frame: Frame) -> None:
        """Queue *frame* (sent with the next ones as one batch); waits while the child is ``max_queued`` batches
        behind."""
        self._batch.append(frame)
        self._batch_points += len(frame.points)
        if len(self._batch) >= self.BATCH_FRAMES or self._batch_points >= self.BATCH_POINTS:
            self._flush()

    def _flush(self) -> None:
        if self._batch:
            self._child.send(self._batch)
            self._batch, self._batch_points = [], 0
            self._sent = True

    def _keyframe(self, msg: tuple) -> Ready | None:
        if msg[0] == "done":
            self._summary = msg[1]
            return None
        return msg[1], msg[2], msg[3]

    def ready(self) -> Iterator[Ready]:
        """Keyframes the child has finished so far (does not wait). The replies are looked at once per batch
        sent, not per frame: an empty look costs the caller ~0.1 ms (1.7 s of a 13,631-scan run on the
        critical path), and the keyframes come out in the same order either way."""
        if not self._sent:
            return
        self._sent = False
        for msg in self._child.replies():
            if (item := self._keyframe(msg)) is not None:
                yield item

    def finish(self) -> tuple[list[Ready], FrontEndSummary]:
        """Waits for the child to process every submitted frame: the remaining keyframes and the summary."""
        self._flush()
        self._child.send(None)
        out: list[Ready] = []
        while self._summary is None:
            if (item := self._keyframe(self._child.receive(wait=True))) is not None:  # type: ignore[arg-type]
                out.append(item)
        self._child.join()
        return out, self._summary

    def close(self) -> None:
        """Stop the child (also after an error or Ctrl-C); idempotent."""
        self._child.close()


def run_front_end(frames: Iterable[Frame], config: SlamConfig, on_keyframe: Callable[[Keyframe, OdometryEdge | None,
                  WheelEdge | None], None], on_scan: Callable[[int, Frame], None] | None = None,
                  processes: bool | None = None) -> FrontEndSummary:
    """The frame loop every command shares (``slam run``, ``slam loops``, the loop replay): each frame (up to
    ``config.max_scans``) into the front end — in its own process when *processes* (default
    ``config.stage_processes``), else here — each keyframe to *on_keyframe* as soon as it is ready, in
    order, and ``on_scan(scans read, frame)`` after each frame; returns the front end's summary once every
    keyframe is out. The front end is stopped on the way out, also on an error or Ctrl-C. Raises
    GpslamError when the frames hold no scan."""
    use_process = config.stage_processes if processes is None else processes
    front: InlineFrontEnd | FrontEndProcess | None = None
    source = iter(frames)
    config, head, beam_time_stats = read_beam_time_order(source, config)
    try:
        n = 0
        for frame in itertools.chain(head, source):
            interrupts.check()  # a Ctrl-C that C code swallowed stops the run here
            if config.max_scans is not None and n >= config.max_scans:
                break
            if front is None:
                front = FrontEndProcess(config, frame.is_planar) if use_process else InlineFrontEnd(config, frame.is_planar)
            front.submit(frame)
            n += 1
            for item in front.ready():
                on_keyframe(*item)
            if on_scan is not None:
                on_scan(n, frame)
        if front is None:
            raise GpslamError("the log yielded no scans")
        rest, summary = front.finish()
        for item in rest:
            on_keyframe(*item)
        summary.stats |= beam_time_stats
        return summary
    finally:
        if front is not None:
            front.close()
