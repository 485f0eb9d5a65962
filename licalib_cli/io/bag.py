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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from licalib_cli.config import yaml_error_summary
from licalib_cli.errors import BagError, TopicError

__all__ = [
    "CLOUD_TYPE",
    "IMU_TYPE",
    "BagHandle",
    "MessageLosses",
    "RawMessage",
    "TopicInfo",
    "bag_paths",
    "detect_format",
    "imu_vectors_from_raw",
    "open_bag",
    "repair_hint",
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


_MAGIC = {
    "ros1": b"#ROSBAG V2.0\n",
    "mcap": b"\x89MCAP",
    "db3": b"SQLite format 3\x00",
}
_SUFFIX_FORMAT = {".bag": "ros1", ".mcap": "mcap", ".db3": "db3"}
_FORMAT_NAME = {
    "ros1": "ROS1 bag",
    "mcap": "ROS2 MCAP file",
    "db3": "ROS2 SQLite (.db3) file",
}
_FORMAT_SUFFIX = {"ros1": ".bag", "mcap": ".mcap", "db3": ".db3"}


def detect_format(path: Path) -> str | None:
    """The container format of a file from its first bytes: ``ros1``, ``mcap``, ``db3``,
    ``empty``, or None when it is none of them (or cannot be read)."""
    try:
        with Path(path).open("rb") as f:
            head = f.read(16)
    except OSError:
        return None
    if not head:
        return "empty"
    for fmt, magic in _MAGIC.items():
        if head.startswith(magic):
            return fmt
    return None


def repair_hint(fmt: str, file: Path) -> str:
    """How to repair a damaged file of format ``fmt`` (a clause after a semicolon)."""
    if fmt == "ros1":
        return f"repair it with `rosbag reindex {file}` (ROS1) or re-record it"
    if fmt == "mcap":
        return (
            f"recover it with `mcap recover {file} -o recovered.mcap` (the mcap command-line "
            "tool) and pass recovered.mcap, or re-record it"
        )
    return (
        f"recover it with `sqlite3 {file} .recover | sqlite3 recovered.db3` and pass "
        "recovered.db3, or re-record it"
    )


def _short(err: BaseException) -> str:
    """The first line of an exception's text, without a final full stop."""
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return text.rstrip(".")


def _file_problem(file: Path, err: BaseException | None) -> str:
    """Why one storage file cannot be read: its format (from its first bytes), and the fix."""
    expected = _SUFFIX_FORMAT.get(file.suffix)
    found = detect_format(file)
    if found == "empty":
        return f"{file} is empty (0 bytes); the recording was not written, re-record it"
    if found is not None and expected is not None and found != expected:
        right = file.with_suffix(_FORMAT_SUFFIX[found])
        return (
            f"{file} is a {_FORMAT_NAME[found]}, not a {_FORMAT_NAME[expected]}; rename it to "
            f"{right.name} and pass that"
        )
    if found is None:
        what = _FORMAT_NAME.get(expected or "", "bag")
        return (
            f"{file} is not a {what} (it does not start with the format's signature); check the "
            "path: licalib reads ROS1 .bag, ROS2 .db3/.mcap files and ROS2 bag folders"
        )
    why = f" ({_short(err)})" if err is not None else ""
    return (
        f"{file} is a {_FORMAT_NAME[found]} that cannot be read{why}: it is truncated or "
        f"damaged, {repair_hint(found, file)}"
    )


def _try_open(paths: list[Path]) -> BaseException | None:
    """The error of opening ``paths`` with rosbags, or None when they open."""
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as err:
        return err
    try:
        reader.close()
    except Exception:  # closing must not hide the answer
        logger.debug("closing %s failed", paths, exc_info=True)
    return None


def _open_failure(path: Path, paths: list[Path], err: BaseException) -> str:
    """One sentence on why ``path`` (resolved to ``paths``) cannot be opened: the format
    detected, the file at fault and the fix for that format."""
    if path.is_dir() and paths == [path]:  # a ROS2 bag folder
        meta = path / "metadata.yaml"
        storage = sorted([*path.glob("*.db3"), *path.glob("*.mcap")])
        try:
            info = yaml.safe_load(meta.read_text(encoding="utf-8"))
            ok = isinstance(info, dict) and isinstance(
                info.get("rosbag2_bagfile_information"), dict
            )
            why = "not a rosbag2 metadata file"
        except yaml.YAMLError as meta_err:
            ok, why = False, f"not valid YAML: {yaml_error_summary(meta_err)}"
        except UnicodeDecodeError:
            ok, why = False, "not a text file"
        except OSError as meta_err:
            ok, why = False, _short(meta_err)
        if not ok:
            direct = f"pass {storage[0]} itself (licalib reads it without metadata.yaml)"
            fix = direct + " or " if len(storage) == 1 else ""
            return (
                f"The ROS2 bag folder {path} has a damaged metadata.yaml ({why}); {fix}rebuild "
                f"it with `ros2 bag reindex {path}`."
            )
        for file in storage:
            file_err = _try_open([file])
            if file_err is not None:
                return f"In the ROS2 bag folder {path}, {_file_problem(file, file_err)}."
        return (
            f"The ROS2 bag folder {path} cannot be read ({_short(err)}); its metadata.yaml does "
            f"not match its files, rebuild it with `ros2 bag reindex {path}`."
        )
    if len(paths) > 1:  # a folder of split ROS1 bags
        for file in paths:
            file_err = _try_open([file])
            if file_err is not None:
                return (
                    f"Of the {len(paths)} split bags in {path}, {_file_problem(file, file_err)}; "
                    "or move it out of the folder to use the others."
                )
        return (
            f"The split bags in {path} cannot be read together ({_short(err)}); they may not "
            "belong to one recording, pass them one at a time."
        )
    return _file_problem(paths[0], err) + "."


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


_IMU_TAIL = 296
"""Bytes of a ``sensor_msgs/Imu`` after its header: orientation (4 doubles), three covariances
(9 doubles each), angular velocity and linear acceleration (3 doubles each)."""


def imu_vectors_from_raw(
    raw: bytes | memoryview, ros1: bool
) -> tuple[float, float, float, float, float, float] | None:
    """``angular_velocity`` and ``linear_acceleration`` of a serialised ``sensor_msgs/Imu``
    read at their fixed offsets, without deserialising (a tenth of the time).

    ROS1: ``seq, sec, nsec, frame_id (u32 length + bytes)``, then the doubles packed; CDR: the
    4-byte encapsulation header, ``sec, nanosec, frame_id (u32 length incl. NUL + bytes)``,
    then the doubles aligned to 8 bytes from the end of the encapsulation header.

    Returns:
        ``(wx, wy, wz, ax, ay, az)``, or None when the bytes do not have exactly this layout
        (the caller then deserialises the message).
    """
    n = len(raw)
    if n < 16 + _IMU_TAIL:
        return None
    little = ros1 or raw[1] == 1
    order = "<" if little else ">"
    (length,) = struct.unpack_from(order + "I", raw, 12)
    pos = 16 + int(length)
    if not ros1:
        pos = 4 + -(-(pos - 4) // 8) * 8
    if pos + _IMU_TAIL != n:
        return None
    w = struct.unpack_from(order + "3d", raw, pos + 104)
    a = struct.unpack_from(order + "3d", raw, pos + 200)
    return (w[0], w[1], w[2], a[0], a[1], a[2])


@dataclass
class MessageLosses:
    """Messages of one topic that the bag lists but that could not be used.

    Attributes:
        undecodable: record times of messages whose bytes do not decode.
        misstamped: record times of messages whose header stamp lies far from their record
            time (more than the reading margin off the topic's usual offset; e.g. zero).
        missing: messages the bag's index counts but that could not be read at all (a damaged
            MCAP chunk is skipped silently by the reader); known only once the whole topic was
            read.
    """

    undecodable: set[int] = field(default_factory=set)
    misstamped: set[int] = field(default_factory=set)
    missing: int = 0

    @property
    def total(self) -> int:
        """All unusable messages."""
        return len(self.undecodable) + len(self.misstamped) + self.missing

    def describe(self) -> str:
        """What the losses are, e.g. ``"3 undecodable, 64 lost in damaged chunks"``."""
        parts = []
        if self.undecodable:
            parts.append(f"{len(self.undecodable)} undecodable")
        if self.misstamped:
            parts.append(f"{len(self.misstamped)} with a header stamp far from the record time")
        if self.missing:
            parts.append(f"{self.missing} lost in damaged chunks")
        return ", ".join(parts)


class BagHandle:
    """An open bag: topics, time range, message streaming and deserialisation.

    Use through :func:`open_bag`. Reading errors are re-raised as :class:`BagError`; messages
    that cannot be used are counted per topic in :attr:`losses` (see :meth:`decode`).
    """

    def __init__(self, path: Path, reader: AnyReader, files: list[Path]) -> None:
        self.path = path
        self.files = files
        self._reader = reader
        self.ros1 = not reader.is2
        self.topics: tuple[TopicInfo, ...] = tuple(
            TopicInfo(name, msgtype, count)
            for (name, msgtype), count in sorted(self._topic_counts().items())
        )
        self.losses: dict[str, MessageLosses] = {}

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
        names = [p.name for p in paths]  # type: ignore[attr-defined]
        if any(n.endswith(".mcap") for n in names):
            return "ros2-mcap"
        folder = paths[0]
        if folder.is_dir() and any(folder.glob("*.mcap")):  # type: ignore[attr-defined]
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

    def loss(self, topic: str) -> MessageLosses:
        """The unusable messages of ``topic`` found so far."""
        return self.losses.setdefault(topic, MessageLosses())

    def _damaged(self, err: BaseException) -> BagError:
        """The error for a bag whose messages stop reading part way."""
        kind = self.format.removeprefix("ros2-")
        files = [f for f in self.files if f.is_file()] or [self.path]
        file = files[0] if len(files) == 1 else self.path
        msg = (
            f"The bag {self.path} is damaged: reading its messages failed part way ("
            f"{type(err).__name__}: {str(err).strip().rstrip('.')}); {repair_hint(kind, file)}."
        )
        return BagError(msg)

    def messages(
        self,
        topics: Sequence[str],
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Stream messages of ``topics`` with record time in ``[start_ns, stop_ns)``.

        When the range covers the whole bag and the stream is read to its end, messages the
        index counts but the reader could not deliver are counted in :attr:`losses`.

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
        whole = (start_ns is None or start_ns <= self.start_ns) and (
            stop_ns is None or stop_ns >= self.end_ns
        )
        seen: dict[str, int] = dict.fromkeys(wanted, 0)
        try:
            for conn, t_rec, raw in self._reader.messages(
                connections=conns, start=start_ns, stop=stop_ns
            ):
                seen[conn.topic] += 1
                yield RawMessage(
                    conn.topic, int(t_rec), _stamp_from_raw(raw, self.ros1), raw, conn.msgtype
                )
        except BagError:
            raise
        except Exception as err:  # storage back ends raise their own exception types
            raise self._damaged(err) from err
        if whole:
            listed = {t.name: t.count for t in self.topics if t.name in wanted}
            for topic, n in listed.items():
                self.loss(topic).missing = max(0, n - seen[topic])

    def decode(self, message: RawMessage) -> Any | None:
        """Deserialise one message with the bag's embedded definitions.

        Returns:
            The message, or None when its bytes do not decode (counted in :attr:`losses`).
        """
        try:
            return self._reader.deserialize(message.raw, message.msgtype)
        except Exception:  # any decoding failure means a damaged message
            logger.debug(
                "%s message at %d on %s does not decode",
                message.msgtype,
                message.record_ns,
                message.topic,
                exc_info=True,
            )
            self.loss(message.topic).undecodable.add(message.record_ns)
            return None


@contextmanager
def open_bag(path: Path) -> Iterator[BagHandle]:
    """Open any supported bag for reading.

    Args:
        path: a ``.bag`` file, a folder of split ``.bag`` files, a ROS2 bag folder, or a bare
            ``.db3``/``.mcap`` file.

    Yields:
        A :class:`BagHandle`, closed on exit.

    Raises:
        BagError: missing path, not a bag, corrupt or truncated bag; the message names the
            format detected, the file at fault and the fix for that format.
    """
    path = Path(path)
    paths = bag_paths(path)
    try:
        reader = AnyReader(paths, default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as err:  # rosbags, sqlite, mcap and OS errors on damaged inputs
        raise BagError(_open_failure(path, paths, err)) from err
    files = [p for q in paths for p in ([q] if q.is_file() else sorted(q.iterdir()))]
    try:
        yield BagHandle(path, reader, files)
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
        from licalib_cli.io.ouster import packet_topics

        packets = packet_topics(bag.topics)
        if packets:
            kinds = sorted({t.msgtype.replace("/msg/", "/") for t in packets})
            msg = (
                f"The bag holds raw Ouster packets ({', '.join(t.name for t in packets)}: "
                f"{', '.join(kinds)}) and no sensor_msgs/PointCloud2 or sensor_msgs/Imu topic; "
                "replay it through the ouster-ros driver (its replay launch file) while "
                "recording the driver's points and imu topics, and pass that bag."
            )
            raise TopicError(msg)
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
