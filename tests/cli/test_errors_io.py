"""Bad input to ``licalib info``: one-sentence message, documented exit code, no traceback."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from licalib_cli.cli import main
from licalib_cli.errors import BagError, ConfigError, DataError, TimestampError, TopicError

_spec = importlib.util.spec_from_file_location(
    "licalib_test_layouts", Path(__file__).parents[1] / "io" / "_layouts.py"
)
assert _spec is not None and _spec.loader is not None
layouts = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = layouts
_spec.loader.exec_module(layouts)

NS = layouts.NS
T0 = 1_700_000_000 * NS


def _fail(argv: list[str], capsys: pytest.CaptureFixture[str], code: int) -> str:
    """Run the CLI, check the exit code and return the single error line."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    assert exc.value.code == code, out.err
    assert "Traceback" not in out.out + out.err
    lines = [ln for ln in out.err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, out.err
    line = " ".join(lines)
    assert line.startswith("Error: ")
    msg = line[len("Error: ") :]
    # one sentence: a single final full stop (dots inside numbers and paths allowed)
    assert msg.endswith(".") and ". " not in msg.replace("e.g. ", "").replace("0. ", "")
    return msg


def _clouds(make=layouts.velodyne_points, n: int = 24) -> list:
    return [(T0 + k * 100_000_000, make(T0 + k * 100_000_000)) for k in range(n)]


def test_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    msg = _fail(["info", str(tmp_path / "nope.bag")], capsys, BagError.exit_code)
    assert "does not exist" in msg


def test_text_file_named_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "x.bag"
    p.write_text("this is not a bag\n")
    msg = _fail(["info", str(p)], capsys, BagError.exit_code)
    assert "is not a ROS1 bag" in msg and "check the path" in msg


def test_random_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "photos"
    d.mkdir()
    (d / "a.jpg").write_bytes(b"\xff\xd8")
    msg = _fail(["info", str(d)], capsys, BagError.exit_code)
    assert "is not a bag" in msg


@pytest.mark.parametrize("fmt", ["ros1", "ros2-db3", "ros2-mcap"])
def test_truncated_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str) -> None:
    src = tmp_path / ("v.bag" if fmt == "ros1" else "v")
    layouts.write_velodyne_bag(src, fmt, n_clouds=6)
    f = src if fmt == "ros1" else next(p for p in src.iterdir() if p.suffix in {".db3", ".mcap"})
    data = f.read_bytes()
    cut = tmp_path / f"cut{f.suffix}"
    cut.write_bytes(data[: len(data) // 2])
    msg = _fail(["info", str(cut)], capsys, BagError.exit_code)
    assert "that cannot be read" in msg and "truncated or damaged" in msg
    fix = {"ros1": "rosbag reindex", "ros2-db3": "sqlite3", "ros2-mcap": "mcap recover"}[fmt]
    assert fix in msg


def test_no_imu_topic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    layouts.write_custom_bag(tmp_path / "x", imu_topics=())
    msg = _fail(["info", str(tmp_path / "x")], capsys, TopicError.exit_code)
    assert "no sensor_msgs/Imu topic" in msg and "/points" in msg


def test_no_cloud_topic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    layouts.write_custom_bag(tmp_path / "x", clouds=[])
    msg = _fail(["info", str(tmp_path / "x")], capsys, TopicError.exit_code)
    assert "no sensor_msgs/PointCloud2 topic" in msg


def test_named_topic_of_wrong_type(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    layouts.write_custom_bag(tmp_path / "x")
    msg = _fail(
        ["info", str(tmp_path / "x"), "--lidar-topic", "/imu"], capsys, TopicError.exit_code
    )
    assert "/imu is sensor_msgs/Imu, not sensor_msgs/PointCloud2" in msg
    assert "candidates: /points" in msg


def test_ambiguous_imu_topics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    layouts.write_custom_bag(tmp_path / "x", imu_topics=("/imu_a", "/imu_b"))
    msg = _fail(["info", str(tmp_path / "x")], capsys, TopicError.exit_code)
    assert "/imu_a, /imu_b" in msg and "--imu-topic" in msg


def test_empty_clouds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = [(s, np.zeros(0, layouts.VELODYNE)) for s, _ in _clouds()]
    layouts.write_custom_bag(tmp_path / "x", clouds=empty)
    msg = _fail(["info", str(tmp_path / "x")], capsys, DataError.exit_code)
    assert "are empty" in msg


def test_all_nan_clouds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    clouds = _clouds()
    for _, pts in clouds:
        pts["y"] = np.nan
    layouts.write_custom_bag(tmp_path / "x", clouds=clouds)
    msg = _fail(["info", str(tmp_path / "x")], capsys, DataError.exit_code)
    assert "only NaN or zero points" in msg


def test_unsorted_imu_stamps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t = T0 + np.arange(480, dtype=np.int64) * 5_000_000
    t[100] -= 20_000_000
    layouts.write_custom_bag(tmp_path / "x", imu_t=t)
    msg = _fail(["info", str(tmp_path / "x")], capsys, TimestampError.exit_code)
    assert "IMU stamps go backwards once (at 0.480 s)" in msg


def test_duplicated_cloud_stamps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    clouds = _clouds()
    clouds[3] = (clouds[2][0], clouds[3][1])
    layouts.write_custom_bag(tmp_path / "x", clouds=clouds)
    msg = _fail(["info", str(tmp_path / "x")], capsys, TimestampError.exit_code)
    assert "LiDAR stamps are duplicated once (at " in msg


def test_imu_gap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t = T0 + np.arange(480, dtype=np.int64) * 5_000_000
    t = np.delete(t, np.arange(80, 120))
    layouts.write_custom_bag(tmp_path / "x", imu_t=t)
    msg = _fail(["info", str(tmp_path / "x")], capsys, TimestampError.exit_code)
    assert "has 1 gap longer than 5x" in msg and "--start/--duration" in msg


def test_zero_span_time_field(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    clouds = _clouds()
    for _, pts in clouds:
        pts["time"] = 0.05
    layouts.write_custom_bag(tmp_path / "x", clouds=clouds)
    msg = _fail(["info", str(tmp_path / "x")], capsys, TimestampError.exit_code)
    assert "zero span" in msg and "lidar.time_field: none" in msg


def test_bad_config_value(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    layouts.write_custom_bag(tmp_path / "x")
    msg = _fail(["info", str(tmp_path / "x"), "--start", "-3"], capsys, 6)
    assert "bag.start_s" in msg


def test_start_after_end_of_bag_is_an_option_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    layouts.write_custom_bag(tmp_path / "x")
    msg = _fail(["info", str(tmp_path / "x"), "--start", "100"], capsys, ConfigError.exit_code)
    assert "bag lasts only 2.399 s" in msg and "smaller --start" in msg


@pytest.mark.parametrize(
    ("key", "option"), [("time_field", "lidar.time_field"), ("ring_field", "lidar.ring_field")]
)
def test_configured_field_missing_from_cloud_is_a_config_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str, option: str
) -> None:
    layouts.write_custom_bag(tmp_path / "x")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"lidar:\n  {key}: foo\n")
    msg = _fail(["info", str(tmp_path / "x"), "-c", str(cfg)], capsys, ConfigError.exit_code)
    assert "'foo' is not in the cloud" in msg and f"`{option}`" in msg
