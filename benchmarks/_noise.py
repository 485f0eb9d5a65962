"""Sensor-noise options shared by the benchmarks: a quiet or noise-free LiDAR, a poorer or
better IMU than the simulator's MTi-100."""

from __future__ import annotations

import argparse
from typing import Any


def add_noise_options(p: argparse.ArgumentParser) -> None:
    """``--range-noise``, ``--imu-noise-scale`` and ``--noise-free``."""
    p.add_argument(
        "--range-noise",
        type=float,
        default=None,
        help="range noise sigma, m (default: the LiDAR model's; 0.002: a quiet LiDAR)",
    )
    p.add_argument(
        "--imu-noise-scale",
        type=float,
        default=1.0,
        help="gyro and accelerometer noise densities times this (10: a poor consumer IMU)",
    )
    p.add_argument("--noise-free", action="store_true", help="no IMU or range noise at all")


def noise_spec_kwargs(
    range_noise: float | None = None, imu_noise_scale: float = 1.0, noise_free: bool = False
) -> dict[str, Any]:
    """The ``SimulationSpec`` fields of these options (none for the defaults)."""
    from licalib_cli.simulation.spec import ACCEL_NOISE_DENSITY, GYRO_NOISE_DENSITY

    out: dict[str, Any] = {}
    if range_noise is not None:
        out["range_noise_m"] = range_noise
    if imu_noise_scale != 1.0:
        out["gyro_noise_density"] = imu_noise_scale * GYRO_NOISE_DENSITY
        out["accel_noise_density"] = imu_noise_scale * ACCEL_NOISE_DENSITY
    if noise_free:
        out["noise_free"] = True
    return out
