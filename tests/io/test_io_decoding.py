"""Unit tests: PointCloud2 views, time-field classification, estimation, beams, IMU units."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from _layouts import NS, OUSTER, spinning_sweep, tilting_imu

from licalib_cli.errors import ConfigError, DataError, TimestampError
from licalib_cli.io.imu_units import GRAVITY, convert_imu, detect_imu_units
from licalib_cli.io.pointcloud2 import decode_cloud, to_structured, valid_mask
from licalib_cli.io.timestamps import (
    assign_beams,
    classify_time_field,
    detect_beams,
    estimate_times,
    find_time_field,
    time_values_to_ns,
)

T0 = 1_700_000_000 * NS
_CODES = {("f", 4): 7, ("f", 8): 8, ("u", 4): 6, ("u", 2): 4, ("u", 1): 2}


def _msg(pts: np.ndarray, row_padding: int = 0) -> SimpleNamespace:
    """A PointCloud2-like object built the way a driver fills the message."""
    pts = pts.reshape(1, -1) if pts.ndim == 1 else pts
    h, w = pts.shape
    dt = pts.dtype
    fields = [
        SimpleNamespace(
            name=n,
            offset=dt.fields[n][1],
            count=1,
            datatype=_CODES[(dt.fields[n][0].kind, dt.fields[n][0].itemsize)],
        )
        for n in dt.names
    ]
    row_step = w * dt.itemsize + row_padding
    rows = np.full((h, row_step), 0xAB, np.uint8)  # padding bytes are garbage
    rows[:, : w * dt.itemsize] = np.ascontiguousarray(pts).view(np.uint8).reshape(h, -1)
    big = dt.fields["x"][0].byteorder == ">"
    data = rows.reshape(-1)
    data.flags.writeable = False  # like rosbags' zero-copy buffer
    return SimpleNamespace(
        height=h,
        width=w,
        fields=fields,
        is_bigendian=big,
        point_step=dt.itemsize,
        row_step=row_step,
        data=data,
    )


def test_structured_view_honours_row_padding_and_byte_order() -> None:
    dt = OUSTER.newbyteorder(">")
    pts = np.zeros((4, 5), dt)
    pts["x"] = np.arange(20).reshape(4, 5)
    pts["t"] = np.arange(20).reshape(4, 5) * 1000
    msg = _msg(pts, row_padding=12)
    view = to_structured(msg)
    np.testing.assert_array_equal(view["x"], np.arange(20))
    np.testing.assert_array_equal(view["t"], np.arange(20) * 1000)
    assert view.dtype["x"].byteorder == ">"


def test_truncated_data_is_a_data_error() -> None:
    pts = np.zeros(10, OUSTER)
    msg = _msg(pts)
    msg.data = msg.data[:-5]
    with pytest.raises(DataError, match="truncated"):
        to_structured(msg)


def test_zero_and_nan_points_dropped_with_same_mask() -> None:
    pts = np.zeros(6, OUSTER)
    pts["x"] = [1, 0, np.nan, 2, 3, 200]
    pts["t"] = [10, 20, 30, 40, 50, 60]
    dec = decode_cloud(_msg(pts), T0, "t", "ring")
    mask = valid_mask(dec.xyz, 0.5, 100.0)
    np.testing.assert_array_equal(mask, [True, False, False, True, True, False])
    np.testing.assert_array_equal(dec.time_raw[mask], [10, 40, 50])


@pytest.mark.parametrize(
    "values,kind,expect",
    [
        (np.linspace(0, 0.0999, 50).astype(np.float32), "f", ("s", "relative", "start")),
        (np.linspace(-0.0999, 0, 50).astype(np.float32), "f", ("s", "relative", "end")),
        (np.linspace(0, 99_900_000, 50).astype(np.uint32), "u", ("ns", "relative", "start")),
        (np.linspace(0, 99_900, 50).astype(np.float32), "f", ("us", "relative", "start")),
        (np.linspace(-0.05, 0.0499, 50), "f", ("s", "relative", "middle")),
    ],
)
def test_classify_relative(values: np.ndarray, kind: str, expect: tuple) -> None:
    tl = classify_time_field("t", [(T0, values), (T0 + 10**8, values)], 100_000_000)
    assert (tl.unit, tl.reference, tl.stamp_position) == expect


def test_classify_absolute_seconds_and_ns() -> None:
    v = T0 / NS + np.linspace(0, 0.0999, 50)
    tl = classify_time_field("timestamp", [(T0, v)], 100_000_000)
    assert (tl.unit, tl.reference, tl.stamp_position) == ("s", "absolute", "start")
    t_ns = time_values_to_ns(v, T0, tl)
    truth = T0 + np.round(np.linspace(0, 0.0999, 50) * 1e9).astype(np.int64)
    assert np.abs(t_ns - truth).max() <= 1_000
    vns = (T0 + np.linspace(0, 99_900_000, 50)).astype(np.float64)
    tl = classify_time_field("timestamp", [(T0 + 99_900_000, vns)], 100_000_000)
    assert (tl.unit, tl.reference, tl.stamp_position) == ("ns", "absolute", "end")


def test_absolute_on_another_clock_is_still_absolute() -> None:
    v = 1_650_000_000.0 + np.linspace(0, 0.0999, 50)
    tl = classify_time_field("timestamp", [(T0, v)], 100_000_000)
    assert (tl.unit, tl.reference) == ("s", "absolute")
    assert tl.notes and "another clock" in tl.notes[0]


def test_zero_span_raises() -> None:
    with pytest.raises(TimestampError, match="zero span"):
        classify_time_field("t", [(T0, np.zeros(10, np.uint32))], 100_000_000)


def test_find_time_field_override_and_none() -> None:
    assert find_time_field(("x", "y", "z", "t"), None) == "t"
    assert find_time_field(("x", "y", "z", "t"), "none") is None
    with pytest.raises(ConfigError, match="configured time field 'time'"):
        find_time_field(("x", "y", "z", "t"), "time")


@pytest.mark.parametrize("clockwise", [True, False])
def test_azimuth_estimate_detects_spin_direction(clockwise: bool) -> None:
    sw = spinning_sweep(T0, columns=720, clockwise=clockwise, azimuth0_deg=-100.0)
    t, method, cw = estimate_times(sw.xyz, T0, 100_000_000, "start", clockwise=not clockwise)
    assert method == "azimuth" and cw == clockwise
    assert np.abs(t - sw.t_ns).max() < 0.005 * 100_000_000


def test_azimuth_estimate_random_order_uses_config_direction() -> None:
    sw = spinning_sweep(T0, columns=720, clockwise=False)
    perm = np.random.default_rng(0).permutation(sw.xyz.shape[0])
    t, _, cw = estimate_times(sw.xyz[perm], T0, 100_000_000, "start", clockwise=False)
    assert cw is False
    # without order the seam is unknown (first point, as LOAM does): times follow the
    # azimuth up to one constant offset modulo the period
    d = np.exp(2j * np.pi * (t - sw.t_ns[perm]) / 100_000_000)
    spread = np.abs(np.angle(d * np.conj(np.mean(d) / np.abs(np.mean(d)))))
    assert np.percentile(spread, 99) < 0.005 * 2 * np.pi


@pytest.mark.parametrize("n_beams,spread_deg", [(16, 30.0), (64, 33.2), (128, 45.0)])
def test_beams_from_elevation(n_beams: int, spread_deg: float) -> None:
    beams = np.linspace(-spread_deg / 2, spread_deg / 2, n_beams) + 0.3
    sw = spinning_sweep(T0, columns=256, beams_deg=beams)
    noisy = sw.xyz * (1 + 1e-4 * np.random.default_rng(1).standard_normal((len(sw.xyz), 1)))
    table = detect_beams([noisy])
    assert table.num_beams == n_beams
    np.testing.assert_allclose(np.rad2deg(table.elevation_rad), beams, atol=0.01)
    np.testing.assert_array_equal(assign_beams(noisy, table), sw.ring)


def test_imu_units_detected_and_converted() -> None:
    rng = np.random.default_rng(2)
    t = np.arange(800, dtype=np.int64) * 5_000_000
    gyro, accel = tilting_imu(t / NS)
    accel = accel + 0.3 * rng.standard_normal((800, 3))
    u = detect_imu_units(gyro, accel, t_ns=t)
    assert (u.gyro_unit, u.accel_unit, u.gyro_source) == ("rad/s", "m/s^2", "detected")
    assert u.gravity_turn_factor == pytest.approx(1.0, rel=0.2)
    assert u.messages() == [] and u.warnings() == []
    u = detect_imu_units(np.rad2deg(gyro), accel / GRAVITY, t_ns=t)
    assert (u.gyro_unit, u.accel_unit, u.gyro_source) == ("deg/s", "g", "detected")
    assert len(u.messages()) == 2 and u.warnings() == []
    g, a = convert_imu(np.rad2deg(gyro), accel / GRAVITY, u)
    np.testing.assert_allclose(g, gyro, rtol=1e-12)
    np.testing.assert_allclose(a, accel, rtol=1e-12)
    # the config decides where the data do not contradict it (no stamps: no tilting evidence)
    u = detect_imu_units(
        np.rad2deg(gyro), accel / GRAVITY, gyro_override="rad/s", accel_override="g"
    )
    assert (u.gyro_unit, u.accel_unit, u.gyro_source, u.accel_source) == (
        "rad/s",
        "g",
        "config",
        "config",
    )
    # a unit the data contradict is said, naming the unit they are in (g on m/s^2 data read
    # gravity as 96 m/s^2 and the calibration ran 36 m off; deg/s on rad/s data stopped on weak
    # excitation); the stream makes it a fatal finding
    assert u.contradiction is None
    said = detect_imu_units(gyro, accel, accel_override="g", t_ns=t).contradiction
    assert said is not None and said.startswith("imu.accel_unit 'g' makes the accelerometer read")
    assert said.endswith("set imu.accel_unit: m/s^2, or remove it to detect the unit.")
    said = detect_imu_units(gyro, accel, gyro_override="deg/s", t_ns=t).contradiction
    assert said is not None and "set imu.gyro_unit: rad/s, or remove it" in said
    said = detect_imu_units(np.rad2deg(gyro), accel, gyro_override="rad/s", t_ns=t).contradiction
    assert said is not None and "set imu.gyro_unit: deg/s, or remove it" in said
    assert detect_imu_units(gyro, accel, gyro_override="rad/s", t_ns=t).contradiction is None
    # without stamps only the magnitude speaks: fast deg/s is clear, the rest is assumed
    u = detect_imu_units(np.rad2deg(gyro), accel)
    assert (u.gyro_unit, u.gyro_source) == ("deg/s", "detected")
    u = detect_imu_units(gyro, accel)
    assert (u.gyro_unit, u.gyro_source) == ("rad/s", "assumed")
    assert "imu.gyro_unit: deg/s" in u.warnings()[0]


def test_slow_gyro_in_deg_s_is_detected_from_the_tilting() -> None:
    """p99 |w| around 5 is plausible in both units; gravity turning at w/57 means deg/s."""
    t = np.arange(2000, dtype=np.int64) * 5_000_000
    gyro, accel = tilting_imu(0.1 * t / NS)  # the tilting of the helper, 10x slower
    gyro = 0.1 * gyro  # rad/s of the slowed-down motion
    gyro_deg = np.rad2deg(gyro)
    p99 = np.percentile(np.linalg.norm(gyro_deg, axis=1), 99)
    assert 2 < p99 < 12
    u = detect_imu_units(gyro_deg, accel, t_ns=t)
    assert (u.gyro_unit, u.gyro_source) == ("deg/s", "detected")
    assert u.gravity_turn_factor == pytest.approx(np.pi / 180, rel=0.2)
    g, _ = convert_imu(gyro_deg, accel, u)
    np.testing.assert_allclose(g, gyro, rtol=1e-12)


def test_ambiguous_gyro_unit_is_assumed_with_a_warning() -> None:
    """Turning about gravity only (yaw) cannot tell rad/s from deg/s."""
    rng = np.random.default_rng(4)
    t = np.arange(800, dtype=np.int64) * 5_000_000
    s = t / NS
    gyro = np.stack([np.zeros_like(s), np.zeros_like(s), 5.0 * np.sin(1.5 * s)], 1)
    accel = np.tile([0.0, 0.0, GRAVITY], (800, 1)) + 0.05 * rng.standard_normal((800, 3))
    u = detect_imu_units(gyro, accel, t_ns=t)
    assert (u.gyro_unit, u.gyro_source, u.gravity_turn_factor) == ("rad/s", "assumed", None)
    assert u.messages() == []
    (warning,) = u.warnings()
    assert "cannot be told" in warning and "`imu.gyro_unit: deg/s`" in warning
    assert warning.endswith(".") and warning.count(". ") == 0


def test_an_accelerometer_in_g_beside_a_livox_pairs_with_rad_s() -> None:
    """Where the data cannot tell the gyro's unit, g pairs with deg/s (IMUs' raw units), but a
    Livox driver publishes g with rad/s: beside Livox clouds the gyro is taken in rad/s."""
    t = np.arange(800, dtype=np.int64) * 5_000_000
    s = t / NS
    gyro = np.stack([np.zeros_like(s), np.zeros_like(s), 2.0 * np.sin(1.5 * s)], 1)
    accel = np.tile([0.0, 0.0, 1.0], (800, 1))
    raw = detect_imu_units(gyro, accel, t_ns=t)
    assert (raw.gyro_unit, raw.gyro_source, raw.accel_unit) == ("deg/s", "assumed", "g")
    livox = detect_imu_units(gyro, accel, t_ns=t, livox=True)
    assert (livox.gyro_unit, livox.gyro_source) == ("rad/s", "assumed")
    (warning,) = livox.warnings()
    assert "Livox driver's, which publishes g with rad/s" in warning
    assert "`imu.gyro_unit: deg/s`" in warning
    # a unit the data show is the data's, Livox or not
    fast = detect_imu_units(np.rad2deg(gyro) * 3, accel, t_ns=t, livox=True)
    assert (fast.gyro_unit, fast.gyro_source) == ("deg/s", "detected")
