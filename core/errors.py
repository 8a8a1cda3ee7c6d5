"""Project exceptions. Every error a user can cause derives from :class:`GpslamError`.

The CLI prints ``error: <message>`` on one line and exits with status 2 for any of them, so the
message must name the file and the position (line, byte offset or message index) and say what
was expected.
"""

from __future__ import annotations


class GpslamError(Exception):
    """Base class of every error caused by bad input or bad configuration."""


class GeometryError(GpslamError, ValueError):
    """A geometric quantity is malformed (wrong shape, zero quaternion, not a rotation)."""


class DegenerateInputError(GpslamError, ValueError):
    """Point sets that do not determine a unique rigid transform (too few pairs, collinear)."""


class InputFileError(GpslamError):
    """A file that cannot be used; *where* is e.g. ``line 12`` or ``message 7``."""

    def __init__(self, path: object, where: str | None, what: str) -> None:
        self.path = str(path)
        self.where = where
        self.what = what
        loc = f"{self.path}:{where}" if where else self.path
        super().__init__(f"{loc}: {what}")


class LogFormatError(InputFileError):
    """A robot log is malformed, truncated or of an unsupported kind."""


class TopicNotFoundError(LogFormatError):
    """The requested topic (or any usable sensor topic) is not in the log."""


class GraphFormatError(InputFileError):
    """A pose-graph file (g2o, TORO) has a malformed line."""


class MapFormatError(InputFileError):
    """A map file (map_server yaml/pgm, npz) is malformed."""


class OutputError(InputFileError):
    """An output path that cannot be written: an existing file or folder of the wrong kind, a folder nothing
    can be created in, a full disk, or a folder that is not an earlier output of the same command."""


class ConfigError(GpslamError, ValueError):
    """An invalid configuration value."""
