"""Simulator bags in every format are read back by ``licalib info`` with the right layout."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from licalib_cli.cli import main
from licalib_cli.io.writer import BagFormat
from licalib_cli.simulation import LidarKind, SimulationSpec, simulate

# (lidar, spec options, expected info --json lidar fields). The OS1-64 keeps its native
# 1024 columns so that the organised 64 x 1024 layout is checked (3 scans keep it fast).
LIDARS = {
    LidarKind.VLP16: (
        {"duration_s": 0.5, "azimuth_resolution_deg": 2.0},
        {
            "topic": "/points_raw",
            "time_field": "time",
            "time_unit": "s",
            "time_reference": "relative",
            "stamp_position": "start",
            "beams": 16,
            "ring_field": "ring",
            "height": 1,
            "point_step": 22,
            "is_bigendian": False,
        },
    ),
    LidarKind.OS1_64: (
        {"duration_s": 0.3},
        {
            "topic": "/ouster/points",
            "time_field": "t",
            "time_unit": "ns",
            "time_reference": "relative",
            "stamp_position": "start",
            "beams": 64,
            "ring_field": "ring",
            "height": 64,
            "width": 1024,
            "point_step": 48,
            "is_bigendian": False,
        },
    ),
}


@pytest.mark.parametrize("lidar", list(LIDARS), ids=[k.value for k in LIDARS])
@pytest.mark.parametrize("fmt", list(BagFormat), ids=[f.value for f in BagFormat])
def test_info_reads_simulated_bag_layout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: BagFormat, lidar: LidarKind
) -> None:
    options, expected = LIDARS[lidar]
    spec = SimulationSpec(lidar=lidar, fmt=fmt, seed=1, **options)
    out = simulate(spec, tmp_path / "sim")
    with pytest.raises(SystemExit) as exc:
        main(["info", str(out.bag_path), "--json"])
        raise SystemExit(0)
    captured = capsys.readouterr()
    assert exc.value.code == 0, captured.err
    data = json.loads(captured.out)
    assert data["format"] == fmt.value and data["usable"] is True
    assert not [p for p in data["problems"] if p["severity"] == "error"]
    li = data["lidar"]
    assert {k: li[k] for k in expected} == expected
    assert li["count"] == out.num_scans and li["rate_hz"] == pytest.approx(10.0)
    assert li["clouds_skipped"] == {}
    imu = data["imu"]
    assert imu["topic"] == "/imu/data" and imu["count"] == out.num_imu
    assert imu["rate_hz"] == pytest.approx(400.0)
    assert (imu["gyro_unit"], imu["accel_unit"]) == ("rad/s", "m/s^2")
    assert abs(data["clock_offset_s"]) < 0.01
