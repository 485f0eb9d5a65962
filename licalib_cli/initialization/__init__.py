"""Initial values for the calibration: rotation extrinsic (hand-eye) and coarse time offset.

See :mod:`licalib_cli.initialization.rotation` and :mod:`licalib_cli.initialization.time_offset`
for the conventions (``p_I = R_imu_lidar p_L + t``; ``t_imu = t_lidar + time_offset_s``).
"""

from __future__ import annotations

from licalib_cli.initialization.rotation import (
    GyroIntegrator,
    HandEyeConfig,
    HandEyeRotation,
    estimate_rotation_extrinsic,
    lidar_rotation_at,
    relative_rotations,
    solve_hand_eye_rotation,
)
from licalib_cli.initialization.time_offset import (
    ClockShift,
    TimeOffsetConfig,
    TimeOffsetEstimate,
    correlate_angular_speed,
    estimate_clock_shift,
    estimate_time_offset,
)

__all__ = [
    "ClockShift",
    "GyroIntegrator",
    "HandEyeConfig",
    "HandEyeRotation",
    "TimeOffsetConfig",
    "TimeOffsetEstimate",
    "correlate_angular_speed",
    "estimate_clock_shift",
    "estimate_rotation_extrinsic",
    "estimate_time_offset",
    "lidar_rotation_at",
    "relative_rotations",
    "solve_hand_eye_rotation",
]
