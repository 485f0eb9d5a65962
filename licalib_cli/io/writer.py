"""Write ROS1 ``.bag``, ROS2 ``.db3`` and ROS2 ``.mcap`` bags with Imu and PointCloud2 messages.

Used by the simulator and by the tests; one writer for all three formats.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from types import TracebackType

    import numpy.typing as npt

IMU_TYPE = "sensor_msgs/msg/Imu"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"

# numpy kind+size -> sensor_msgs/PointField datatype code
_POINTFIELD_CODE = {
    ("i", 1): 1,
    ("u", 1): 2,
    ("i", 2): 3,
    ("u", 2): 4,
    ("i", 4): 5,
    ("u", 4): 6,
    ("f", 4): 7,
    ("f", 8): 8,
}


class BagFormat(str, Enum):
    """Container formats licalib reads and writes."""

    ROS1 = "ros1"
    ROS2_DB3 = "ros2-db3"
    ROS2_MCAP = "ros2-mcap"


def default_bag_path(out_dir: Path, fmt: BagFormat) -> Path:
    """``out_dir/bag.bag`` for ROS1, the ROS2 bag folder ``out_dir/bag`` otherwise."""
    return out_dir / ("bag.bag" if fmt is BagFormat.ROS1 else "bag")


def _stamp(ts: Any, t_ns: int) -> Any:
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)


class BagWriter:
    """Context manager that writes Imu and PointCloud2 messages to any supported format.

    Example::

        with BagWriter(tmp_path / "x.bag", BagFormat.ROS1) as w:
            w.write_imu("/imu", t_ns, gyro, accel)
            w.write_cloud("/points", t_ns, structured_points)
    """

    def __init__(self, path: Path, fmt: BagFormat | str) -> None:
        # rosbags is imported here, not with the module: the command line imports BagFormat
        # for its options and should not pay for the bag library to print its help
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        self.fmt = BagFormat(fmt)
        self._ros1 = self.fmt is BagFormat.ROS1
        self.typestore = get_typestore(Stores.ROS1_NOETIC if self._ros1 else Stores.ROS2_HUMBLE)
        if self._ros1:
            self._writer: Any = Writer1(self.path)
        else:
            mcap = self.fmt is BagFormat.ROS2_MCAP
            plugin = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
            self._writer = Writer2(self.path, version=Writer2.VERSION_LATEST, storage_plugin=plugin)
        self._conns: dict[tuple[str, str], Any] = {}
        self._seq = 0

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._writer.close()

    def header(self, t_ns: int, frame_id: str) -> Any:
        """A ``std_msgs/Header`` for this format (ROS1 carries ``seq``)."""
        header_t = self.typestore.types["std_msgs/msg/Header"]
        self._seq += 1
        if self._ros1:
            return header_t(seq=self._seq, stamp=_stamp(self.typestore, t_ns), frame_id=frame_id)
        return header_t(stamp=_stamp(self.typestore, t_ns), frame_id=frame_id)

    def write_message(self, topic: str, msgtype: str, msg: Any, record_ns: int) -> None:
        """Serialise and write any message of this writer's typestore."""
        key = (topic, msgtype)
        if key not in self._conns:
            self._conns[key] = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
        ts = self.typestore
        raw = ts.serialize_ros1(msg, msgtype) if self._ros1 else ts.serialize_cdr(msg, msgtype)
        self._writer.write(self._conns[key], int(record_ns), raw)

    def write_imu(
        self,
        topic: str,
        t_ns: int,
        gyro: npt.ArrayLike,
        accel: npt.ArrayLike,
        frame_id: str = "imu",
        record_ns: int | None = None,
    ) -> None:
        """Write one ``sensor_msgs/Imu`` (orientation unknown: covariance[0] = -1)."""
        msg = self.imu_message(t_ns, gyro, accel, frame_id)
        self.write_message(topic, IMU_TYPE, msg, t_ns if record_ns is None else record_ns)

    def imu_message(
        self, t_ns: int, gyro: npt.ArrayLike, accel: npt.ArrayLike, frame_id: str = "imu"
    ) -> Any:
        """A ``sensor_msgs/Imu`` of this writer's typestore (see :meth:`write_imu`)."""
        types = self.typestore.types
        vec = types["geometry_msgs/msg/Vector3"]
        g = np.asarray(gyro, dtype=np.float64)
        a = np.asarray(accel, dtype=np.float64)
        ocov = np.zeros(9)
        ocov[0] = -1.0
        msg = types[IMU_TYPE](
            header=self.header(t_ns, frame_id),
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=ocov,
            angular_velocity=vec(x=float(g[0]), y=float(g[1]), z=float(g[2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(x=float(a[0]), y=float(a[1]), z=float(a[2])),
            linear_acceleration_covariance=np.zeros(9),
        )
        return msg

    def write_cloud(
        self,
        topic: str,
        t_ns: int,
        points: np.ndarray,
        frame_id: str = "lidar",
        record_ns: int | None = None,
        is_dense: bool | None = None,
        row_padding: int = 0,
    ) -> None:
        """Write one ``sensor_msgs/PointCloud2`` from a structured array.

        Args:
            topic: topic name.
            t_ns: header stamp, ns.
            points: structured array, shape (N,) (unorganised) or (H, W) (organised). Field
                names, offsets, padding (``itemsize``) and byte order are taken from its dtype,
                so a big-endian or padded layout is written as such.
            frame_id: header frame.
            record_ns: bag record time; defaults to ``t_ns``.
            is_dense: defaults to "no NaN in x".
            row_padding: extra bytes at the end of each row (``row_step > width*point_step``).
        """
        msg = self.cloud_message(t_ns, points, frame_id, is_dense, row_padding)
        self.write_message(topic, CLOUD_TYPE, msg, t_ns if record_ns is None else record_ns)

    def cloud_message(
        self,
        t_ns: int,
        points: np.ndarray,
        frame_id: str = "lidar",
        is_dense: bool | None = None,
        row_padding: int = 0,
    ) -> Any:
        """A ``sensor_msgs/PointCloud2`` of this writer's typestore (see :meth:`write_cloud`);
        its fields can be altered before :meth:`write_message` (e.g. to write a damaged one)."""
        types = self.typestore.types
        pts = np.asarray(points)
        if pts.ndim == 1:
            pts = pts.reshape(1, -1)
        height, width = pts.shape
        dt = pts.dtype
        layout: Mapping[str, tuple[Any, ...]] = dt.fields or {}
        fields = []
        for name in dt.names or ():
            base, offset = layout[name][:2]
            count = 1
            if base.subdtype is not None:
                base, shape = base.subdtype
                count = int(np.prod(shape))
            code = _POINTFIELD_CODE[(base.kind, base.itemsize)]
            fields.append(
                types["sensor_msgs/msg/PointField"](
                    name=name, offset=offset, datatype=code, count=count
                )
            )
        bigendian = any(layout[n][0].byteorder == ">" for n in (dt.names or ()))
        point_step = dt.itemsize
        row_step = point_step * width + row_padding
        rows = np.zeros((height, row_step), dtype=np.uint8)
        rows[:, : point_step * width] = np.ascontiguousarray(pts).view(np.uint8).reshape(height, -1)
        if is_dense is None:
            is_dense = bool(np.isfinite(pts["x"]).all()) if "x" in (dt.names or ()) else True
        msg = types[CLOUD_TYPE](
            header=self.header(t_ns, frame_id),
            height=height,
            width=width,
            fields=fields,
            is_bigendian=bigendian,
            point_step=point_step,
            row_step=row_step,
            data=rows.reshape(-1),
            is_dense=is_dense,
        )
        return msg
