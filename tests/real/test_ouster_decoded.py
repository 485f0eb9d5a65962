"""Real Ouster output through the whole reader: every capture of ``../shared/data/real/ouster``,
decoded with ouster-sdk into the ouster-ros layout and written as ROS1 ``.bag``, ROS2 ``.db3``
and ``.mcap``, in SI units and in the packets' own g and deg/s (``conftest.py``).

On each bag ``licalib info`` must report the time field ``t`` in ns relative to the header
stamp, the beam count, an organised cloud, the IMU near 100 Hz with every message counted, the
IMU units it used (and that 0.1-0.3 s is too little to tell the gyro unit), the factory
extrinsic of the metadata; ``calibrate`` must refuse the 0.1-0.3 s with one sentence and exit
code 7; and the points licalib decodes must be ouster-sdk's XYZ to float precision.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from real_data import CAPTURES, DecodedBag, lidar_points

from licalib_cli.cli import main
from licalib_cli.config import load_config
from licalib_cli.io.pointcloud2 import valid_mask
from licalib_cli.io.reader import read_segment
from licalib_cli.io.writer import BagFormat

# (capture, variant): each capture in the three formats (conftest._variants)
CASES = [(i, j) for i in range(len(CAPTURES)) for j in range(3)]
IDS = [f"{CAPTURES[i].name}-{('ros1', 'db3', 'mcap')[j]}" for i, j in CASES]


def _bag(bags: list[DecodedBag], case: tuple[int, int]) -> DecodedBag:
    return bags[3 * case[0] + case[1]]


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(exc.value.code or 0), out.out, out.err


def test_the_bags_cover_every_format_and_both_unit_systems(ouster_bags: list[DecodedBag]) -> None:
    assert {b.fmt for b in ouster_bags} == set(BagFormat)
    for cap in CAPTURES:
        mine = [b for b in ouster_bags if b.capture is cap]
        assert {b.units for b in mine} == {"si", "gdeg"}
        assert {b.fmt for b in mine} == set(BagFormat)


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_info_reads_real_ouster_output(
    ouster_bags: list[DecodedBag], case: tuple[int, int], capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _bag(ouster_bags, case)
    cap = bag.capture
    code, out, _ = _run(["info", str(bag.path), "--json"], capsys)
    data = json.loads(out)
    li, imu = data["lidar"], data["imu"]
    # the per-point time field: ns since the header stamp, which marks the sweep start
    assert (li["time_field"], li["time_unit"], li["time_reference"]) == ("t", "ns", "relative")
    assert li["stamp_position"] == "start"
    assert li["beams"] == cap.beams and li["ring_field"] == "ring"
    assert (li["height"], li["width"]) == (cap.beams, 1024)  # organised
    assert li["count"] == cap.frames
    # every IMU message counted, at 100 Hz, on the same clock as the clouds
    assert imu["count"] == cap.imu_messages
    assert imu["rate_hz"] == pytest.approx(100.0, rel=0.05)
    assert abs(data["clock_offset_s"]) < 0.05
    # the units used, and that the 0.1-0.3 s cannot tell the gyro's
    if bag.units == "si":
        assert (imu["accel_unit"], imu["accel_unit_source"]) == ("m/s^2", "detected")
        assert (imu["gyro_unit"], imu["gyro_unit_source"]) == ("rad/s", "assumed")
        assert imu["gyro_unit_basis"] == "too little data to tell, ROS convention"
    else:
        assert (imu["accel_unit"], imu["accel_unit_source"]) == ("g", "detected")
        assert (imu["gyro_unit"], imu["gyro_unit_source"]) == ("deg/s", "assumed")
        assert imu["gyro_unit_basis"] == "too little data to tell, accelerometer in g"
    warnings = [p["message"] for p in data["problems"] if p["severity"] == "warning"]
    (unit_warning,) = [w for w in warnings if "gyro unit" in w and "too little" in w]
    assert f"assumed {imu['gyro_unit']}" in unit_warning
    (motion,) = [w for w in warnings if w.startswith("The IMU shows")]
    assert f"gyro unit assumed {imu['gyro_unit']}" in motion and "hardly any rotation" in motion
    # too short to calibrate: one sentence, exit code 7, and nothing else fatal
    errors = [p for p in data["problems"] if p["severity"] == "error"]
    assert len(errors) == 1 and errors[0]["exit_code"] == 7
    assert "too little to calibrate" in errors[0]["message"]
    assert code == 7 and data["exit_code"] == 7
    # the factory extrinsic of the metadata, for the os_lidar frame the clouds are in
    factory = data["factory_extrinsic"]
    if cap.factory is None:
        assert factory is None
    else:
        t, sensor = cap.factory
        np.testing.assert_allclose(factory["translation"], t, atol=5e-7)
        q = np.asarray(factory["rotation_quaternion"])
        np.testing.assert_allclose(np.abs(q), [0.0, 0.0, 1.0, 0.0], atol=1e-9)
        assert factory["cloud_frame"] == "os_lidar" and factory["sensor"] == sensor


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_calibrate_refuses_real_ouster_output_as_too_short(
    ouster_bags: list[DecodedBag],
    case: tuple[int, int],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    bag = _bag(ouster_bags, case)
    out = tmp_path / "calib.yaml"
    code, _, err = _run(["calibrate", str(bag.path), "-o", str(out)], capsys)
    assert code == 7
    text = " ".join(err.split())
    assert "too little to calibrate" in text and "Traceback" not in text
    assert text.count("Error:") == 1 and text.endswith(".")
    assert not out.exists()


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_decoded_points_are_ouster_sdk_xyz(
    ouster_bags: list[DecodedBag], case: tuple[int, int]
) -> None:
    bag = _bag(ouster_bags, case)
    cfg = load_config(None, {})
    rec = read_segment(bag.path, cfg, min_span_s=0.0)
    arrays = bag.arrays
    assert len(rec.scans) == bag.capture.frames
    for k, scan in enumerate(rec.scans):
        sdk = lidar_points(arrays, k).reshape(-1, 3)
        as_recorded = sdk.astype(np.float32).astype(np.float64)  # PointCloud2 holds float32
        keep = valid_mask(as_recorded, cfg.lidar.min_range_m, cfg.lidar.max_range_m)
        assert scan.stamp_ns == arrays["stamp_ns"][k]
        np.testing.assert_allclose(scan.xyz, sdk[keep], rtol=1e-7, atol=1e-9)
        rows = np.repeat(np.arange(bag.capture.beams), 1024)
        np.testing.assert_array_equal(scan.ring, rows[keep])
        np.testing.assert_array_equal(scan.t_ns - scan.stamp_ns, arrays["t_ns"][k].ravel()[keep])
    n_imu = bag.capture.imu_messages
    assert len(rec.imu.t_ns) == n_imu  # the first message too
    np.testing.assert_array_equal(rec.imu.t_ns, arrays["imu_stamp_ns"])
    np.testing.assert_allclose(rec.imu.gyro, arrays["gyro_si"], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rec.imu.accel, arrays["accel_si"], rtol=1e-6, atol=1e-9)
