"""The IMU vectors read at fixed offsets agree with a full decode in every bag format; a
message of another layout is left to the full decode."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from licalib_cli.io.bag import imu_vectors_from_raw, open_bag
from licalib_cli.simulation import SimulationSpec, simulate


@pytest.mark.parametrize("fmt", ["ros1", "ros2-db3", "ros2-mcap"])
def test_fixed_offsets_match_the_full_decode(tmp_path: Path, fmt: str) -> None:
    spec = SimulationSpec(
        duration_s=2.2, fmt=fmt, intrinsics="none", azimuth_resolution_deg=8.0, imu_topic="/imu"
    )
    sim = simulate(spec, tmp_path / "sim")
    with open_bag(sim.bag_path) as bag:
        n = 0
        for m in bag.messages(["/imu"]):
            msg = bag.decode(m)
            w, a = msg.angular_velocity, msg.linear_acceleration
            assert imu_vectors_from_raw(m.raw, bag.ros1) == (w.x, w.y, w.z, a.x, a.y, a.z)
            # one byte more or less is not this layout
            assert imu_vectors_from_raw(bytes(m.raw) + b"\0", bag.ros1) is None
            assert imu_vectors_from_raw(bytes(m.raw)[:-1], bag.ros1) is None
            n += 1
        assert n > 800


def test_imu_read_in_chunks_equals_one_chunk(tmp_path: Path, monkeypatch) -> None:
    """Samples packed into arrays every few messages (as an hour-long bag is read) come out
    the same as gathered in one piece."""
    from licalib_cli.io import imu_stream
    from licalib_cli.io import window as segment

    spec = SimulationSpec(
        duration_s=2.2, intrinsics="none", azimuth_resolution_deg=8.0, imu_topic="/imu"
    )
    sim = simulate(spec, tmp_path / "sim")
    window = segment.SegmentWindow(0, None, from_bag_start=True)
    topic = "/imu"
    with open_bag(sim.bag_path) as bag:
        whole = imu_stream.read_raw_imu(bag, topic, window, 0)
    monkeypatch.setattr(imu_stream, "_IMU_CHUNK", 7)
    with open_bag(sim.bag_path) as bag:
        chunked = imu_stream.read_raw_imu(bag, topic, window, 0)
    assert whole.t_ns.size > 800 and whole.t_ns.size % 7 != 0
    for a, b in zip(whole.__dict__.values(), chunked.__dict__.values(), strict=True):
        np.testing.assert_array_equal(a, b)
