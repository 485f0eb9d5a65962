"""Open ROS1 and ROS2 bags through one code path and stream their messages.

This is the only reading module that imports rosbags. Accepted inputs:

* a ROS1 ``.bag`` file, or a folder of split ``.bag`` files (merged in time order);
* a ROS2 bag folder (with ``metadata.yaml``);
* a bare ROS2 ``.db3`` or ``.mcap`` file.

Conventions: every time is int64 nanoseconds. ``record_ns`` is the bag's record time (the
recorder's clock); ``stamp_ns`` is the message's ``header.stamp``. Windows are read by record
time (cheap, indexed) and then filtered by header stamp by the callers.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.typesys import Stores, get_typestore

from licalib_cli.errors import BagError, TopicError

__all__ = [
    "CLOUD_TYPE",
    "IMU_TYPE",
    "BagHandle",
    "RawMessage",
    "TopicInfo",
    "bag_paths",
    "open_bag",
    "select_topic",
]

logger = logging.getLogger(__name__)

IMU_TYPE = "sensor_msgs/msg/Imu"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"

_STAMP = struct.Struct("<iI")
_STAMP_BE = struct.Struct(">iI")
_NS = 1_000_000_000


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag.

    Attributes:
        name: topic name.
        msgtype: normalised message type, e.g. ``sensor_msgs/msg/Imu``.
        count: number of messages in the whole bag.
    """

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class RawMessage:
    """A message as stored, with its header stamp read without deserialising.

    Attributes:
        topic: topic name.
        record_ns: bag record time, ns.
        stamp_ns: ``header.stamp`` in ns, or None when the message type has no leading header.
        raw: serialised bytes.
        msgtype: normalised message type.
    """

    topic: str
    record_ns: int
    stamp_ns: int | None
    raw: bytes
    msgtype: str


def bag_paths(path: Path) -> list[Path]:
    """The paths to hand to the reader for one user-given input.

    Args:
        path: a ``.bag`` file, a folder of ``.bag`` files, a ROS2 bag folder, or a bare
            ``.db3``/``.mcap`` file.

    Returns:
        The list of files/folders for :class:`rosbags.highlevel.AnyReader`.

    Raises:
        BagError: the path does not exist or is not a bag.
    """
    path = Path(path)
    if not path.exists():
        msg = f"The bag {path} does not exist; check the path."
        raise BagError(msg)
    if path.is_dir():
        split = sorted(path.glob("*.bag"))
        if split:
            return split
        if (path / "metadata.yaml").is_file():
            return [path]
        storage = sorted([*path.glob("*.db3"), *path.glob("*.mcap")])
        if len(storage) == 1:
            return storage
        msg = (
            f"The folder {path} is not a bag: it has no .bag files, no ROS2 metadata.yaml and "
            "no single .db3/.mcap file; pass a ROS1 .bag, a ROS2 bag folder or a .db3/.mcap file."
        )
        raise BagError(msg)
    if path.suffix not in {".bag", ".db3", ".mcap"}:
        msg = (
            f"{path} is not a bag (expected a .bag, .db3 or .mcap file, or a ROS2 bag folder); "
            "check the path."
        )
        raise BagError(msg)
    return [path]


def _stamp_from_raw(raw: bytes | memoryview, ros1: bool) -> int | None:
    """``header.stamp`` of a serialised message that starts with a ``std_msgs/Header``.

    ROS1: ``seq u32, sec u32, nsec u32``; CDR: 4-byte encapsulation header then
    ``sec i32, nanosec u32``. Both put the stamp at bytes 4..12.
    """
    if len(raw) < 12:
        return None
    if ros1:
        sec, nsec = _STAMP.unpack_from(raw, 4)
    else:
        little = raw[1] == 1
        sec, nsec = (_STAMP if little else _STAMP_BE).unpack_from(raw, 4)
    return int(sec) * _NS + int(nsec)


