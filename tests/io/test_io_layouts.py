"""Driver point layouts decode to the right xyz, absolute per-point times, rings and layout.

The exact field layouts (names, datatypes, offsets, point_step) and stamp conventions of each
driver are documented, with their sources, in ``tests/io/_layouts.py``:
velodyne_pointcloud PointcloudXYZIRT (packed, point_step 22) and velodyne_pcl::PointXYZIRT
(point_step 32); ouster-ros ouster_ros::Point (point_step 48, organised) and Point_LEGACY;
HesaiLidar_ROS_2.0 and rslidar_sdk XYZIRT (packed, point_step 26, timestamp f64 s);
livox_ros_driver2 PointCloud2 xfer_format 0 (packed, point_step 26, timestamp f64 ns);
livox_ros_driver v1 PointCloud2 (point_step 18, no time field).
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
    spinning_sweep,
    write_imu_stream,
)

from licalib_cli.config import load_config
from licalib_cli.io.reader import read_segment
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
    rec = read_segment(path, load_config(None, {"lidar.min_range_m": 0.0}))
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
    _write(path, CASES[2])
    rec = read_segment(path, load_config(None))
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
    rec = read_segment(path, load_config(None, {"lidar.min_range_m": 0.0}))
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
    rec = read_segment(path, cfg)
    for scan, tr in zip(rec.scans, truths, strict=True):
        # stamps are at the sweep start, so "end" shifts every time one period earlier
        assert np.abs(scan.t_ns - (tr.t_ns - PERIOD)).max() <= 0.01 * PERIOD


def test_livox_v1_index_estimate(tmp_path: Path) -> None:
    path = tmp_path / "x"
    truths = _write(path, CASES[-1])
    rec = read_segment(path, load_config(None, {"lidar.min_range_m": 0.0}))
    assert rec.layout.time.method == "index"
    assert rec.layout.ring_field == "line" and rec.layout.beams == 4
    for scan, tr in zip(rec.scans, truths, strict=True):
        assert np.abs(scan.t_ns - tr.t_ns).max() <= 1_000


def test_time_overrides(tmp_path: Path) -> None:
    """Config forces the unit/reference; a wrong override gives wrong times (it is obeyed)."""
    path = tmp_path / "x"
    truths = _write(path, CASES[2])
    cfg = load_config(None, {"lidar.time_unit": "us", "lidar.min_range_m": 0.0})
    rec = read_segment(path, cfg)
    assert rec.layout.time.unit == "us"
    tr = truths[1]
    rel = tr.t_ns - tr.stamp_ns
    np.testing.assert_array_equal(rec.scans[1].t_ns - tr.stamp_ns, rel * 1000)
