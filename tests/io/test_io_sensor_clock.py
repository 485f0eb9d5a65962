"""Data as a sensor publishes it before its clock is synchronised, and very short recordings:
the per-point time unit from the data's span, one cloud counted as one sweep, the first IMU
message kept, and IMU units that the data cannot tell named as assumed."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from licalib_cli.config import load_config
from licalib_cli.inspection import inspect_bag, motion_excitation
from licalib_cli.io.imu_units import GRAVITY, detect_imu_units
from licalib_cli.io.reader import read_segment
from licalib_cli.io.timestamps import classify_time_field
from licalib_cli.io.writer import BagWriter

_spec = importlib.util.spec_from_file_location(
    "licalib_test_layouts", Path(__file__).with_name("_layouts.py")
)
assert _spec is not None and _spec.loader is not None
layouts = sys.modules.get(_spec.name) or importlib.util.module_from_spec(_spec)
if _spec.name not in sys.modules:
    sys.modules[_spec.name] = layouts
    _spec.loader.exec_module(layouts)

NS = 1_000_000_000
PERIOD = 100_000_000


@pytest.mark.parametrize("stamp_s", [5.0, 278.2, 991.6, 99_000.0, 1_700_000_000.0])
def test_ouster_t_is_ns_relative_whatever_the_sensor_clock_reads(stamp_s: float) -> None:
    """``t`` in ns since the stamp spans 0-0.1 s; read as ms it would span 0-100 s and contain
    every stamp under 1e5 s: the span decides the unit, not where the stamp falls."""
    t = np.linspace(0, 99_979_000, 2048).astype(np.uint32)
    stamp = round(stamp_s * NS)
    tl = classify_time_field("t", [(stamp, t), (stamp + PERIOD, t)], PERIOD)
    assert (tl.unit, tl.reference, tl.stamp_position) == ("ns", "relative", "start")
    assert tl.warnings == ()


def test_absolute_times_on_the_stamps_clock_stay_absolute() -> None:
    stamp = 991 * NS
    v = (stamp + np.linspace(0, 99_900_000, 500)).astype(np.uint64)
    tl = classify_time_field("timestamp", [(stamp, v)], PERIOD)
    assert (tl.unit, tl.reference, tl.stamp_position) == ("ns", "absolute", "start")
    v_s = stamp / NS + np.linspace(0, 0.0999, 500)
    tl = classify_time_field("timestamp", [(stamp, v_s)], PERIOD)
    assert (tl.unit, tl.reference) == ("s", "absolute")


def _one_cloud_bag(path: Path, stamp_at_end: bool) -> Path:
    """One velodyne cloud and an IMU covering exactly its sweep (a 0.1 s bag)."""
    t0 = 1000 * NS
    sw = layouts.spinning_sweep(t0, columns=120)
    pts = layouts.fill(sw, layouts.VELODYNE)
    stamp = sw.start_ns + sw.period_ns if stamp_at_end else sw.start_ns
    pts["time"] = (sw.t_ns - stamp) / NS
    imu_t = t0 + np.arange(21, dtype=np.int64) * 5_000_000
    gyro, accel = layouts.tilting_imu((imu_t - t0) / NS)
    with BagWriter(path, "ros1") as w:
        for i, t in enumerate(imu_t):
            w.write_imu("/imu", int(t), gyro[i], accel[i], record_ns=int(t) + 1_000_000)
        w.write_cloud(
            "/velodyne_points", stamp, pts, record_ns=sw.start_ns + sw.period_ns + NS // 1000
        )
    return path


@pytest.mark.parametrize("stamp_at_end", [False, True], ids=["stamp-start", "stamp-end"])
def test_one_cloud_overlaps_the_imu_by_its_sweep(tmp_path: Path, stamp_at_end: bool) -> None:
    """The overlap is the sweep's span (0.1 s), not last minus first stamp (0 for one cloud);
    with the stamp at the sweep end the IMU lies entirely before it."""
    bag = _one_cloud_bag(tmp_path / "one.bag", stamp_at_end)
    cfg = load_config(None, {})
    rec = read_segment(bag, cfg, min_span_s=0.0)  # no "do not overlap" TimestampError
    assert len(rec.scans) == 1 and len(rec.imu) == 21
    report = inspect_bag(bag, cfg)
    errors = [p for p in report.problems if p.fatal]
    assert [p.exit_code for p in errors] == [7]
    assert "too little to calibrate" in errors[0].message
    report = inspect_bag(bag, cfg, min_span_s=0.05)
    assert report.usable, [p.message for p in report.problems if p.fatal]


def test_first_imu_message_is_kept(tmp_path: Path) -> None:
    """The first message recorded with a little more latency than the others maps, with the
    median stamp-to-record offset, to just before the bag's first record time."""
    n = 600

    def imu(i: int, stamp: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
        latency = 1_021_000 if i == 0 else 1_000_000
        return [(stamp, g, a, stamp + latency)]

    bag = layouts.write_bag(tmp_path / "b.bag", "ros1", seconds=3.0, imu=imu)
    cfg = load_config(None, {})
    report = inspect_bag(bag, cfg)
    assert report.imu is not None and report.imu.count == n
    assert len(read_segment(bag, cfg).imu) == n
    # a later segment start still cuts at its start
    later = load_config(None, {"bag.start_s": 0.5})
    assert len(read_segment(bag, later, min_span_s=0.0).imu) < n


def _still_imu(seconds: float, g_units: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    n = round(seconds * 100) + 1
    t = 991 * NS + np.arange(n, dtype=np.int64) * 10_000_000
    gyro = np.radians(1.5) * rng.standard_normal((n, 3))  # a still rig: about 1.5 deg/s noise
    accel = np.array([0.3, 0.1, GRAVITY]) + 0.05 * rng.standard_normal((n, 3))
    if g_units:
        return t, np.degrees(gyro), accel / GRAVITY
    return t, gyro, accel


def test_gyro_unit_from_a_g_accelerometer_on_too_little_data() -> None:
    t, gyro, accel = _still_imu(0.1, g_units=True)
    u = detect_imu_units(gyro, accel, t_ns=t)
    assert (u.accel_unit, u.accel_source) == ("g", "detected")
    assert (u.gyro_unit, u.gyro_source) == ("deg/s", "assumed") and u.too_short
    (warning,) = u.warnings()
    assert warning.startswith("0.10 s of IMU data is too little to tell the gyro unit")
    assert "assumed deg/s as the accelerometer reads g" in warning
    assert "`imu.gyro_unit: rad/s`" in warning and warning.count(". ") == 0
    assert u.gyro_assumption == "gyro unit assumed deg/s"
    # SI data: rad/s, as ROS specifies, also said to be assumed
    t, gyro, accel = _still_imu(0.29, g_units=False)
    u = detect_imu_units(gyro, accel, t_ns=t)
    assert (u.gyro_unit, u.gyro_source, u.too_short) == ("rad/s", "assumed", True)
    assert "too little to tell" in u.warnings()[0]
    # the config settles it: nothing assumed, nothing to warn about
    u = detect_imu_units(gyro, accel, gyro_override="rad/s", t_ns=t)
    assert u.gyro_source == "config" and u.warnings() == [] and u.gyro_assumption is None


def test_motion_claims_name_the_assumed_gyro_unit() -> None:
    rng = np.random.default_rng(1)
    w = rng.standard_normal((200, 3))  # "rad/s": a rate of deg/s data read as rad/s
    a = np.tile([0.0, 0.0, GRAVITY], (200, 1))
    e = motion_excitation(w, a, "gyro unit assumed rad/s")
    assert e.summary.startswith("rotation about all three axes (RMS")
    assert "gyro unit assumed rad/s): the extrinsic is fully observable" in e.summary
    assert "assumed" not in motion_excitation(w, a).summary
