"""ROS 2 bag folder reader (``ros2 bag record``'s output: ``metadata.yaml`` beside its storage files), for the
storage :class:`~slam.logs.mcap_reader.McapReader` does not read alone: SQLite (``.db3``, the default before
ROS 2 Iron) and bags split into several files.

The container is read by ``rosbags.rosbag2.Reader``; messages (CDR) are decoded with types built from the
definitions the bag stores (bag format ≥ 8), else from the standard ROS 2 (Humble) interfaces bundled with
rosbags, whose ``sensor_msgs`` / ``nav_msgs`` / ``tf2_msgs`` / ``geometry_msgs`` the readers use are the same in
every ROS 2 release. The conversions to :class:`~core.frame.Frame` are shared with the other ROS readers
(:mod:`slam.logs.ros_msgs`). Stamps are the header stamps (float seconds).
"""

from __future__ import annotations

from typing import Any, Iterator

from core.errors import LogFormatError

from .base import SkipHandler, TopicInfo, lost
from .ros_msgs import RawMessage, normalize_msgtype
from .rosbags_container import RosbagsReader

__all__ = ["Rosbag2Reader"]


class Rosbag2Reader(RosbagsReader):
    """Stream a ROS 2 bag folder as Frames (see :class:`RosLogReader` for the arguments)."""

    format = "ros2 bag"

    def _open(self):  # type: ignore[no-untyped-def]
        from rosbags.rosbag2 import Reader

        try:
            reader = Reader(self.path)
            reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises ReaderError, yaml and sqlite3 errors on damaged bags
            raise LogFormatError(self.path, None, f"not a readable ROS 2 bag: {type(exc).__name__}: {exc}") from None
        return reader

    def _load_meta(self, tolerant: bool = False) -> None:
        """Topics, counts and message types from the bag's metadata and connections (read before any message,
        *tolerant* or not)."""
        if self._topics is not None:
            return
        from rosbags.interfaces import MessageDefinitionFormat
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        reader = self._open()
        try:
            counts: dict[str, list] = {}
            store = get_typestore(Stores.ROS2_HUMBLE)
            try:
                for c in reader.connections:
                    mt = normalize_msgtype(c.msgtype)
                    entry = counts.setdefault(c.topic, [mt, 0])
                    entry[1] += c.msgcount
                    md = c.msgdef
                    if mt in store.types or md is None or not md.data:
                        continue  # a standard interface, or a type the bag does not define (refused when read)
                    if md.format == MessageDefinitionFormat.IDL:
                        store.register(get_types_from_idl(md.data))
                    else:
                        store.register(get_types_from_msg(md.data, mt))
            except Exception as exc:  # noqa: BLE001 - rosbags raises several types for bad definitions
                raise LogFormatError(self.path, "metadata", f"bad message definition: {exc}") from None
            self._store = store
            self._topics = [TopicInfo(name, mt, n) for name, (mt, n) in sorted(counts.items())]
        finally:
            reader.close()

    def _raw_messages(self, topics: set[str] | None, on_skip: SkipHandler | None = None) -> Iterator[RawMessage]:
        """Messages in time order. A storage rosbags cannot read on (a damaged SQLite page, a cut file) is an error
        naming the last message read; with *on_skip* it is reported once and the messages end there (the
        storage gives no index to resume from)."""
        self._load_meta()
        own = self._shared is None
        reader = self._open() if own else self._shared
        counts: dict[str, int] = {}
        last = "before the first message"
        try:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            if not conns:
                return
            it = reader.messages(connections=conns)
            while True:
                try:
                    item = next(it)
                except StopIteration:
                    return
                except Exception as exc:  # noqa: BLE001 - sqlite3.DatabaseError, the mcap plugin's errors, ...
                    why = f"{type(exc).__name__}: {exc}".rstrip(": ")
                    error = LogFormatError(self.path, last, f"corrupt or truncated ROS 2 bag: {why}")
                    if on_skip is None:
                        raise error from None
                    on_skip(lost(error, None))
                    return
                conn, t_ns, data = item
                k = counts.get(conn.topic, 0)
                counts[conn.topic] = k + 1
                where = f"{conn.topic} message {k}"
                last = f"after {where}"
                yield RawMessage(k, conn.topic, normalize_msgtype(conn.msgtype), int(t_ns), bytes(data), where)
        finally:
            if own:
                reader.close()

    def _decode(self, raw: RawMessage) -> Any:
        assert self._store is not None
        if raw.msgtype not in self._store.types:
            raise LogFormatError(self.path, raw.where, f"no definition of {raw.msgtype} on {raw.topic} in the bag")
        try:
            return self._store.deserialize_cdr(raw.data, raw.msgtype)
        except Exception as exc:  # noqa: BLE001 - rosbags raises SerdeError, struct.error, IndexError, ...
            raise LogFormatError(self.path, raw.where, f"cannot decode {raw.msgtype} on {raw.topic}: {exc}") from None
