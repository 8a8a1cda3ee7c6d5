"""The reader interface every log format implements."""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Mapping

from core.errors import LogFormatError
from core.frame import Frame

#: Called with the error of each corrupt record a reader skipped (see :meth:`LogReader.frames`).
SkipHandler = Callable[[LogFormatError], None]

#: The key of :func:`lost` for a record of unknown kind (a garbled line: it may have been a scan).
UNKNOWN = "?"


def lost(error: LogFormatError, records: Mapping[str, int] | None) -> LogFormatError:
    """Mark what skipping *error* cost: records per topic (or CARMEN tag, :data:`UNKNOWN` for a record of
    unknown kind), or None when not known (a cut stream: whatever followed). Returns *error*."""
    error.lost = None if records is None else dict(records)  # type: ignore[attr-defined]
    return error


def counting(on_skip: SkipHandler, sensor: str) -> SkipHandler:
    """*on_skip* behind a handler that sets each error's ``records`` (how many were lost; None when not
    known) and ``scans`` (how many of them were scans of *sensor*; None when not known) from :func:`lost`
    (an error without it is one record of unknown kind)."""

    def report(error: LogFormatError) -> None:
        recs = getattr(error, "lost", {UNKNOWN: 1})
        error.records = None if recs is None else sum(recs.values())  # type: ignore[attr-defined]
        error.scans = None if recs is None or UNKNOWN in recs else recs.get(sensor, 0)  # type: ignore[attr-defined]
        on_skip(error)

    return report


@dataclass
class TopicInfo:
    """One stream of a log: its name, ROS type (or CARMEN message tag) and message count."""

    name: str
    msgtype: str
    count: int


@dataclass
class LogInfo:
    """What ``slam info`` prints about a log (read by streaming the whole file once)."""

    path: str
    format: str  # "carmen", "mcap", "ros1", "kitti"
    sensor_topic: str  # the topic whose messages become frames
    scans: int
    beams_per_scan: int | None  # 2D: beams per scan (max); 3D: median points per cloud
    dimension: int  # 2 or 3
    start: float | None
    end: float | None
    has_odometry: bool
    has_ground_truth: bool
    topics: list[TopicInfo] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        if self.start is None or self.end is None:
            return 0.0
        return self.end - self.start


class LogReader(abc.ABC):
    """A log that yields :class:`~core.frame.Frame` objects in time order, streaming.

    Implementations keep memory constant in the log length: they hold at most the current
    message plus small interpolation state (odometry, transforms).
    """

    format: str = ""

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        self.path = Path(path)
        self.topic = topic

    @abc.abstractmethod
    def frames(self, on_skip: SkipHandler | None = None) -> Iterator[Frame]:
        """Yield every scan of the chosen sensor topic as a Frame.

        Args:
            on_skip: None (default): the first corrupt record raises :class:`LogFormatError`
                naming the file and position. Given: each corrupt record (a line, a message, a
                chunk, a scan file) is passed to ``on_skip`` as that same error and reading goes
                on after it; a corrupt stretch the format cannot resynchronise after (a truncated
                compressed stream, a cut container) is reported once and ends the frames.
        """

    def has_ground_truth(self) -> bool:
        """Whether the frames carry a ``ground_truth`` pose (a cheap check, not a full pass)."""
        return False

    @abc.abstractmethod
    def info(self) -> LogInfo:
        """Summarise the log (streams it once)."""

    def scan_count_hint(self) -> int | None:
        """The number of scans when the log's own index tells it without reading the log (a progress bar's
        total), else None."""
        return None

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()


@dataclass
class SkipLog:
    """A :data:`SkipHandler` that keeps what was skipped: ``reader.frames(on_skip=log)``."""

    errors: list[LogFormatError] = field(default_factory=list)

    def __call__(self, error: LogFormatError) -> None:
        self.errors.append(error)

    def __len__(self) -> int:
        return len(self.errors)

    def lines(self) -> list[str]:
        """One ``file:pos: what`` line per skip."""
        return [" ".join(str(e).split()) for e in self.errors]

    def records(self) -> int | None:
        """Records lost (lines, messages, files), None when a skip lost an unknown number (a cut stream)."""
        counts = [getattr(e, "records", 1) for e in self.errors]
        return None if any(c is None for c in counts) else sum(counts)

    def scans(self) -> tuple[int, bool]:
        """``(scans lost, exact)``: the scans known to be lost, and whether every skip said how many."""
        counts = [getattr(e, "scans", None) for e in self.errors]
        return sum(c for c in counts if c is not None), all(c is not None for c in counts)
