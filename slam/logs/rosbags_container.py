"""The part the ROS bag readers built on rosbags share: the container opened once for all passes of one
``frames()`` / ``info()`` call (:class:`~slam.logs.ros_reader.RosLogReader` makes several: topics, the static
transforms, the frames)."""

from __future__ import annotations

import abc
import contextlib
from pathlib import Path
from typing import Any, Iterator

from .base import TopicInfo
from .ros_reader import RosLogReader

__all__ = ["RosbagsReader"]


class RosbagsReader(RosLogReader):
    """A :class:`RosLogReader` whose container is a rosbags ``Reader`` (see :class:`RosLogReader` for the
    arguments); subclasses open it (:meth:`_open`, raising LogFormatError naming the file)."""

    def __init__(self, path: str | Path, topic: str | None = None, **kwargs: Any) -> None:
        super().__init__(path, topic, **kwargs)
        self._topics: list[TopicInfo] | None = None
        self._store: Any = None
        self._shared: Any = None  # an open rosbags Reader during one frames() call

    @abc.abstractmethod
    def _open(self) -> Any:
        """A new open rosbags Reader of the log."""

    @contextlib.contextmanager
    def _session(self) -> Iterator[None]:
        """Open the container (and parse its index) once for all passes of a frames() call."""
        if self._shared is not None:
            yield
            return
        self._shared = self._open()
        try:
            yield
        finally:
            reader, self._shared = self._shared, None
            reader.close()

    def topics(self) -> list[TopicInfo]:
        self._load_meta()
        assert self._topics is not None
        return list(self._topics)
