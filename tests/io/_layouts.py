"""Synthetic LiDAR sweeps in the exact PointCloud2 layouts of common drivers, and bag helpers.

Field names, datatypes, offsets and point_step of each driver, as published by its ROS node:

* Velodyne, ``ros-drivers/velodyne`` ``velodyne_pointcloud`` ``PointcloudXYZIRT``: fields set
  with ``setPointCloud2Fields`` (packed): x f32 @0, y f32 @4, z f32 @8, intensity f32 @12,
  ring u16 @16, time f32 @18, point_step 22. ``time`` is seconds relative to the header
  stamp, which is the last packet's stamp (negative times).
* Velodyne through PCL (``velodyne_pcl::PointXYZIRT`` with ``PCL_ADD_POINT4D``, EIGEN_ALIGN16,
  e.g. LIO-SAM bags): x @0, y @4, z @8, intensity f32 @16, ring u16 @20, time f32 @24,
  point_step 32.
* Ouster, ``ouster-lidar/ouster-ros`` ``ouster_ros::Point`` (default): x @0, y @4, z @8,
  intensity f32 @16, t u32 @20 (ns relative to the sweep start), reflectivity u16 @24,
  ring u16 @26, ambient u16 @28, range u32 @32, point_step 48; organised (beams x columns)
  with (0, 0, 0) for missing returns.
* Ouster ``ouster_ros::Point_LEGACY`` (``os_point.h`` / ``point_meta_helpers``): x @0, y @4,
  z @8, t u32 @16, ring u16 @20, range u32 @24, signal u32 @28, reflectivity u32 @32,
  near_ir u32 @36, point_step 48.
* Hesai, ``HesaiTechnology/HesaiLidar_ROS_2.0`` ``source_driver_ros1.hpp`` ``ToRosMsg``
  (``addPointField``, packed): x @0, y @4, z @8, intensity f32 @12, ring u16 @16,
  timestamp f64 @18 (absolute seconds), point_step 26; header stamp = first point.
* Robosense, ``RoboSense-LiDAR/rslidar_sdk`` ``ros_msg_translator.hpp`` (POINT_TYPE_XYZIRT):
  same packed layout as Hesai (x, y, z, intensity f32, ring u16 @16, timestamp f64 @18,
  point_step 26); header stamp = frame timestamp, the last point unless ``ts_first_point``.
* Livox, ``Livox-SDK/livox_ros_driver2`` ``lddc.cpp`` ``InitPointcloud2MsgHeader``
  (xfer_format 0, ``#pragma pack(1) LivoxPointXyzrtlt``): x f32 @0, y @4, z @8,
  intensity f32 @12, tag u8 @16, line u8 @17, timestamp f64 @18 (absolute ns), point_step 26;
  header stamp = base time (first point).
* Livox, ``Livox-SDK/livox_ros_driver`` v1 ``lddc.cpp`` (``LivoxPointXyzrtl``, packed):
  x @0, y @4, z @8, intensity f32 @12, tag u8 @16, line u8 @17, point_step 18, no time field.
* Livox ``CustomMsg`` converted to PointCloud2 (the usual CustomMsg -> PointCloud2 converter
  nodes keep the ``CustomPoint`` fields): x @0, y @4, z @8, intensity f32 @12,
  offset_time u32 @16 (ns since ``timebase``, the header stamp), tag u8 @20, line u8 @21,
  point_step 24 (2 bytes of padding).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from licalib_cli.io.writer import CLOUD_TYPE, BagFormat, BagWriter

NS = 1_000_000_000


def dtype_of(fields: list[tuple[str, str, int]], point_step: int, big: bool = False) -> np.dtype:
    """Structured dtype from (name, numpy type, offset) with explicit itemsize."""
    order = ">" if big else "<"
    return np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [order + f[1] for f in fields],
            "offsets": [f[2] for f in fields],
            "itemsize": point_step,
        }
    )


VELODYNE = dtype_of(
    [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("intensity", "f4", 12),
        ("ring", "u2", 16),
        ("time", "f4", 18),
    ],
    22,
)
VELODYNE_PCL = [
    ("x", "f4", 0),
    ("y", "f4", 4),
    ("z", "f4", 8),
    ("intensity", "f4", 16),
    ("ring", "u2", 20),
    ("time", "f4", 24),
]
OUSTER = dtype_of(
    [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("intensity", "f4", 16),
        ("t", "u4", 20),
        ("reflectivity", "u2", 24),
        ("ring", "u2", 26),
        ("ambient", "u2", 28),
        ("range", "u4", 32),
    ],
    48,
)
OUSTER_LEGACY = dtype_of(
    [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("t", "u4", 16),
        ("ring", "u2", 20),
        ("range", "u4", 24),
        ("signal", "u4", 28),
        ("reflectivity", "u4", 32),
        ("near_ir", "u4", 36),
    ],
    48,
)
HESAI = dtype_of(
    [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("intensity", "f4", 12),
        ("ring", "u2", 16),
        ("timestamp", "f8", 18),
    ],
    26,
)
ROBOSENSE = HESAI
LIVOX2 = dtype_of(
    [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("intensity", "f4", 12),
        ("tag", "u1", 16),
        ("line", "u1", 17),
        ("timestamp", "f8", 18),
    ],
    26,
)
LIVOX1 = dtype_of(
    [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("intensity", "f4", 12),
        ("tag", "u1", 16),
        ("line", "u1", 17),
    ],
    18,
)
LIVOX_OFFSET = dtype_of(
    [
        ("x", "f4", 0),
        ("y", "f4", 4),
        ("z", "f4", 8),
        ("intensity", "f4", 12),
        ("offset_time", "u4", 16),
        ("tag", "u1", 20),
        ("line", "u1", 21),
    ],
    24,
)
XYZI = dtype_of([("x", "f4", 0), ("y", "f4", 4), ("z", "f4", 8), ("intensity", "f4", 12)], 16)


def box_ranges(dirs: np.ndarray, half: tuple[float, float, float] = (9.0, 7.0, 3.0)) -> np.ndarray:
    """Range from the origin to the walls of a box room along unit directions (N, 3)."""
    h = np.asarray(half)
    with np.errstate(divide="ignore"):
        t = np.where(np.abs(dirs) > 1e-12, h / np.abs(dirs), np.inf)
    return t.min(axis=1)


@dataclass(frozen=True)
class Sweep:
    """Ground truth of one synthetic sweep, in firing (time) order.

    xyz (N, 3) metres; t_ns (N,) absolute; ring (N,) beam index as the driver numbers it;
    grid_shape (beams, columns) of the firing grid (column-major firing order).
    """

    xyz: np.ndarray
    t_ns: np.ndarray
    ring: np.ndarray
    start_ns: int
    period_ns: int


def spinning_sweep(
    start_ns: int,
    period_ns: int = 100_000_000,
    beams_deg: np.ndarray | None = None,
    columns: int = 360,
    clockwise: bool = True,
    ring_top_first: bool = False,
    azimuth0_deg: float = 0.0,
) -> Sweep:
    """A spinning LiDAR sweep inside a box: columns in time order, all beams per column."""
    el = np.deg2rad(np.linspace(-15, 15, 16) if beams_deg is None else beams_deg)
    nb = el.size
    col = np.arange(columns)
    frac = col / columns
    sign = -1.0 if clockwise else 1.0
    az = np.deg2rad(azimuth0_deg) + sign * 2 * np.pi * frac
    azg, elg = np.meshgrid(az, el, indexing="ij")  # (columns, beams)
    dirs = np.stack(
        [np.cos(elg) * np.cos(azg), np.cos(elg) * np.sin(azg), np.sin(elg)], -1
    ).reshape(-1, 3)
    r = box_ranges(dirs)
    xyz = dirs * r[:, None]
    t = start_ns + np.repeat(np.round(frac * period_ns).astype(np.int64), nb)
    ring = np.tile(np.arange(nb), columns)
    if ring_top_first:
        ring = nb - 1 - ring
    return Sweep(xyz, t, ring.astype(np.int64), start_ns, period_ns)


def fill(sweep: Sweep, dt: np.dtype) -> np.ndarray:
    """Structured array with x/y/z (and intensity, ring/line if present) from a sweep."""
    pts = np.zeros(sweep.xyz.shape[0], dtype=dt)
    pts["x"], pts["y"], pts["z"] = sweep.xyz.T
    names = dt.names or ()
    if "intensity" in names:
        pts["intensity"] = 10.0
    if "ring" in names:
        pts["ring"] = sweep.ring
    if "line" in names:
        pts["line"] = sweep.ring % 4
    return pts


def tilting_imu(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gyro (rad/s) and accelerometer (m/s^2) of a rig tilting in place, physically consistent.

    The orientation is ``R = Rz(yaw) Ry(pitch) Rx(roll)`` with smooth angles of a few tenths of
    a radian; the gyro is the body rate of ``R`` and the accelerometer the specific force
    ``R^T [0, 0, 9.81]`` of a rig that does not translate. Args: ``s`` (N,) seconds.
    """
    from scipy.spatial.transform import Rotation

    def rot(x: np.ndarray) -> Rotation:
        yaw = 0.8 * np.sin(0.7 * x + 0.3)
        pitch = 0.25 * np.cos(1.3 * x)
        roll = 0.3 * np.sin(2.1 * x)
        return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], 1))

    h = 1e-4
    gyro = (rot(s - h).inv() * rot(s + h)).as_rotvec() / (2 * h)
    accel = rot(s).inv().apply([0.0, 0.0, 9.81])
    return gyro, accel


