"""Driver point layouts decode to the right xyz, absolute per-point times, rings and layout.

The exact field layouts (names, datatypes, offsets, point_step) and stamp conventions of each
driver are documented, with their sources, in ``tests/io/_layouts.py``:
velodyne_pointcloud PointcloudXYZIRT (packed, point_step 22) and velodyne_pcl::PointXYZIRT
(point_step 32); ouster-ros ouster_ros::Point (point_step 48, organised) and Point_LEGACY;
HesaiLidar_ROS_2.0 and rslidar_sdk XYZIRT (packed, point_step 26, timestamp f64 s);
livox_ros_driver2 PointCloud2 xfer_format 0 (packed, point_step 26, timestamp f64 ns);
livox_ros_driver v1 PointCloud2 (point_step 18, no time field); Livox CustomMsg converted to
PointCloud2 (offset_time u32 ns, point_step 24).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from _layouts import (
    HESAI,
    LIVOX1,
    LIVOX2,
    LIVOX_OFFSET,
    NS,
    OUSTER,
    OUSTER_LEGACY,
    ROBOSENSE,
    VELODYNE,
    VELODYNE_PCL,
    XYZI,
    box_ranges,
    dtype_of,
    fill,
    read_short,
    spinning_sweep,
    tilting_imu,
    write_imu_stream,
)

from licalib_cli.config import load_config
from licalib_cli.errors import ConfigError
from licalib_cli.io.writer import BagWriter

T0 = 1_700_000_000 * NS
PERIOD = 100_000_000
N_CLOUDS = 4


@dataclass
class Truth:
    """One written cloud: message points and the expected decoded values (message order)."""

    points: np.ndarray  # structured, (N,) or (H, W)
    stamp_ns: int
    xyz: np.ndarray  # (M, 3) expected valid points
    t_ns: np.ndarray  # (M,)
    ring: np.ndarray | None  # (M,)


def _velodyne(k: int, dt: np.dtype) -> Truth:
    sw = spinning_sweep(T0 + k * PERIOD, columns=180)
    stamp = sw.start_ns + PERIOD  # velodyne_pointcloud: stamp of the last packet
    pts = fill(sw, dt)
    pts["time"] = (sw.t_ns - stamp) / NS
    return Truth(pts, stamp, sw.xyz, sw.t_ns, sw.ring)


def _ouster(k: int, dt: np.dtype) -> Truth:
    beams, cols = 16, 128
    sw = spinning_sweep(T0 + k * PERIOD, columns=cols, clockwise=False)
    grid = sw.xyz.reshape(cols, beams, 3)
    tgrid = sw.t_ns.reshape(cols, beams)
    # organised rows = rings, ring 0 = top beam (ouster convention)
    xyz = np.stack([grid[:, beams - 1 - r] for r in range(beams)])  # (beams, cols, 3)
    t = np.stack([tgrid[:, beams - 1 - r] for r in range(beams)])
    ring = np.repeat(np.arange(beams)[:, None], cols, axis=1)
    missing = np.zeros((beams, cols), bool)
    missing[::3, ::5] = True  # no return -> (0, 0, 0)
    nan = np.zeros((beams, cols), bool)
    nan[1::4, 2::7] = True
    pts = np.zeros((beams, cols), dtype=dt)
    pts["x"], pts["y"], pts["z"] = np.moveaxis(np.where(missing[..., None], 0.0, xyz), -1, 0)
    pts["x"][nan] = np.nan
    pts["t"] = t - sw.start_ns
    pts["ring"] = ring
    if "intensity" in (dt.names or ()):
        pts["intensity"] = 5.0
    valid = ~missing & ~nan
    return Truth(pts, sw.start_ns, xyz[valid], t[valid], ring[valid])


def _absolute_seconds(k: int, dt: np.dtype, at_end: bool) -> Truth:
    sw = spinning_sweep(T0 + k * PERIOD, columns=180, beams_deg=np.linspace(-25, 15, 32))
    pts = fill(sw, dt)
    pts["timestamp"] = sw.t_ns / NS  # float64 absolute seconds
    stamp = int(sw.t_ns[-1]) if at_end else int(sw.t_ns[0])
    return Truth(pts, stamp, sw.xyz, sw.t_ns, sw.ring)


def _livox_cone(k: int, n: int = 3000) -> tuple[np.ndarray, np.ndarray, int]:
    rng = np.random.default_rng(k)
    az = np.deg2rad(rng.uniform(-35, 35, n))
    el = np.deg2rad(rng.uniform(-35, 35, n))
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    xyz = dirs * box_ranges(dirs)[:, None]
    start = T0 + k * PERIOD
    t = start + np.round(np.arange(n) / (n - 1) * PERIOD).astype(np.int64)
    return xyz, t, start


def _livox2(k: int) -> Truth:
    xyz, t, start = _livox_cone(k)
    pts = np.zeros(xyz.shape[0], LIVOX2)
    pts["x"], pts["y"], pts["z"] = xyz.T
    pts["line"] = np.arange(xyz.shape[0]) % 4
    pts["timestamp"] = t.astype(np.float64)  # absolute ns as double
    return Truth(pts, start, xyz, t, pts["line"].astype(np.int64))


def _livox_offset(k: int) -> Truth:
    xyz, t, start = _livox_cone(k)
    pts = np.zeros(xyz.shape[0], LIVOX_OFFSET)
    pts["x"], pts["y"], pts["z"] = xyz.T
    pts["line"] = np.arange(xyz.shape[0]) % 4
    pts["tag"] = 0x10
    pts["offset_time"] = t - start  # ns since the timebase (= header stamp)
    return Truth(pts, start, xyz, t, pts["line"].astype(np.int64))


def _livox1(k: int) -> Truth:
    xyz, t, start = _livox_cone(k)
    pts = np.zeros(xyz.shape[0], LIVOX1)
    pts["x"], pts["y"], pts["z"] = xyz.T
    pts["line"] = np.arange(xyz.shape[0]) % 4
    return Truth(pts, start, xyz, t, pts["line"].astype(np.int64))


def _xyzi(k: int) -> Truth:
    sw = spinning_sweep(T0 + k * PERIOD, columns=360, azimuth0_deg=40.0)
    pts = fill(sw, XYZI)
    return Truth(pts, sw.start_ns, sw.xyz, sw.t_ns, sw.ring)


@dataclass(frozen=True)
class Case:
    name: str
    make: object
    fmt: str
    expect: tuple  # (time_field, unit, reference, stamp_position)
    t_tol_ns: int = 1_000
    row_padding: int = 0


CASES = [
    Case("velodyne", lambda k: _velodyne(k, VELODYNE), "ros1", ("time", "s", "relative", "end")),
    Case(
        "velodyne_pcl_bigendian",
        lambda k: _velodyne(k, dtype_of(VELODYNE_PCL, 32, big=True)),
        "ros2-mcap",
        ("time", "s", "relative", "end"),
    ),
    Case("ouster", lambda k: _ouster(k, OUSTER), "ros2-db3", ("t", "ns", "relative", "start")),
    Case(
        "ouster_row_padding",
        lambda k: _ouster(k, OUSTER),
        "ros1",
        ("t", "ns", "relative", "start"),
        row_padding=24,
    ),
    Case(
        "ouster_legacy",
        lambda k: _ouster(k, OUSTER_LEGACY),
        "ros2-mcap",
        ("t", "ns", "relative", "start"),
    ),
    Case(
        "hesai",
        lambda k: _absolute_seconds(k, HESAI, at_end=False),
        "ros2-mcap",
        ("timestamp", "s", "absolute", "start"),
    ),
    Case(
        "robosense",
        lambda k: _absolute_seconds(k, ROBOSENSE, at_end=True),
        "ros1",
        ("timestamp", "s", "absolute", "end"),
    ),
    Case("livox2", _livox2, "ros2-mcap", ("timestamp", "ns", "absolute", "start")),
    Case(
        "livox_offset_time",
        _livox_offset,
        "ros2-db3",
        ("offset_time", "ns", "relative", "start"),
    ),
    Case("livox1", _livox1, "ros2-mcap", (None, None, "estimated", "start")),
]


def _write(path: Path, case: Case) -> list[Truth]:
    truths = [case.make(k) for k in range(N_CLOUDS)]
    with BagWriter(path, case.fmt) as w:
        write_imu_stream(w, T0 - 50_000_000, N_CLOUDS * 0.1 + 0.2)
        for tr in truths:
            w.write_cloud("/points", tr.stamp_ns, tr.points, row_padding=case.row_padding)
    return truths


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_driver_layout_decodes(tmp_path: Path, case: Case) -> None:
    path = tmp_path / ("x.bag" if case.fmt == "ros1" else "x")
    truths = _write(path, case)
    rec = read_short(path, load_config(None, {"lidar.min_range_m": 0.0}))
    tl = rec.layout.time
    assert (tl.field, tl.unit, tl.reference, tl.stamp_position) == case.expect
    assert len(rec.scans) == N_CLOUDS
    for scan, tr in zip(rec.scans, truths, strict=True):
        assert scan.stamp_ns == tr.stamp_ns
        assert scan.xyz.shape == tr.xyz.shape
        np.testing.assert_allclose(scan.xyz, tr.xyz, atol=2e-6 * 20)  # float32 storage
        assert np.abs(scan.t_ns - tr.t_ns).max() <= case.t_tol_ns
        assert scan.ring is not None and tr.ring is not None
        np.testing.assert_array_equal(scan.ring, tr.ring)


def test_ouster_organised_layout_reported(tmp_path: Path) -> None:
    path = tmp_path / "o"
    _write(path, next(c for c in CASES if c.name == "ouster"))
    rec = read_short(path, load_config(None))
    lay = rec.layout
    assert (lay.height, lay.width, lay.point_step, lay.ring_field, lay.beams) == (
        16,
        128,
        48,
        "ring",
        16,
    )
    assert lay.fields[:5] == ("x:f4", "y:f4", "z:f4", "intensity:f4", "t:u4")
    assert lay.points_per_scan == 16 * 128
    # zeros and NaN removed together with their times and rings
    assert lay.valid_points_per_scan < lay.points_per_scan


def test_no_time_field_azimuth_estimate_and_beams_from_elevation(tmp_path: Path) -> None:
    path = tmp_path / "x"
    truths = _write(path, Case("xyzi", _xyzi, "ros2-mcap", ()))
    rec = read_short(path, load_config(None, {"lidar.min_range_m": 0.0}))
    tl = rec.layout.time
    assert (tl.field, tl.reference, tl.method, tl.clockwise) == (None, "estimated", "azimuth", True)
    assert rec.layout.ring_field is None and rec.layout.beams == 16
    for scan, tr in zip(rec.scans, truths, strict=True):
        err = np.abs(scan.t_ns - tr.t_ns)
        # within 1 % of the scan period (0.1 s) for every point
        assert err.max() <= 0.01 * PERIOD
        np.testing.assert_array_equal(scan.ring, tr.ring)  # ring 0 = lowest beam


def test_no_time_field_stamp_at_end_override(tmp_path: Path) -> None:
    path = tmp_path / "x"
    truths = _write(path, Case("xyzi", _xyzi, "ros2-mcap", ()))
    cfg = load_config(None, {"lidar.stamp_position": "end", "lidar.min_range_m": 0.0})
    rec = read_short(path, cfg)
    for scan, tr in zip(rec.scans, truths, strict=True):
        # stamps are at the sweep start, so "end" shifts every time one period earlier
        assert np.abs(scan.t_ns - (tr.t_ns - PERIOD)).max() <= 0.01 * PERIOD


def test_livox_v1_index_estimate(tmp_path: Path) -> None:
    path = tmp_path / "x"
    truths = _write(path, next(c for c in CASES if c.name == "livox1"))
    rec = read_short(path, load_config(None, {"lidar.min_range_m": 0.0}))
    assert rec.layout.time.method == "index"
    assert rec.layout.ring_field == "line" and rec.layout.beams == 4
    for scan, tr in zip(rec.scans, truths, strict=True):
        assert np.abs(scan.t_ns - tr.t_ns).max() <= 1_000


def test_time_overrides(tmp_path: Path) -> None:
    """Config forces the unit; one the data contradict (a sweep of 100 s at 10 Hz where another
    unit gives 0.1 s) is refused, naming the unit that fits."""
    path = tmp_path / "x"
    truths = _write(path, next(c for c in CASES if c.name == "ouster"))
    cfg = load_config(None, {"lidar.time_unit": "ns", "lidar.min_range_m": 0.0})
    rec = read_short(path, cfg)
    assert rec.layout.time.unit == "ns" and "time unit 'ns' set in the config" in (
        rec.layout.time.notes
    )
    tr = truths[1]
    np.testing.assert_array_equal(rec.scans[1].t_ns, tr.t_ns)
    for wrong, span in (("us", "9.92e+04 ms"), ("ms", "9.92e+07 ms")):
        cfg = load_config(None, {"lidar.time_unit": wrong, "lidar.min_range_m": 0.0})
        with pytest.raises(ConfigError) as info:
            read_short(path, cfg)
        assert str(info.value) == (
            f"lidar.time_unit '{wrong}' makes the points of a cloud span {span} of its 100 ms "
            "sweep; read in ns they span 99.2 ms: set lidar.time_unit: ns, or remove it to "
            "detect the unit."
        )
    # the detected layout has no warning
    assert read_short(path, load_config(None)).layout.time.warnings == ()


def _case(name: str) -> Case:
    return next(c for c in CASES if c.name == name)


def test_time_reference_override_is_obeyed_and_flagged(tmp_path: Path) -> None:
    """Absolute Hesai seconds forced relative: stamp + value, far from the stamp, warned."""
    path = tmp_path / "x"
    truths = _write(path, _case("hesai"))
    cfg = load_config(None, {"lidar.time_reference": "relative", "lidar.min_range_m": 0.0})
    rec = read_short(path, cfg)
    tl = rec.layout.time
    assert (tl.field, tl.unit, tl.reference) == ("timestamp", "s", "relative")
    assert "time reference 'relative' set in the config" in tl.notes
    tr = truths[2]
    expected = tr.stamp_ns + np.round(tr.points["timestamp"] * NS).astype(np.int64)
    np.testing.assert_array_equal(rec.scans[2].t_ns, expected)
    (warning,) = tl.warnings
    assert warning.startswith("Per-point times ('timestamp') lie 1.7e+09 s from the header")
    assert "`lidar.time_unit` and `lidar.time_reference`" in warning
    assert warning in rec.warnings


def test_wrong_unit_and_reference_overrides_are_reported_by_info(tmp_path: Path) -> None:
    """On a Hesai bag (absolute seconds): the wrong ``time_unit: ns`` is refused, naming the
    unit that fits; the wrong ``time_reference: relative`` is obeyed and warned about."""
    from licalib_cli.inspection import inspect_bag

    path = tmp_path / "x"
    _write(path, _case("hesai"))
    cfg = load_config(None, {"lidar.time_unit": "ns", "lidar.time_reference": "absolute"})
    report = inspect_bag(path, cfg, min_span_s=0.0)
    assert not report.usable
    (fatal,) = [p for p in report.problems if p.fatal]
    assert fatal.error is ConfigError and fatal.message.startswith("lidar.time_unit 'ns' makes")
    assert "set lidar.time_unit: s, or remove it" in fatal.message
    cfg = load_config(None, {"lidar.time_reference": "relative"})
    report = inspect_bag(path, cfg, min_span_s=0.0)
    assert report.usable  # a warning: the reference is obeyed
    messages = [p.message for p in report.problems if not p.fatal]
    assert any(
        m.startswith("Per-point times ('timestamp') lie 1.7e+09 s from the header stamps")
        for m in messages
    ), messages
    detected = inspect_bag(path, load_config(None), min_span_s=0.0)
    assert not [p for p in detected.problems if "Per-point" in p.message]


def _channel_cloud(k: int) -> Truth:
    """Velodyne-like cloud whose beam index is in a 'channel' field, numbered top first."""
    sw = spinning_sweep(T0 + k * PERIOD, columns=90, ring_top_first=True)
    dt = dtype_of(
        [
            ("x", "f4", 0),
            ("y", "f4", 4),
            ("z", "f4", 8),
            ("intensity", "f4", 12),
            ("channel", "u2", 16),
            ("time", "f4", 18),
        ],
        22,
    )
    pts = fill(sw, dt)
    pts["channel"] = sw.ring
    pts["time"] = (sw.t_ns - sw.start_ns) / NS
    return Truth(pts, sw.start_ns, sw.xyz, sw.t_ns, sw.ring)


def test_ring_field_override(tmp_path: Path) -> None:
    path = tmp_path / "x"
    truths = _write(path, Case("channel", _channel_cloud, "ros2-mcap", ()))
    base = {"lidar.min_range_m": 0.0}
    # not a known beam field name: beams recovered from elevation, ring 0 = lowest
    rec = read_short(path, load_config(None, base))
    assert rec.layout.ring_field is None and rec.layout.beams == 16
    lowest_first = 15 - truths[0].ring
    np.testing.assert_array_equal(rec.scans[0].ring, lowest_first)
    # named in the config: the driver's own numbering is used
    rec = read_short(path, load_config(None, {**base, "lidar.ring_field": "channel"}))
    assert rec.layout.ring_field == "channel" and rec.layout.beams == 16
    for scan, tr in zip(rec.scans, truths, strict=True):
        np.testing.assert_array_equal(scan.ring, tr.ring)
    # `none` ignores a ring field that is present
    path2 = tmp_path / "v.bag"
    _write(path2, _case("velodyne"))
    rec = read_short(path2, load_config(None, {**base, "lidar.ring_field": "none"}))
    assert rec.layout.ring_field is None and rec.layout.beams == 16


@pytest.mark.parametrize("fmt", ["ros1", "ros2-db3"])
def test_ouster_bigendian_padded_bag_written_with_rosbags(tmp_path: Path, fmt: str) -> None:
    """A bag written by rosbags itself (not licalib's writer): organised big-endian Ouster
    clouds with 16 bytes of garbage at the end of every row, and IMU messages."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    ros1 = fmt == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ty = ts.types
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    big = dtype_of(
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
        big=True,
    )
    codes = {"f4": 7, "u4": 6, "u2": 4}
    fields = [
        ty["sensor_msgs/msg/PointField"](
            name=name,
            offset=big.fields[name][1],
            datatype=codes[big.fields[name][0].str[1:]],
            count=1,
        )
        for name in big.names
    ]
    pad = 16

    def header(seq: int, t_ns: int, frame: str) -> object:
        sec, nsec = divmod(t_ns, NS)
        stamp = ty["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        if ros1:
            return ty["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame)
        return ty["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    truths = [_ouster(k, big) for k in range(N_CLOUDS)]
    t_imu = T0 - 50_000_000 + np.arange(120, dtype=np.int64) * 5_000_000
    gyro, accel = tilting_imu((t_imu - t_imu[0]) / NS)
    path = tmp_path / ("x.bag" if ros1 else "x")
    writer = (
        Writer1(path)
        if ros1
        else Writer2(path, version=Writer2.VERSION_LATEST, storage_plugin=StoragePlugin.SQLITE3)
    )
    vec3 = ty["geometry_msgs/msg/Vector3"]
    with writer:
        c_imu = writer.add_connection("/os/imu", "sensor_msgs/msg/Imu", typestore=ts)
        c_pts = writer.add_connection("/os/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        events = [(int(t), "imu", i) for i, t in enumerate(t_imu)]
        events += [(tr.stamp_ns + PERIOD, "cloud", k) for k, tr in enumerate(truths)]
        for rec_ns, kind, i in sorted(events):
            if kind == "imu":
                msg = ty["sensor_msgs/msg/Imu"](
                    header=header(i, rec_ns, "os_imu"),
                    orientation=ty["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.zeros(9),
                    angular_velocity=vec3(x=gyro[i, 0], y=gyro[i, 1], z=gyro[i, 2]),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=vec3(x=accel[i, 0], y=accel[i, 1], z=accel[i, 2]),
                    linear_acceleration_covariance=np.zeros(9),
                )
                writer.write(c_imu, rec_ns, ser(msg, "sensor_msgs/msg/Imu"))
                continue
            tr = truths[i]
            h, w = tr.points.shape
            rows = np.full((h, w * big.itemsize + pad), 0xAB, dtype=np.uint8)
            rows[:, : w * big.itemsize] = tr.points.view(np.uint8).reshape(h, -1)
            msg = ty["sensor_msgs/msg/PointCloud2"](
                header=header(i, tr.stamp_ns, "os_sensor"),
                height=h,
                width=w,
                fields=fields,
                is_bigendian=True,
                point_step=big.itemsize,
                row_step=w * big.itemsize + pad,
                data=rows.reshape(-1),
                is_dense=False,
            )
            writer.write(c_pts, rec_ns, ser(msg, "sensor_msgs/msg/PointCloud2"))

    rec = read_short(path, load_config(None, {"lidar.min_range_m": 0.0}))
    lay = rec.layout
    assert (lay.is_bigendian, lay.height, lay.width, lay.point_step) == (True, 16, 128, 48)
    assert (lay.time.field, lay.time.unit, lay.time.reference) == ("t", "ns", "relative")
    assert lay.ring_field == "ring" and lay.beams == 16
    assert rec.imu_topic == "/os/imu" and len(rec.imu.t_ns) == 120
    np.testing.assert_allclose(rec.imu.gyro, gyro, rtol=1e-12)
    assert len(rec.scans) == N_CLOUDS
    for scan, tr in zip(rec.scans, truths, strict=True):
        assert scan.stamp_ns == tr.stamp_ns
        np.testing.assert_allclose(scan.xyz, tr.xyz, atol=4e-5)
        np.testing.assert_array_equal(scan.t_ns, tr.t_ns)
        np.testing.assert_array_equal(scan.ring, tr.ring)
