"""Residual blocks of the calibration problem (whitened residuals with analytic Jacobians).

Parameter block names (the solver's ``trajectory`` group eliminates the first five):

=========================  ======  =========  ==============================================
name                       shape   manifold   meaning
=========================  ======  =========  ==============================================
``traj.so3``               (N, 4)  so3        rotation control points ``R_G_I``
``traj.r3``                (N, 3)  euclidean  position control points ``G p_I``, m
``imu.gyro_bias``          (3,)    euclidean  ``b_w``, rad/s
``imu.accel_bias``         (3,)    euclidean  ``b_a``, m/s^2
``gravity``                (3,)    s2         ``g_G``, m/s^2 (fixed norm)
``ext.rotation``           (4,)    so3        ``R_imu_lidar``
``ext.translation``        (3,)    euclidean  ``t_imu_lidar``, m
``ext.time_offset``        (1,)    euclidean  ``t_c`` (``t_imu = t_lidar + t_c``), s
``imu.gyro_scale``         (3,)    euclidean  ``S_w`` diagonal
``imu.gyro_misalignment``  (3,)    euclidean  ``[m0, m1, m2]`` of ``M_w``
``imu.gyro_rotation``      (4,)    so3        ``R_wI`` (IMU -> gyro frame)
``imu.accel_scale``        (3,)    euclidean  ``S_a`` diagonal
``imu.accel_misalignment`` (3,)    euclidean  ``[m0, m1, m2]`` of ``M_a``
``imu.gyro_g_sensitivity`` (9,)    euclidean  ``A_w`` row-major, rad/s per m/s^2
``lidar.intrinsics``       (B, 6)  euclidean  per beam ``[dphi, dtheta, V, H, s, drho]``
=========================  ======  =========  ==============================================

A residual block reads the blocks it needs from the value mapping and returns Jacobians only for
blocks present in it (absent intrinsic blocks take their identity/zero value).
"""

from __future__ import annotations

TRAJ_SO3 = "traj.so3"
TRAJ_R3 = "traj.r3"
GYRO_BIAS = "imu.gyro_bias"
ACCEL_BIAS = "imu.accel_bias"
GRAVITY = "gravity"
EXT_ROTATION = "ext.rotation"
EXT_TRANSLATION = "ext.translation"
TIME_OFFSET = "ext.time_offset"
GYRO_SCALE = "imu.gyro_scale"
GYRO_MISALIGNMENT = "imu.gyro_misalignment"
GYRO_ROTATION = "imu.gyro_rotation"
ACCEL_SCALE = "imu.accel_scale"
ACCEL_MISALIGNMENT = "imu.accel_misalignment"
GYRO_G_SENSITIVITY = "imu.gyro_g_sensitivity"
LIDAR_INTRINSICS = "lidar.intrinsics"
GYRO_BIAS_DRIFT = "imu.gyro_bias_drift"
ACCEL_BIAS_DRIFT = "imu.accel_bias_drift"
TIME_DRIFT = "ext.time_drift"
POINT_TIME_SCALE = "lidar.point_time_scale"

# The submodules import the names above from this package.
from licalib_cli.residuals.imu import AccelResidual, GyroResidual  # noqa: E402
from licalib_cli.residuals.lidar import PointToPlaneResidual  # noqa: E402
from licalib_cli.residuals.priors import GaussianPrior  # noqa: E402

__all__ = [
    "ACCEL_BIAS",
    "ACCEL_BIAS_DRIFT",
    "ACCEL_MISALIGNMENT",
    "ACCEL_SCALE",
    "EXT_ROTATION",
    "EXT_TRANSLATION",
    "GRAVITY",
    "GYRO_BIAS",
    "GYRO_BIAS_DRIFT",
    "GYRO_G_SENSITIVITY",
    "GYRO_MISALIGNMENT",
    "GYRO_ROTATION",
    "GYRO_SCALE",
    "LIDAR_INTRINSICS",
    "POINT_TIME_SCALE",
    "TIME_DRIFT",
    "TIME_OFFSET",
    "TRAJ_R3",
    "TRAJ_SO3",
    "AccelResidual",
    "GaussianPrior",
    "GyroResidual",
    "PointToPlaneResidual",
]
