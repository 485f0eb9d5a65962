"""The ready-made Ouster bags and the packet bag of ``../shared/data/real/ouster``, read as they
are (no ouster-sdk needed), and the factory extrinsic of the captures' metadata.

Facts from the data's README: ``t`` is ns relative to the header stamp (sensor clock, seconds
since power-on), 128 or 64 beams, organised, IMU at 100 Hz with 30 or 11 messages, the clock
difference IMU - LiDAR is 0.0158 s on the OS-1-128 capture, 0.1-0.3 s is too short to calibrate.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from real_data import OUSTER, metadata_of, require_data

from licalib_cli.cli import main
from licalib_cli.io.bag import open_bag
from licalib_cli.io.ouster import factory_extrinsic, read_factory_extrinsic

BAGS = OUSTER / "bags"


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(exc.value.code or 0), out.out, out.err


@pytest.fixture(autouse=True)
def _data() -> None:
    require_data(BAGS)


@pytest.mark.parametrize(
    ("name", "beams", "imu", "gyro_unit"),
    [
        ("os1-128_si", 128, 30, "rad/s"),
        ("os1-64_si", 64, 11, "rad/s"),
        ("os1-64_gdeg", 64, 11, "deg/s"),
    ],
)
def test_ready_made_bags_are_read_right(
    name: str, beams: int, imu: int, gyro_unit: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, _ = _run(["info", str(BAGS / f"{name}.bag"), "--json"], capsys)
    data = json.loads(out)
    li = data["lidar"]
    # the unit from the span of t (0-0.1 s in ns), not from where the stamp (278-991 s) falls
    assert (li["time_field"], li["time_unit"], li["time_reference"]) == ("t", "ns", "relative")
    assert (li["beams"], li["height"], li["width"]) == (beams, beams, 1024)
    # every IMU message, the first one included
    assert data["imu"]["count"] == imu
    assert data["imu"]["rate_hz"] == pytest.approx(100.0, rel=0.02)
    assert (data["imu"]["gyro_unit"], data["imu"]["gyro_unit_source"]) == (gyro_unit, "assumed")
    assert data["imu"]["gyro_unit_basis"].startswith("too little data to tell")
    # motion claims say the gyro unit they rest on
    summary = data["imu"]["excitation"]["summary"]
    assert f"gyro unit assumed {gyro_unit}" in summary and "hardly any rotation" in summary
    # one cloud is one sweep: too short (exit 7), said once, as calibrate says it
    errors = [p for p in data["problems"] if p["severity"] == "error"]
    assert [e["exit_code"] for e in errors] == [7] and code == 7
    assert "too little to calibrate" in errors[0]["message"]
    assert not any("overlap" in p["message"] for p in data["problems"])
    if name == "os1-128_si":
        assert data["clock_offset_s"] == pytest.approx(0.0158, abs=0.001)


@pytest.mark.parametrize("name", ["os1-128_si", "os1-64_si", "os1-64_gdeg"])
def test_calibrate_says_the_ready_made_bags_are_too_short(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code_info, out, _ = _run(["info", str(BAGS / f"{name}.bag"), "--json"], capsys)
    (first,) = [p["message"] for p in json.loads(out)["problems"] if p["severity"] == "error"]
    code, _, err = _run(
        ["calibrate", str(BAGS / f"{name}.bag"), "-o", str(tmp_path / "c.yaml")], capsys
    )
    assert code == code_info == 7
    assert " ".join(first.split()) in " ".join(err.split())


def test_packet_bag_is_named_as_such(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = OUSTER / "512x10_raw.bag"
    code, out, _ = _run(["info", str(bag), "--json"], capsys)
    data = json.loads(out)
    errors = [p["message"] for p in data["problems"] if p["severity"] == "error"]
    assert code == 3 and data["exit_code"] == 3
    packets = [e for e in errors if "Ouster packets" in e]
    assert len(packets) == 1 and errors[0] == packets[0]
    text = packets[0]
    assert "/os_node0/lidar_packets" in text and "no sensor_msgs/PointCloud2" in text
    assert "replay it through the ouster-ros driver" in text and text.count(". ") == 0
    code, _, err = _run(["calibrate", str(bag), "-o", str(tmp_path / "c.yaml")], capsys)
    assert code == 3 and " ".join(text.split()) in " ".join(err.split())


@pytest.mark.parametrize(
    ("metadata", "translation"),
    [
        ("OS-1-128_v2.3.0_1024x10.json", (-0.006253, 0.011775, 0.028535)),
        ("OS-0-128-U1_v2.3.0_1024x10.json", (-0.006253, 0.011775, 0.028535)),
        ("OS-2-128-U1_v2.3.0_1024x10.json", (-0.006253, 0.011775, 0.066651)),
    ],
)
def test_factory_extrinsic_matches_the_readme(
    metadata: str, translation: tuple[float, ...]
) -> None:
    """``T_imu_lidar = inv(imu_to_sensor) * lidar_to_sensor``: 180 deg about z, README's t."""
    meta = json.loads((OUSTER / metadata).read_text())
    f = factory_extrinsic(meta)
    assert f is not None and f.cloud_frame == "os_lidar"
    np.testing.assert_allclose(f.rotation, np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    np.testing.assert_allclose(f.translation, translation, atol=1e-9)
    np.testing.assert_allclose(np.abs(f.quaternion_xyzw()), [0, 0, 1, 0], atol=1e-12)
    # a point of os_lidar lands where the two metadata transforms put it
    p_lidar = np.array([1.0, -2.0, 0.5])
    lidar_to_sensor = np.asarray(meta["lidar_to_sensor_transform"], float).reshape(4, 4)
    imu_to_sensor = np.asarray(meta["imu_to_sensor_transform"], float).reshape(4, 4)
    p_sensor = lidar_to_sensor[:3, :3] @ p_lidar + lidar_to_sensor[:3, 3] / 1000
    p_imu = imu_to_sensor[:3, :3].T @ (p_sensor - imu_to_sensor[:3, 3] / 1000)
    np.testing.assert_allclose(f.rotation @ p_lidar + f.translation, p_imu, atol=1e-12)
    # clouds published in os_sensor: only the IMU's transform applies
    s = factory_extrinsic(meta, "os_sensor")
    assert s is not None and s.cloud_frame == "os_sensor"
    np.testing.assert_allclose(s.rotation, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(s.translation, -imu_to_sensor[:3, 3] / 1000, atol=1e-12)


def test_reduced_metadata_has_no_factory_extrinsic() -> None:
    from real_data import CAPTURES

    (os1_64,) = [c for c in CAPTURES if c.name == "os1-64"]
    assert factory_extrinsic(metadata_of(os1_64)) is None


def test_factory_extrinsic_from_the_packet_bags_metadata_topic() -> None:
    """The newer, nested metadata format of the driver's /metadata topic."""
    with open_bag(OUSTER / "512x10_raw.bag") as bag:
        f = read_factory_extrinsic(bag)
    assert f is not None and f.topic == "/os_node0/metadata"
    np.testing.assert_allclose(f.rotation, np.diag([-1.0, -1.0, 1.0]), atol=1e-9)
    assert abs(f.translation[2]) < 0.1
