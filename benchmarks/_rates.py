"""Sensor-rate options shared by the benchmarks: IMUs and LiDARs slower or faster than the
simulator's 400 Hz MTi-100 and 10 Hz spinning LiDAR (a 100 or 200 Hz IMU, a 20 Hz LiDAR are
common on real rigs)."""

from __future__ import annotations

import argparse
from typing import Any


def add_rate_options(p: argparse.ArgumentParser) -> None:
    """``--imu-rate`` and ``--lidar-rate``."""
    p.add_argument(
        "--imu-rate",
        type=float,
        default=None,
        help="IMU samples per second (default: the simulator's 400; 100 or 200: common IMUs)",
    )
    p.add_argument(
        "--lidar-rate",
        type=float,
        default=None,
        help="LiDAR sweeps per second (default: the simulator's 10; 20: a fast spin)",
    )


def check_rates(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse rates that are not positive numbers (through ``p.error``)."""
    for flag, value in (("--imu-rate", args.imu_rate), ("--lidar-rate", args.lidar_rate)):
        if value is not None and not value > 0:
            p.error(f"{flag} must be a positive number of samples per second, not {value}")


def rate_spec_kwargs(
    imu_rate: float | None = None, lidar_rate: float | None = None
) -> dict[str, Any]:
    """The ``SimulationSpec`` fields of these options (none for the defaults)."""
    out: dict[str, Any] = {}
    if imu_rate is not None:
        out["imu_rate_hz"] = float(imu_rate)
    if lidar_rate is not None:
        out["lidar_rate_hz"] = float(lidar_rate)
    return out
