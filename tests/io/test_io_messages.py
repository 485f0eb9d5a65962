"""Wording of the findings: counts agree with their nouns; JSON has no negative zero."""

from __future__ import annotations

import json
import re

import numpy as np

from licalib_cli.inspection import BagReport
from licalib_cli.io.cloud_layout import ScanTally
from licalib_cli.io.findings import IMU_GAP_FACTOR, imu_problems, lidar_stamp_problems, stamp_stats

NS = 1_000_000_000
BAD = re.compile(r"\b1 (times|gaps|samples|messages|clouds|LiDAR clouds|IMU samples)\b")


def _stamps(n: int, period: int, backwards: int = 0, dups: int = 0, gaps: int = 0) -> np.ndarray:
    t = np.arange(n, dtype=np.int64) * period
    for k in range(backwards):
        t[20 + 10 * k] -= 3 * period
    for k in range(dups):
        t[60 + 10 * k] = t[59 + 10 * k]
    for k in range(gaps):
        t[100 + 10 * k :] += int(IMU_GAP_FACTOR * 2 * period)
    return t


def test_singular_counts() -> None:
    stats = stamp_stats(_stamps(200, 5_000_000, backwards=1, dups=1, gaps=1), IMU_GAP_FACTOR)
    messages = [p.message for p in imu_problems(stats, exact_duplicates=0)]
    messages += [p.message for p in imu_problems(stats, exact_duplicates=1)]
    messages += [p.message for p in lidar_stamp_problems(stats)]
    tally = ScanTally(total=10)
    tally.skipped["empty"] = 1
    tally.skipped["no time field"] = 1
    messages += [p.message for p in tally.problems()]
    one = ScanTally(total=1)
    one.skipped["invalid"] = 1
    messages += [p.message for p in one.problems()]
    text = "\n".join(messages)
    assert not BAD.search(text), text
    assert "IMU stamps go backwards once (at " in text
    assert "IMU stamps are duplicated once with different values (at " in text
    assert "1 IMU message was recorded twice" in text
    assert "The IMU stream has 1 gap longer than" in text
    assert "LiDAR stamps are duplicated once (at " in text
    assert "1 of 10 LiDAR clouds is empty and was skipped." in text
    assert "1 of 10 LiDAR clouds lacks the time field and was skipped." in text
    assert "The only LiDAR cloud of the segment has only NaN or zero points" in text


def test_plural_counts() -> None:
    stats = stamp_stats(_stamps(200, 5_000_000, backwards=3, gaps=2), IMU_GAP_FACTOR)
    text = "\n".join(p.message for p in imu_problems(stats) + lidar_stamp_problems(stats))
    assert "IMU stamps go backwards 3 times (first at " in text
    assert "The IMU stream has 2 gaps longer than" in text
    stats = stamp_stats(np.arange(5, dtype=np.int64), IMU_GAP_FACTOR)
    assert "Only 5 IMU samples in the segment" in imu_problems(stats)[0].message


def test_negative_zero_clock_offset_is_written_as_zero() -> None:
    report = BagReport(
        path="x",
        format="ros1",
        start_ns=0,
        end_ns=NS,
        segment_start_s=0.0,
        segment_duration_s=None,
        topics=(),
        imu=None,
        lidar=None,
        clock_offset_s=-4e-10,
        problems=(),
    )
    text = json.dumps(report.to_dict())
    assert '"clock_offset_s": 0.0' in text and "-0.0" not in text
