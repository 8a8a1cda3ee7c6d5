"""Robot-log readers and writers. ``open_log`` picks the reader from the file name and content."""

from __future__ import annotations

from pathlib import Path

from core.errors import LogFormatError

from .base import LogInfo, LogReader, SkipHandler, SkipLog, TopicInfo

__all__ = ["open_log", "LogReader", "LogInfo", "TopicInfo", "SkipHandler", "SkipLog", "detect_format"]

_CARMEN_SUFFIXES = (".clf", ".log", ".carmen", ".txt")


def detect_format(path: str | Path) -> str:
    """Return ``"carmen"``, ``"mcap"``, ``"ros1"``, ``"ros2"`` (a ROS 2 bag folder not stored as one MCAP file) or
    ``"kitti"`` for *path* (raises LogFormatError)."""
    p = Path(path)
    if not p.exists():
        raise LogFormatError(p, None, "no such file or directory")
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return "mcap" if rosbag2_file(p) is not None else "ros2"
        if (p / "velodyne").is_dir() or any(p.glob("*.bin")):
            return "kitti"
        raise LogFormatError(p, None, "directory is neither a ROS 2 bag (metadata.yaml) nor a KITTI sequence "
                                      "(velodyne/ folder or .bin files)")
    if p.suffix == ".bin":
        return "kitti"
    name = p.name.lower()
    for comp in (".bz2", ".gz"):
        if name.endswith(comp):
            name = name[: -len(comp)]
    try:
        with open(p, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise LogFormatError(p, None, f"cannot read: {exc.strerror or exc}") from None
    if head.startswith(b"\x89MCAP") or name.endswith(".mcap"):
        return "mcap"
    if head.startswith(b"#ROSBAG V2.0") or name.endswith(".bag"):
        return "ros1"
    if name.endswith(".db3"):
        raise LogFormatError(p, None, "the SQLite file of a ROS 2 bag: give the bag's folder (metadata.yaml beside it)")
    if name.endswith(_CARMEN_SUFFIXES) or head[:2] == b"BZ" or head[:2] == b"\x1f\x8b":
        return "carmen"
    raise LogFormatError(p, None, "unknown log format (expected .clf/.log[.bz2|.gz], .mcap, .bag, a ROS 2 bag folder or a KITTI sequence)")


def rosbag2_file(folder: Path) -> Path | None:
    """The one ``.mcap`` file of a ROS 2 bag folder (``metadata.yaml`` beside its storage), read as any MCAP log;
    None for a bag :class:`~slam.logs.rosbag2.Rosbag2Reader` reads instead (SQLite ``.db3`` storage, or split into
    several files). Raises LogFormatError naming the folder when it holds no storage file at all."""
    mcaps = sorted(folder.glob("*.mcap"))
    if len(mcaps) == 1:
        return mcaps[0]
    if not mcaps and not any(folder.glob("*.db3")):
        raise LogFormatError(folder, None, "a ROS 2 bag folder (metadata.yaml) without its .mcap or .db3 storage file")
    return None


def open_log(path: str | Path, topic: str | None = None) -> LogReader:
    """Open a robot log of any supported format as a streaming :class:`LogReader`.

    Args:
        path: a CARMEN log (``.clf``/``.log``, optionally ``.bz2``/``.gz``), an MCAP file, a ROS 2 bag folder
            (MCAP or SQLite storage), a ROS 1 bag, or a KITTI sequence folder (``sequences/NN`` with
            ``velodyne/`` and ``calib.txt``).
        topic: the sensor topic to read (MCAP / ROS 1); auto-detected when None.
    """
    fmt = detect_format(path)
    if fmt == "carmen":
        from .carmen import CarmenReader

        return CarmenReader(path, topic)
    if fmt == "mcap":
        from .mcap_reader import McapReader

        return McapReader(rosbag2_file(Path(path)) if Path(path).is_dir() else path, topic)
    if fmt == "ros2":
        from .rosbag2 import Rosbag2Reader

        return Rosbag2Reader(path, topic)
    if fmt == "ros1":
        from .rosbag1 import Ros1BagReader

        return Ros1BagReader(path, topic)
    from .kitti import KittiReader

    return KittiReader(path, topic)
