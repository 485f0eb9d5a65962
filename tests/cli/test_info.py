"""``licalib info``: readable table, ``--json`` for scripts, exit codes."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from licalib_cli.cli import main

_spec = importlib.util.spec_from_file_location(
    "licalib_test_layouts", Path(__file__).parents[1] / "io" / "_layouts.py"
)
assert _spec is not None and _spec.loader is not None
layouts = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = layouts
_spec.loader.exec_module(layouts)

PERIOD = 100_000_000
JSON_IMU_KEYS = {"topic", "count", "rate_hz", "gyro_unit", "accel_unit"}
JSON_LIDAR_KEYS = {
    "topic",
    "count",
    "rate_hz",
    "time_field",
    "time_unit",
    "time_reference",
    "beams",
}


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(exc.value.code or 0), out.out, out.err


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("info") / "small.bag"
    layouts.write_velodyne_bag(path, "ros1", n_clouds=24)
    return path


def test_info_table(small_bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(["info", str(small_bag)], capsys)
    assert code == 0, err
    for text in (
        "/imu",
        "/velodyne_points",
        "sensor_msgs/msg/PointCloud2",
        "200.0 Hz",
        "'time' in s, relative",
        "end",
        "16 (field 'ring')",
        "rad/s",
        "m/s^2",
        "Clock difference",
        "usable",
    ):
        assert text in out, text
    assert "Traceback" not in out + err


def test_info_json(small_bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(["info", str(small_bag), "--json"], capsys)
    assert code == 0
    data = json.loads(out)
    assert JSON_IMU_KEYS <= set(data["imu"])
    assert JSON_LIDAR_KEYS <= set(data["lidar"])
    assert {"clock_offset_s", "problems", "usable", "exit_code", "topics"} <= set(data)
    assert data["imu"]["count"] == 520 and data["imu"]["rate_hz"] == pytest.approx(200.0)
    assert data["imu"]["gyro_unit"] == "rad/s" and data["imu"]["accel_unit"] == "m/s^2"
    li = data["lidar"]
    assert (li["count"], li["time_field"], li["time_unit"], li["time_reference"]) == (
        24,
        "time",
        "s",
        "relative",
    )
    assert li["stamp_position"] == "end" and li["beams"] == 16
    assert li["rate_hz"] == pytest.approx(10.0)
    # velodyne stamps the last packet: the last point is 0.56 ms before the record time
    assert abs(data["clock_offset_s"]) < 1e-3
    assert data["problems"] == [] and data["usable"]


def test_info_segment_options(small_bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(
        ["info", str(small_bag), "--json", "--start", "0.2", "--duration", "2"], capsys
    )
    assert code == 0
    data = json.loads(out)
    assert data["imu"]["count"] == 400 and data["lidar"]["count"] == 20


def test_info_json_reports_fatal_problem_with_exit_code(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "two"
    layouts.write_custom_bag(path, imu_topics=("/imu_a", "/imu_b"))
    code, out, err = _run(["info", str(path), "--json"], capsys)
    assert code == 3
    data = json.loads(out)
    assert data["usable"] is False and data["exit_code"] == 3 and data["imu"] is None
    assert data["problems"][0]["severity"] == "error"
    assert "--imu-topic" in err
    code, out, _ = _run(["info", str(path), "--json", "--imu-topic", "/imu_b"], capsys)
    assert code == 0 and json.loads(out)["imu"]["topic"] == "/imu_b"


def test_info_shows_coarse_clock_difference(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import numpy as np

    from licalib_cli.io.writer import BagWriter

    path = tmp_path / "clock"
    t0 = 1_700_000_000 * layouts.NS
    boot = 3_000 * layouts.NS
    with BagWriter(path, "ros2-mcap") as w:
        for i in range(480):
            t = t0 + i * 5_000_000
            w.write_imu(
                "/imu", t - t0 + boot, [0.4 * np.sin(i / 9), 0.1, 0], [0, 0, 9.8], record_ns=t
            )
        for k in range(24):
            stamp = t0 + k * 100_000_000
            w.write_cloud(
                "/points", stamp, layouts.velodyne_points(stamp), record_ns=stamp + PERIOD
            )
    code, out, _ = _run(["info", str(path), "--json"], capsys)
    assert code == 0
    data = json.loads(out)
    assert data["clock_offset_s"] == pytest.approx((boot - t0) / 1e9, abs=2e-3)
    assert any("different clocks" in p["message"] for p in data["problems"])
    code, out, _ = _run(["info", str(path)], capsys)
    assert code == 0
    line = next(ln for ln in out.splitlines() if ln.startswith("Clock difference"))
    shown = float(line.split(":")[1].split()[0])
    assert shown == pytest.approx((boot - t0) / 1e9, abs=2e-3)


def _bag_with_imu(path: Path, gyro: np.ndarray, accel: np.ndarray) -> None:
    from licalib_cli.io.writer import BagWriter

    t0 = 1_700_000_000 * layouts.NS
    with BagWriter(path, "ros2-mcap") as w:
        for i in range(len(gyro)):
            w.write_imu("/imu", t0 + i * 5_000_000, gyro[i], accel[i])
        for k in range(24):
            stamp = t0 + k * PERIOD
            w.write_cloud(
                "/points", stamp, layouts.velodyne_points(stamp), record_ns=stamp + PERIOD
            )


def test_info_slow_deg_s_gyro_detected(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    s = np.arange(480) / 200.0
    gyro, accel = layouts.tilting_imu(0.2 * s)
    gyro_deg = np.rad2deg(0.2 * gyro)  # slow tilting, p99 |w| of a few deg/s
    _bag_with_imu(tmp_path / "x", gyro_deg, accel)
    code, out, err = _run(["info", str(tmp_path / "x"), "--json"], capsys)
    assert code == 0, err
    imu = json.loads(out)["imu"]
    assert (imu["gyro_unit"], imu["gyro_unit_source"]) == ("deg/s", "detected")
    assert 1 < imu["gyro_p99"] < 12


def test_info_ambiguous_gyro_unit_warns_but_stays_usable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    s = np.arange(480) / 200.0
    gyro = np.stack([0 * s, 0 * s, 5.0 * np.sin(2.0 * s)], 1)  # yaw only: cannot tell
    accel = np.tile([0.0, 0.0, 9.81], (480, 1))
    _bag_with_imu(tmp_path / "x", gyro, accel)
    code, out, err = _run(["info", str(tmp_path / "x"), "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert data["usable"] is True and data["exit_code"] == 0
    assert (data["imu"]["gyro_unit"], data["imu"]["gyro_unit_source"]) == ("rad/s", "assumed")
    problem, motion = data["problems"]  # the unit, and the yaw-only motion (planar)
    assert problem["severity"] == "warning" and "`imu.gyro_unit: deg/s`" in problem["message"]
    assert motion["severity"] == "warning" and "rotation about one axis only" in motion["message"]
    code, out, _ = _run(["info", str(tmp_path / "x")], capsys)
    assert code == 0
    assert "rad/s (assumed" in out and "warning: The IMU gyro unit cannot be told" in out
    assert "usable" in out
