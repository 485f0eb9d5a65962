"""Named effects for the benchmarks: bags that hide one effect (or a few) of a known size.

Every effect is the simulator's own (``licalib simulate --effect NAME --effect-scale K``,
:mod:`licalib_cli.simulation.effects`): intrinsic effects drawn per axis (per beam) as
N(0, size) with the sizes of the paper's Table sensor_intrinsic_setting, the others at their
reference sizes (g-sensitivity 0.1 deg/s/g, IMU clock drift 50 ppm, bias walks ten times the
MTi-100's, per-point time error 1 %), all times the scale.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

EFFECTS = [
    "gyro_scale",
    "gyro_misalignment",
    "gyro_rotation",
    "accel_scale",
    "accel_misalignment",
    "g_sensitivity",
    "lidar_range_offset",
    "lidar_elevation",
    "lidar_horizontal_offset",
    "imu_clock_drift",
]
"""The effects of bench_consistency, one per run."""

INTRINSIC_EFFECTS = (
    "gyro_scale",
    "gyro_misalignment",
    "gyro_rotation",
    "accel_scale",
    "accel_misalignment",
    "lidar_range_offset",
    "lidar_range_scale",
    "lidar_elevation",
    "lidar_azimuth",
    "lidar_vertical_offset",
    "lidar_horizontal_offset",
)
SIMULATOR_EFFECTS = (
    "g_sensitivity",
    "imu_clock_drift",
    "gyro_bias_walk",
    "accel_bias_walk",
    "lidar_point_time",
)


def effect_spec_kwargs(
    effects: list[str],
    lidar: str,
    seed: int,
    workdir: Path,
    scale: float = 2.0,
    sim_scale: float = 1.0,
) -> dict[str, Any]:
    """``SimulationSpec`` keyword arguments that hide ``effects``: intrinsic effects at
    ``scale`` times the paper's sizes, the others at ``sim_scale`` times their reference
    sizes. ``lidar``, ``seed`` and ``workdir`` are kept for the callers (the
    simulator draws from the run's seed)."""
    del lidar, seed, workdir
    from licalib_cli.simulation.effects import EFFECT_SIZES, Effect

    if not effects:
        return {}
    kwargs: dict[str, Any] = {"effects": tuple(effects), "effect_scale": scale}
    k = sim_scale
    if k != scale:  # the simulator's own effects at their own multiple
        if "g_sensitivity" in effects:
            kwargs["g_sensitivity_dps_per_g"] = EFFECT_SIZES[Effect.G_SENSITIVITY].size * k
        if "imu_clock_drift" in effects:
            kwargs["imu_clock_drift_ppm"] = EFFECT_SIZES[Effect.IMU_CLOCK_DRIFT].size * k
        if "lidar_point_time" in effects:
            kwargs["point_time_error"] = EFFECT_SIZES[Effect.LIDAR_POINT_TIME].size * k
    if "bias_walk" in effects:  # both walks (bench_consistency's name)
        names = [e for e in effects if e != "bias_walk"]
        kwargs["effects"] = (*names, "gyro_bias_walk", "accel_bias_walk")
        kwargs["bias_walk_scale"] = EFFECT_SIZES[Effect.GYRO_BIAS_WALK].size * k
    return kwargs
