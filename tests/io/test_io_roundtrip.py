"""IMU and clouds written in every format are read back exactly, through one code path."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from _layouts import (
    NS,
    VELODYNE,
    fill,
    read_short,
    spinning_sweep,
    write_imu_stream,
    write_velodyne_bag,
)

from licalib_cli.config import load_config
from licalib_cli.errors import BagError, ConfigError, DataError
from licalib_cli.io.bag import bag_paths, open_bag
from licalib_cli.io.reader import iter_scans, read_imu
from licalib_cli.io.writer import BagWriter

FORMATS = ["ros1", "ros2-db3", "ros2-mcap"]
T0 = 1_700_000_000 * NS


def _bag(tmp_path: Path, fmt: str) -> Path:
    return tmp_path / ("x.bag" if fmt == "ros1" else "x")


@pytest.mark.parametrize("fmt", FORMATS)
def test_roundtrip_exact(tmp_path: Path, fmt: str) -> None:
    path = _bag(tmp_path, fmt)
    with BagWriter(path, fmt) as w:
        t, gyro, accel = write_imu_stream(w, T0, 1.2, 400.0)
        sweeps = []
        for k in range(10):
            sw = spinning_sweep(T0 + k * 100_000_000, columns=120)
            pts = fill(sw, VELODYNE)
            pts["time"] = (sw.t_ns - sw.start_ns) / NS
            w.write_cloud("/points", sw.start_ns, pts, record_ns=int(sw.t_ns[-1]))
            sweeps.append((sw, pts))
    rec = read_short(path, load_config(None, {"lidar.min_range_m": 0.0}))
    assert rec.imu.t_ns.dtype == np.int64
    np.testing.assert_array_equal(rec.imu.t_ns, t)
    np.testing.assert_array_equal(rec.imu.gyro, gyro)
    np.testing.assert_array_equal(rec.imu.accel, accel)
    assert len(rec.scans) == 10
    for scan, (sw, pts) in zip(rec.scans, sweeps, strict=True):
        assert scan.stamp_ns == sw.start_ns
        np.testing.assert_array_equal(scan.xyz, np.stack([pts["x"], pts["y"], pts["z"]], 1))
        assert scan.t_ns.dtype == np.int64
        assert np.abs(scan.t_ns - sw.t_ns).max() <= 10  # float32 seconds -> ns rounding
        np.testing.assert_array_equal(scan.ring, pts["ring"])
        np.testing.assert_array_equal(scan.intensity, pts["intensity"])
    # the clouds are recorded at their last point, like a driver publishing each sweep
    assert abs(rec.clock_offset_ns) < 1_000_000 and rec.lidar_shift_ns == 0
    assert rec.imu_topic == "/imu" and rec.lidar_topic == "/points"


@pytest.mark.parametrize("fmt", FORMATS)
def test_iter_scans_matches_read_short(tmp_path: Path, fmt: str) -> None:
    path = _bag(tmp_path, fmt)
    write_velodyne_bag(path, fmt, n_clouds=6)
    cfg = load_config(None)
    rec = read_short(path, cfg)
    streamed = list(iter_scans(path, cfg))
    assert len(streamed) == len(rec.scans) == 6
    for a, b in zip(streamed, rec.scans, strict=True):
        assert a.stamp_ns == b.stamp_ns
        np.testing.assert_array_equal(a.t_ns, b.t_ns)


def test_split_ros1_folder(tmp_path: Path) -> None:
    folder = tmp_path / "split"
    folder.mkdir()
    with BagWriter(folder / "a_0.bag", "ros1") as w:
        t_a, _, _ = write_imu_stream(w, T0, 0.6)
    with BagWriter(folder / "a_1.bag", "ros1") as w:
        t_b, _, _ = write_imu_stream(w, T0 + 600_000_000, 0.6)
    assert [p.name for p in bag_paths(folder)] == ["a_0.bag", "a_1.bag"]
    imu, _, _ = read_imu(folder, load_config(None))
    np.testing.assert_array_equal(imu.t_ns, np.concatenate([t_a, t_b]))


@pytest.mark.parametrize("fmt,suffix", [("ros2-db3", ".db3"), ("ros2-mcap", ".mcap")])
def test_bare_storage_file(tmp_path: Path, fmt: str, suffix: str) -> None:
    folder = tmp_path / "x"
    write_velodyne_bag(folder, fmt, n_clouds=4)
    bare = tmp_path / f"bare{suffix}"
    shutil.copy(next(folder.glob(f"*{suffix}")), bare)
    rec_folder = read_short(folder, load_config(None))
    rec_bare = read_short(bare, load_config(None))
    np.testing.assert_array_equal(rec_folder.imu.t_ns, rec_bare.imu.t_ns)
    assert len(rec_bare.scans) == 4
    with open_bag(bare) as bag:
        assert bag.format == fmt


def test_window_selects_by_header_stamp(tmp_path: Path) -> None:
    """Record times lag the stamps by 30 ms; the segment follows the stamps."""
    path = tmp_path / "x"
    with BagWriter(path, "ros2-mcap") as w:
        for i in range(400):
            t = T0 + i * 5_000_000
            w.write_imu("/imu", t, [0.3, 0, 0], [0, 0, 9.8], record_ns=t + 30_000_000)
        for k in range(20):
            sw = spinning_sweep(T0 + k * 100_000_000, columns=60)
            pts = fill(sw, VELODYNE)
            pts["time"] = (sw.t_ns - sw.start_ns) / NS
            w.write_cloud("/points", sw.start_ns, pts, record_ns=sw.start_ns + 40_000_000)
    cfg = load_config(None, {"bag.start_s": 0.5, "bag.duration_s": 0.5})
    rec = read_short(path, cfg)
    # first record time is T0 + 30 ms, so the window is [T0 + 0.5 s, T0 + 1.0 s) in stamps
    assert rec.imu.t_ns[0] == T0 + 500_000_000
    assert rec.imu.t_ns[-1] == T0 + 995_000_000
    assert [s.stamp_ns for s in rec.scans] == [T0 + k * 100_000_000 for k in range(5, 10)]
    assert rec.start_ns == T0 + 500_000_000 and rec.end_ns == T0 + 1_000_000_000


def test_coarse_clock_offset_shifts_lidar(tmp_path: Path) -> None:
    """LiDAR on UNIX time, IMU on boot time: reported and shifted into the IMU clock."""
    path = tmp_path / "x"
    boot = 5_000 * NS
    with BagWriter(path, "ros2-mcap") as w:
        for i in range(300):
            t = T0 + i * 5_000_000
            w.write_imu("/imu", t - T0 + boot, [0.3, 0, 0], [0, 0, 9.8], record_ns=t)
        for k in range(10):
            sw = spinning_sweep(T0 + k * 100_000_000, columns=60)
            pts = fill(sw, VELODYNE)
            pts["time"] = (sw.t_ns - sw.start_ns) / NS
            w.write_cloud("/points", sw.start_ns, pts, record_ns=int(sw.t_ns[-1]) + 2_000_000)
    rec = read_short(path, load_config(None))
    # coarse: good to the 2 ms publication latency of the clouds
    assert abs(rec.clock_offset_ns - (boot - T0)) <= 2_000_000
    assert rec.lidar_shift_ns == rec.clock_offset_ns
    assert rec.scans[0].stamp_ns == T0 + rec.lidar_shift_ns
    assert abs(rec.scans[0].stamp_ns - boot) <= 2_000_000
    assert any("use different clocks" in w for w in rec.warnings)


def test_missing_and_not_a_bag(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="does not exist"):
        bag_paths(tmp_path / "nope.bag")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(BagError, match="not a bag"):
        bag_paths(tmp_path / "notes.txt")
    (tmp_path / "d").mkdir()
    with pytest.raises(BagError, match="is not a bag"):
        bag_paths(tmp_path / "d")


def test_imu_units_detected_in_bag_and_overridden(tmp_path: Path) -> None:
    path = tmp_path / "x"
    with BagWriter(path, "ros2-db3") as w:
        _, gyro, accel = write_imu_stream(w, T0, 1.2, 200.0, np.rad2deg(1.0), 1 / 9.80665)
        for k in range(10):
            sw = spinning_sweep(T0 + k * 100_000_000, columns=60)
            pts = fill(sw, VELODYNE)
            pts["time"] = (sw.t_ns - sw.start_ns) / NS
            w.write_cloud("/points", sw.start_ns, pts)
    rec = read_short(path, load_config(None))
    assert (rec.imu_units.gyro_unit, rec.imu_units.accel_unit) == ("deg/s", "g")
    np.testing.assert_allclose(rec.imu.gyro, np.deg2rad(gyro), rtol=1e-12)
    np.testing.assert_allclose(rec.imu.accel, accel * 9.80665, rtol=1e-12)
    assert any("deg/s" in w for w in rec.warnings) and any("in g" in w for w in rec.warnings)
    cfg = load_config(None, {"imu.gyro_unit": "deg/s", "imu.accel_unit": "g"})
    rec = read_short(path, cfg)
    assert (rec.imu_units.gyro_source, rec.imu_units.accel_source) == ("config", "config")
    np.testing.assert_allclose(rec.imu.gyro, np.deg2rad(gyro), rtol=1e-12)
    # A gyro override the tilting contradicts is refused, naming the unit the data are in.
    cfg = load_config(None, {"imu.gyro_unit": "rad/s"})
    with pytest.raises(ConfigError, match=r"gravity turns .* set imu.gyro_unit: deg/s, or remove"):
        read_short(path, cfg)
    # An accelerometer override that leaves no gravity is refused, naming the setting.
    cfg = load_config(None, {"imu.accel_unit": "m/s^2"})
    with pytest.raises(
        DataError, match=r"reads no gravity \(median \|a\| 1 m/s\^2.*`imu.accel_unit`"
    ):
        read_short(path, cfg)