def write_imu_stream(
    w: BagWriter,
    t0_ns: int,
    duration_s: float,
    rate_hz: float = 200.0,
    gyro_scale: float = 1.0,
    accel_scale: float = 1.0,
    topic: str = "/imu",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Write a tilting IMU stream (rad/s and m/s^2 times the scales); returns t, gyro, accel."""
    n = int(duration_s * rate_hz)
    t = t0_ns + np.round(np.arange(n) * NS / rate_hz).astype(np.int64)
    gyro, accel = tilting_imu((t - t0_ns) / NS)
    gyro = gyro * gyro_scale
    accel = accel * accel_scale
    for i in range(n):
        w.write_imu(topic, int(t[i]), gyro[i], accel[i])
    return t, gyro, accel


def write_velodyne_bag(
    path: Path,
    fmt: BagFormat | str,
    n_clouds: int = 10,
    t0_ns: int = 1_700_000_000 * NS,
    imu_rate_hz: float = 200.0,
    columns: int = 180,
) -> list[Sweep]:
    """A small VLP-16 (velodyne_pointcloud layout) + IMU bag; returns the sweeps."""
    sweeps = []
    with BagWriter(path, fmt) as w:
        write_imu_stream(w, t0_ns, n_clouds * 0.1 + 0.2, imu_rate_hz)
        for k in range(n_clouds):
            sw = spinning_sweep(t0_ns + k * 100_000_000, columns=columns)
            stamp = sw.start_ns + sw.period_ns  # velodyne: stamp = last packet
            pts = fill(sw, VELODYNE)
            pts["time"] = (sw.t_ns - stamp) / NS
            w.write_cloud("/velodyne_points", stamp, pts)
            sweeps.append(sw)
    return sweeps


def velodyne_points(stamp_ns: int, columns: int = 60) -> np.ndarray:
    """One small velodyne_pointcloud cloud whose times are relative to a start stamp."""
    sw = spinning_sweep(stamp_ns, columns=columns)
    pts = fill(sw, VELODYNE)
    pts["time"] = (sw.t_ns - sw.start_ns) / NS
    return pts


def write_custom_bag(
    path: Path,
    fmt: BagFormat | str = "ros2-mcap",
    imu_t: np.ndarray | None = None,
    clouds: list[tuple[int, np.ndarray]] | None = None,
    imu_topics: tuple[str, ...] = ("/imu",),
    cloud_topic: str = "/points",
    t0_ns: int = 1_700_000_000 * NS,
) -> None:
    """A bag with IMU samples at ``imu_t`` (default 2.4 s at 200 Hz) and the given clouds
    (default 24 at 10 Hz: longer than the 2 s a calibration needs).

    Record times follow the message index (IMU: its nominal time; clouds: the end of their
    nominal sweep), so unsorted or duplicated stamps stay as written in the bag.
    """
    if imu_t is None:
        imu_t = t0_ns + np.arange(480, dtype=np.int64) * 5_000_000
    if clouds is None:
        clouds = [
            (t0_ns + k * 100_000_000, velodyne_points(t0_ns + k * 100_000_000)) for k in range(24)
        ]
    gyro, accel = tilting_imu(np.arange(len(imu_t)) / 200.0)
    with BagWriter(path, fmt) as w:
        for topic in imu_topics:
            for i, t in enumerate(imu_t):
                w.write_imu(topic, int(t), gyro[i], accel[i], record_ns=t0_ns + i * 5_000_000)
        for k, (stamp, pts) in enumerate(clouds):
            # published when the sweep ends, in the original order
            w.write_cloud(cloud_topic, stamp, pts, record_ns=t0_ns + k * 100_000_000 + 99_000_000)


def read_short(path: Path, cfg: object) -> object:
    """``read_segment`` without the 2 s a calibration needs: these bags test decoding and
    validation on a few clouds."""
    from licalib_cli.io.reader import read_segment

    return read_segment(path, cfg, min_span_s=0.0)  # type: ignore[arg-type]


def organised_points(stamp_ns: int, beams: int = 16, columns: int = 128) -> np.ndarray:
    """An organised (beams x columns) Ouster-layout cloud of the box room, times from the stamp."""
    sw = spinning_sweep(stamp_ns, columns=columns, clockwise=False)
    pts = np.zeros((beams, columns), dtype=OUSTER)
    xyz = sw.xyz.reshape(columns, beams, 3).transpose(1, 0, 2)  # rows = beams
    pts["x"], pts["y"], pts["z"] = np.moveaxis(xyz, -1, 0)
    pts["t"] = (sw.t_ns - sw.start_ns).reshape(columns, beams).T
    pts["ring"] = np.arange(beams)[:, None]
    return pts


def write_bag(
    path: Path,
    fmt: BagFormat | str = "ros2-mcap",
    seconds: float = 3.0,
    imu_rate_hz: float = 200.0,
    *,
    imu: Callable[[int, int, np.ndarray, np.ndarray], Iterable[tuple]] | None = None,
    cloud: Callable[[BagWriter, int, int], object] | None = None,
    columns: int = 60,
    t0_ns: int = 1_700_000_000 * NS,
) -> Path:
    """A bag of ``seconds`` of a tilting IMU and 10 Hz velodyne clouds, to damage in tests.

    Args:
        imu: ``(index, stamp, gyro, accel) -> [(stamp, gyro, accel, record), ...]`` replaces
            each IMU message (an empty list drops it); None keeps them.
        cloud: ``(writer, index, stamp) -> message`` replaces each cloud (None drops it); the
            default writes :func:`velodyne_points` with ``columns`` columns.
    """
    n = round(seconds * imu_rate_hz)
    t = t0_ns + np.round(np.arange(n) * NS / imu_rate_hz).astype(np.int64)
    gyro, accel = tilting_imu((t - t0_ns) / NS)
    with BagWriter(path, fmt) as w:
        for i in range(n):
            out = (
                [(int(t[i]), gyro[i], accel[i], int(t[i]))]
                if imu is None
                else imu(i, int(t[i]), gyro[i], accel[i])
            )
            for stamp, g, a, rec in out:
                w.write_imu("/imu", stamp, g, a, record_ns=rec)
        for k in range(round(seconds * 10)):
            stamp = t0_ns + k * 100_000_000
            if cloud is None:
                msg = w.cloud_message(stamp, velodyne_points(stamp, columns))
            else:
                msg = cloud(w, k, stamp)
            if msg is not None:
                w.write_message("/points", CLOUD_TYPE, msg, stamp + 99_000_000)
    return path


def damage_mcap_records(path: Path, first: int, count: int) -> None:
    """Damage the opcode of ``count`` message records of an MCAP file from the ``first``
    one (in file order): the reader skips them as unknown records, silently, as it skips what
    a damaged chunk holds."""
    import struct

    data = bytearray(path.read_bytes())
    pos, seen = 8, 0
    while pos < len(data):
        op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        if op in (0x02, 0x0E, 0x0F):
            break
        if op == 0x06:  # a chunk: walk its (uncompressed) records
            p = pos + 9 + 28
            p += 4 + struct.unpack_from("<I", data, p)[0]  # compression name
            end = p + 8 + struct.unpack_from("<Q", data, p)[0]
            q = p + 8
            while q < end:
                if data[q] == 0x05:
                    if first <= seen < first + count:
                        data[q] = 0x0A
                    seen += 1
                q += 9 + struct.unpack_from("<Q", data, q + 1)[0]
        pos += 9 + length
    path.write_bytes(bytes(data))