class BagHandle:
    """An open bag: topics, time range, message streaming and deserialisation.

    Use through :func:`open_bag`. All reading errors are re-raised as :class:`BagError`.
    """

    def __init__(self, path: Path, reader: AnyReader) -> None:
        self.path = path
        self._reader = reader
        self.ros1 = not reader.is2
        self.topics: tuple[TopicInfo, ...] = tuple(
            TopicInfo(name, msgtype, count)
            for (name, msgtype), count in sorted(self._topic_counts().items())
        )

    def _topic_counts(self) -> dict[tuple[str, str], int]:
        counts: dict[tuple[str, str], int] = {}
        for conn in self._reader.connections:
            key = (conn.topic, conn.msgtype)
            counts[key] = counts.get(key, 0) + int(conn.msgcount)
        return counts

    @property
    def format(self) -> str:
        """``ros1``, ``ros2-db3`` or ``ros2-mcap``."""
        if self.ros1:
            return "ros1"
        paths = self._reader.paths
        names = [p.name for p in paths]
        if any(n.endswith(".mcap") for n in names):
            return "ros2-mcap"
        folder = paths[0]
        if folder.is_dir() and any(folder.glob("*.mcap")):
            return "ros2-mcap"
        return "ros2-db3"

    @property
    def start_ns(self) -> int:
        """Record time of the first message, ns."""
        return int(self._reader.start_time)

    @property
    def end_ns(self) -> int:
        """Record time just after the last message, ns."""
        return int(self._reader.end_time)

    def topics_of_type(self, msgtype: str) -> list[TopicInfo]:
        """Topics carrying ``msgtype``."""
        return [t for t in self.topics if t.msgtype == msgtype]

    def messages(
        self,
        topics: Sequence[str],
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Stream messages of ``topics`` with record time in ``[start_ns, stop_ns)``.

        Args:
            topics: topic names to read.
            start_ns: first record time, ns (None: from the start).
            stop_ns: record time to stop before, ns (None: to the end).

        Yields:
            :class:`RawMessage` in record-time order; nothing is kept in memory.

        Raises:
            BagError: the bag is corrupt or truncated.
        """
        wanted = set(topics)
        conns = [c for c in self._reader.connections if c.topic in wanted]
        if not conns:
            return
        try:
            for conn, t_rec, raw in self._reader.messages(
                connections=conns, start=start_ns, stop=stop_ns
            ):
                yield RawMessage(
                    conn.topic, int(t_rec), _stamp_from_raw(raw, self.ros1), raw, conn.msgtype
                )
        except BagError:
            raise
        except Exception as err:  # storage back ends raise their own exception types
            msg = (
                f"The bag {self.path} is corrupt or truncated ({type(err).__name__}: {err}); "
                "re-record it or repair it (ROS1: `rosbag reindex`; ROS2: `ros2 bag reindex`)."
            )
            raise BagError(msg) from err

    def deserialize(self, message: RawMessage) -> Any:
        """Deserialise one message with the bag's embedded definitions.

        Raises:
            BagError: the bytes do not decode (corrupt message).
        """
        try:
            return self._reader.deserialize(message.raw, message.msgtype)
        except Exception as err:
            msg = (
                f"A {message.msgtype} message on {message.topic} in {self.path} cannot be "
                f"decoded ({err}); the bag is corrupt, re-record or repair it."
            )
            raise BagError(msg) from err


@contextmanager
def open_bag(path: Path) -> Iterator[BagHandle]:
    """Open any supported bag for reading.

    Args:
        path: a ``.bag`` file, a folder of split ``.bag`` files, a ROS2 bag folder, or a bare
            ``.db3``/``.mcap`` file.

    Yields:
        A :class:`BagHandle`, closed on exit.

    Raises:
        BagError: missing path, not a bag, corrupt or truncated bag.
    """
    path = Path(path)
    paths = bag_paths(path)
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except (AnyReaderError, FileNotFoundError, OSError, ValueError, KeyError) as err:
        msg = (
            f"{path} cannot be read as a bag ({err}); check that it is a complete ROS1 .bag, "
            "ROS2 bag folder or .db3/.mcap file (a truncated ROS1 bag can be repaired with "
            "`rosbag reindex`)."
        )
        raise BagError(msg) from err
    except Exception as err:  # e.g. sqlite or mcap parsing errors on damaged files
        msg = (
            f"{path} cannot be read as a bag ({type(err).__name__}: {err}); it is corrupt or "
            "truncated, re-record or repair it."
        )
        raise BagError(msg) from err
    try:
        yield BagHandle(path, reader)
    finally:
        try:
            reader.close()
        except Exception:  # closing a damaged bag must not hide the real error
            logger.debug("closing %s failed", path, exc_info=True)


def select_topic(
    bag: BagHandle, msgtype: str, requested: str | None, option: str, config_key: str
) -> TopicInfo:
    """Choose the topic of ``msgtype``: the requested one, or the only one in the bag.

    Args:
        bag: an open bag.
        msgtype: normalised type, :data:`IMU_TYPE` or :data:`CLOUD_TYPE`.
        requested: topic named by the user (option or config), or None.
        option: the command-line option that names it, for the message (``--imu-topic``).
        config_key: the config key that names it (``imu.topic``).

    Returns:
        The selected topic.

    Raises:
        TopicError: the named topic is missing or of another type, or there is no topic of
            that type, or several and none was named. The message lists the candidates.
    """
    short = msgtype.replace("/msg/", "/")
    candidates = bag.topics_of_type(msgtype)
    names = ", ".join(t.name for t in candidates) or "none"
    if requested is not None:
        for t in bag.topics:
            if t.name == requested:
                if t.msgtype != msgtype:
                    got = t.msgtype.replace("/msg/", "/")
                    msg = (
                        f"Topic {requested} is {got}, not {short}; pass a {short} topic with "
                        f"{option} (candidates: {names})."
                    )
                    raise TopicError(msg)
                return t
        msg = (
            f"Topic {requested} is not in the bag; pass an existing {short} topic with {option} "
            f"(candidates: {names})."
        )
        raise TopicError(msg)
    if not candidates:
        others = ", ".join(f"{t.name} ({t.msgtype.replace('/msg/', '/')})" for t in bag.topics)
        msg = (
            f"The bag has no {short} topic (topics: {others or 'none'}); record one, or convert "
            "the data to this message type."
        )
        raise TopicError(msg)
    if len(candidates) > 1:
        msg = (
            f"The bag has {len(candidates)} {short} topics ({names}); choose one with {option} "
            f"or `{config_key}` in the config."
        )
        raise TopicError(msg)
    return candidates[0]
