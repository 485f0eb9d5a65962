"""The reader's validation: which findings are fatal (and with which error) and which warn."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _layouts import NS, VELODYNE, read_short, velodyne_points, write_custom_bag

from licalib_cli.config import load_config
from licalib_cli.errors import ConfigError, DataError, TimestampError, TopicError
from licalib_cli.io.findings import stamp_stats
from licalib_cli.io.writer import BagWriter

T0 = 1_700_000_000 * NS


def _imu_t(n: int = 240) -> np.ndarray:
    return T0 + np.arange(n, dtype=np.int64) * 5_000_000


def _clouds(make=velodyne_points, n: int = 10) -> list[tuple[int, np.ndarray]]:
    return [(T0 + k * 100_000_000, make(T0 + k * 100_000_000)) for k in range(n)]


def test_stamp_stats_counts() -> None:
    t = np.array([0, 10, 20, 20, 15, 30, 40, 50, 120], dtype=np.int64)
    s = stamp_stats(t, 5.0)
    assert (s.count, s.backwards, s.duplicates, s.period_ns) == (9, 1, 1, 10)
    assert s.gaps == 1 and s.max_gap_s == pytest.approx(70e-9)
    assert s.first_backwards_s == pytest.approx(15e-9)


def test_imu_backwards_is_fatal(tmp_path: Path) -> None:
    t = _imu_t()
    t[[50, 120]] = t[[50, 120]] - 12_000_000
    write_custom_bag(tmp_path / "x", imu_t=t)
    with pytest.raises(
        TimestampError, match=r"IMU stamps go backwards twice \(first at 0\.238 s\)"
    ):
        read_short(tmp_path / "x", load_config(None))


def test_imu_duplicates_with_other_values_are_fatal(tmp_path: Path) -> None:
    t = _imu_t()
    t[60] = t[59]
    write_custom_bag(tmp_path / "x", imu_t=t)
    with pytest.raises(TimestampError, match="duplicated once with different values"):
        read_short(tmp_path / "x", load_config(None))


def test_imu_exact_copies_are_dropped(tmp_path: Path) -> None:
    path = tmp_path / "x"
    with BagWriter(path, "ros2-mcap") as w:
        for i, t in enumerate(_imu_t()):
            w.write_imu("/imu", int(t), [0.3, 0.1, 0.2], [0, 0, 9.8])
            if i == 40:
                w.write_imu("/imu", int(t), [0.3, 0.1, 0.2], [0, 0, 9.8])
        for stamp, pts in _clouds():
            w.write_cloud("/points", stamp, pts)
    rec = read_short(path, load_config(None))
    assert len(rec.imu) == 240
    assert any("recorded twice" in w for w in rec.warnings)


def test_imu_gap_is_fatal(tmp_path: Path) -> None:
    t = np.concatenate([_imu_t(100), _imu_t(240)[140:]])
    write_custom_bag(tmp_path / "x", imu_t=t)
    with pytest.raises(TimestampError, match=r"1 gap longer .* \(largest 0\.205 s at 0\.495 s\)"):
        read_short(tmp_path / "x", load_config(None))


def test_lidar_backwards_and_duplicates_are_fatal(tmp_path: Path) -> None:
    clouds = _clouds()
    clouds[4], clouds[5] = clouds[5], clouds[4]
    write_custom_bag(tmp_path / "a", clouds=clouds)
    with pytest.raises(TimestampError, match="LiDAR stamps go backwards once"):
        read_short(tmp_path / "a", load_config(None))
    clouds = _clouds()
    clouds[6] = (clouds[5][0], clouds[6][1])
    write_custom_bag(tmp_path / "b", clouds=clouds)
    with pytest.raises(TimestampError, match="LiDAR stamps are duplicated once"):
        read_short(tmp_path / "b", load_config(None))


def _empty(stamp: int) -> np.ndarray:
    return np.zeros(0, VELODYNE)


def _nan(stamp: int) -> np.ndarray:
    pts = velodyne_points(stamp)
    pts["x"] = np.nan
    return pts


def _zero_span(stamp: int) -> np.ndarray:
    pts = velodyne_points(stamp)
    pts["time"] = 0.0
    return pts


def test_one_empty_cloud_is_a_warning(tmp_path: Path) -> None:
    clouds = _clouds()
    clouds[3] = (clouds[3][0], _empty(0))
    write_custom_bag(tmp_path / "x", clouds=clouds)
    rec = read_short(tmp_path / "x", load_config(None))
    assert len(rec.scans) == 9
    assert any("1 of 10 LiDAR clouds is empty and was skipped." == w for w in rec.warnings)


def test_all_empty_clouds_fatal(tmp_path: Path) -> None:
    write_custom_bag(tmp_path / "x", clouds=_clouds(_empty))
    with pytest.raises(DataError, match="All 10 LiDAR clouds of the segment are empty"):
        read_short(tmp_path / "x", load_config(None))


def test_all_nan_clouds_fatal(tmp_path: Path) -> None:
    write_custom_bag(tmp_path / "x", clouds=_clouds(_nan))
    with pytest.raises(DataError, match="only NaN or zero points"):
        read_short(tmp_path / "x", load_config(None))


def test_zero_span_time_field_fatal_and_override(tmp_path: Path) -> None:
    write_custom_bag(tmp_path / "x", clouds=_clouds(_zero_span))
    with pytest.raises(TimestampError, match="zero span"):
        read_short(tmp_path / "x", load_config(None))
    rec = read_short(tmp_path / "x", load_config(None, {"lidar.time_field": "none"}))
    assert rec.layout.time.reference == "estimated" and len(rec.scans) == 10


def test_one_zero_span_cloud_is_skipped(tmp_path: Path) -> None:
    clouds = _clouds()
    clouds[7] = (clouds[7][0], _zero_span(0))
    write_custom_bag(tmp_path / "x", clouds=clouds)
    rec = read_short(tmp_path / "x", load_config(None))
    assert len(rec.scans) == 9
    assert any("zero span" in w for w in rec.warnings)


def test_topic_errors(tmp_path: Path) -> None:
    write_custom_bag(tmp_path / "two", imu_topics=("/imu_a", "/imu_b"))
    with pytest.raises(
        TopicError, match=r"2 sensor_msgs/Imu topics \(/imu_a, /imu_b\).*--imu-topic"
    ):
        read_short(tmp_path / "two", load_config(None))
    rec = read_short(tmp_path / "two", load_config(None, {"imu.topic": "/imu_b"}))
    assert rec.imu_topic == "/imu_b"
    with pytest.raises(
        TopicError, match="Topic /imu_a is sensor_msgs/Imu, not sensor_msgs/PointCloud2"
    ):
        read_short(
            tmp_path / "two", load_config(None, {"imu.topic": "/imu_b", "lidar.topic": "/imu_a"})
        )
    with pytest.raises(TopicError, match=r"Topic /nope is not in the bag.*candidates: /points"):
        read_short(
            tmp_path / "two", load_config(None, {"imu.topic": "/imu_b", "lidar.topic": "/nope"})
        )
    write_custom_bag(tmp_path / "noimu", imu_topics=())
    with pytest.raises(TopicError, match="no sensor_msgs/Imu topic"):
        read_short(tmp_path / "noimu", load_config(None))
    write_custom_bag(tmp_path / "nocloud", clouds=[])
    with pytest.raises(TopicError, match="no sensor_msgs/PointCloud2 topic"):
        read_short(tmp_path / "nocloud", load_config(None))


def test_start_after_end(tmp_path: Path) -> None:
    write_custom_bag(tmp_path / "x")
    with pytest.raises(ConfigError, match="bag lasts only"):
        read_short(tmp_path / "x", load_config(None, {"bag.start_s": 50.0}))


def test_long_bag_is_cut_to_max_duration_with_a_warning(tmp_path: Path) -> None:
    """Without --duration a long bag is cut to bag.max_duration_s; info-style reads are not."""
    write_custom_bag(tmp_path / "x", imu_t=_imu_t(440), clouds=_clouds(n=20))  # 2.2 s of IMU
    cut = read_short(tmp_path / "x", load_config(None, {"bag.max_duration_s": 1.0}))
    span = (cut.imu.t_ns[-1] - cut.imu.t_ns[0]) / NS
    assert 0.9 < span < 1.05
    assert len(cut.scans) in (10, 11)
    assert any("only 1 s from 0 s are used" in w for w in cut.warnings), cut.warnings
    whole = read_short(tmp_path / "x", load_config(None))
    assert len(whole.scans) == 20
    assert not any("are used" in w for w in whole.warnings)
    chosen = read_short(
        tmp_path / "x", load_config(None, {"bag.max_duration_s": 1.0, "bag.duration_s": 1.5})
    )
    assert 1.4 < (chosen.imu.t_ns[-1] - chosen.imu.t_ns[0]) / NS < 1.55
    assert not any("are used" in w for w in chosen.warnings)
