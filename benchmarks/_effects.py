"""Named effects for the benchmarks: bags that hide one effect (or a few) of a known size.

Intrinsic effects are drawn per axis (per beam) as N(0, size) with the sizes of the paper's
Table sensor_intrinsic_setting times ``scale`` and written to an intrinsics file the simulator
reads (everything else ideal); g-sensitivity (0.1 deg/s/g), the IMU clock drift (50 ppm) and the
bias random walk (ten times the MTi-100's) are the simulator's own effects, times ``sim_scale``.
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
SIMULATOR_EFFECTS = ("g_sensitivity", "imu_clock_drift", "bias_walk")


def _intrinsics(effects: list[str], lidar: str, seed: int, scale: float, path: Path) -> Path | None:
    import numpy as np
    from scipy.spatial.transform import Rotation

    from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
    from licalib_cli.results import CalibrationResult
    from licalib_cli.simulation import ground_truth as gt
    from licalib_cli.simulation.lidar_models import lidar_model

    wanted = [e for e in effects if e in INTRINSIC_EFFECTS]
    if not wanted:
        return None
    rng = np.random.default_rng([seed, 77])
    k = scale
    imu = ImuIntrinsics()
    nominal = lidar_model(lidar).nominal_elevation
    lid = LidarIntrinsics.nominal(nominal)
    b = nominal.shape[0]

    def per_beam(std: float) -> Any:
        v = rng.normal(0.0, std * k, b)
        v[0] = 0.0  # the gauge beam
        return v

    for effect in wanted:
        if effect == "gyro_scale":
            imu = imu.with_(gyro_scale=1.0 + rng.normal(0.0, gt.GYRO_SCALE_STD * k, 3))
        elif effect == "accel_scale":
            imu = imu.with_(accel_scale=1.0 + rng.normal(0.0, gt.ACCEL_SCALE_STD * k, 3))
        elif effect == "gyro_misalignment":
            m = rng.normal(0.0, np.radians(gt.GYRO_MISALIGNMENT_STD_DEG) * k, 3)
            imu = imu.with_(gyro_misalignment=m)
        elif effect == "accel_misalignment":
            m = rng.normal(0.0, np.radians(gt.ACCEL_MISALIGNMENT_STD_DEG) * k, 3)
            imu = imu.with_(accel_misalignment=m)
        elif effect == "gyro_rotation":
            angles = rng.normal(0.0, gt.GYRO_ROTATION_STD_DEG * k, 3)
            q = Rotation.from_euler("xyz", angles, degrees=True).as_quat()
            imu = imu.with_(gyro_rotation=q)
        elif effect == "lidar_range_offset":
            lid = lid.with_(range_offset=per_beam(gt.LIDAR_RANGE_OFFSET_STD_M))
        elif effect == "lidar_range_scale":
            lid = lid.with_(range_scale=1.0 + per_beam(gt.LIDAR_RANGE_SCALE_STD))
        elif effect == "lidar_elevation":
            lid = lid.with_(elevation_correction=per_beam(np.radians(gt.LIDAR_ELEVATION_STD_DEG)))
        elif effect == "lidar_azimuth":
            lid = lid.with_(azimuth_correction=per_beam(np.radians(gt.LIDAR_AZIMUTH_STD_DEG)))
        elif effect == "lidar_vertical_offset":
            lid = lid.with_(vertical_offset=per_beam(gt.LIDAR_VERTICAL_STD_M))
        elif effect == "lidar_horizontal_offset":
            lid = lid.with_(horizontal_offset=per_beam(gt.LIDAR_HORIZONTAL_STD_M))
    CalibrationResult(imu_intrinsics=imu, lidar_intrinsics=lid).save(path)
    return path


def effect_spec_kwargs(
    effects: list[str],
    lidar: str,
    seed: int,
    workdir: Path,
    scale: float = 2.0,
    sim_scale: float = 1.0,
) -> dict[str, Any]:
    """``SimulationSpec`` keyword arguments that hide ``effects``: intrinsic effects at
    ``scale`` times the paper's sizes, the simulator's effects at ``sim_scale`` times theirs."""
    kwargs: dict[str, Any] = {}
    path = _intrinsics(effects, lidar, seed, scale, workdir / f"intrinsics{seed}.yaml")
    if path is not None:
        kwargs["intrinsics_file"] = path
    sim: list[str] = []
    if "g_sensitivity" in effects:
        sim.append("g-sensitivity")
        kwargs["g_sensitivity_dps_per_g"] = 0.1 * sim_scale
    if "imu_clock_drift" in effects:
        sim.append("imu-clock-drift")
        kwargs["imu_clock_drift_ppm"] = 50.0 * sim_scale
    if "bias_walk" in effects:
        sim.append("bias-random-walk")
        kwargs["bias_walk_scale"] = 10.0 * sim_scale
    if sim:
        kwargs["effects"] = tuple(sim)
    return kwargs
