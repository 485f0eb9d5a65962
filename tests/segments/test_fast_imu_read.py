"""The IMU vectors read at fixed offsets agree with a full decode in every bag format; a
message of another layout is left to the full decode."""

from __future__ import annotations

from pathlib import Path

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
