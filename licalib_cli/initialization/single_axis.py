"""Rotation extrinsic when the rig turns about one axis only (planar, vehicle-like motion).

Hand-eye alignment of relative rotations needs rotation about two axes: with one axis ``a`` the
rotations only say that ``R_imu_lidar`` maps the LiDAR's axis ``a_L`` onto the IMU's ``a_I``, and
any further rotation about ``a_I`` fits them equally well. The accelerations fix that last angle:
the LiDAR odometry's acceleration, mapped into the IMU frame, must equal the specific force plus
a constant gravity, and a vehicle driving curves accelerates in varying directions within the
plane. With ``R = Rot(a_I, psi) R0`` (``R0`` the smallest rotation taking ``a_L`` to ``a_I``) the
angle ``psi`` is a two-dimensional Procrustes problem with a closed-form solution.

The lever arm (translation extrinsic) is ignored here: its centripetal acceleration
``w^2 |t|`` is small for the slow turns of such motion, and the optimisation estimates it.

Conventions: ``p_I = R_imu_lidar p_L + t``; ``t_imu = t_lidar + t_c``; int64 ns at the interface.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from licalib_cli.errors import ExcitationError
from licalib_cli.initialization.rotation import GyroIntegrator, relative_rotations
from licalib_cli.measurements import ImuSamples
from licalib_cli.odometry import PoseSeries
from licalib_cli.spline import R3Spline, UniformKnots

__all__ = ["RotationAxes", "SingleAxisRotation", "rotation_axes", "single_axis_rotation"]

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class RotationAxes:
    """Principal axes of the rotation between consecutive times.

    Attributes:
        rms_deg: (3,) RMS rotation angle per interval about each principal axis, descending.
        axes: (3, 3) the axes as columns, in the rotating frame.
    """

    rms_deg: FloatArray
    axes: FloatArray

    @property
    def second_to_first(self) -> float:
        """How much the rig turned about a second axis relative to the first (0: one axis)."""
        return float(self.rms_deg[1] / self.rms_deg[0]) if self.rms_deg[0] > 0 else 0.0


def _axes_of(rotvec: FloatArray) -> RotationAxes:
    lam, vec = np.linalg.eigh(rotvec.T @ rotvec / max(rotvec.shape[0], 1))
    return RotationAxes(np.degrees(np.sqrt(lam[::-1].clip(min=0.0))), vec[:, ::-1])


def rotation_axes(gyro: GyroIntegrator, t_ns: npt.NDArray[np.int64]) -> RotationAxes:
    """Principal rotation axes of the IMU between consecutive (K,) times ``t_ns``."""
    rel = relative_rotations(gyro, t_ns[:-1], t_ns[1:])
    return _axes_of(np.asarray(rel.as_rotvec(), dtype=np.float64))


@dataclass(frozen=True)
class SingleAxisRotation:
    """Result of :func:`single_axis_rotation`.

    Attributes:
        R_imu_lidar: (3, 3) rotation extrinsic.
        axis_imu: (3,) the rotation axis in the IMU frame.
        axis_lidar: (3,) the same axis in the LiDAR frame.
        axis_residual_deg: RMS angle between ``R a_L``-rotated LiDAR rotation vectors and the
            IMU's over the intervals (how well one axis explains both sensors).
        relative_residual: RMS of the difference of those vectors over the RMS of the IMU's
            (:data:`MAX_RELATIVE_RESIDUAL` at most: the sensors turn together).
        planar_acceleration: RMS acceleration within the plane perpendicular to the axis after
            removing its mean, m/s^2 (what determines the angle about the axis).
        acceleration_residual: RMS misfit of the accelerations at the solution, m/s^2.
    """

    R_imu_lidar: FloatArray
    axis_imu: FloatArray
    axis_lidar: FloatArray
    axis_residual_deg: float
    relative_residual: float
    planar_acceleration: float
    acceleration_residual: float


def _align(a: FloatArray, b: FloatArray) -> FloatArray:
    """Smallest rotation (3, 3) taking unit vector ``a`` onto unit vector ``b``."""
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    c = float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return np.asarray(Rotation.from_rotvec(np.pi * perp / np.linalg.norm(perp)).as_matrix())
    return np.asarray(Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix())


MAX_RELATIVE_RESIDUAL = 0.35
"""The largest RMS difference between the LiDAR's rotations between scans (turned onto the
IMU's axis) and the IMU's, over the RMS of the IMU's. Odometry of one rig leaves 3-9 % on
figure-8s (its error of a few hundredths of a degree per interval against turns of 1-2 deg);
LiDAR poses turning as much about the same axis at other times leave 128 % (the tests' case).
The angle between the two per
interval is no measure of it: on intervals turning half a degree the odometry's error alone
tilts the LiDAR's axis by several degrees (a clean 20 s figure-8: 7.0 deg RMS, median 1.7)."""


def single_axis_rotation(
    imu: ImuSamples,
    gyro: GyroIntegrator,
    poses: PoseSeries,
    time_offset_s: float = 0.0,
    min_angle_deg: float = 0.5,
    smoothing_s: float = 0.2,
) -> SingleAxisRotation:
    """Rotation extrinsic from one rotation axis plus the accelerations in the plane.

    Args:
        imu: IMU samples (specific force in m/s^2, IMU frame).
        gyro: integrated gyro orientation of the same samples.
        poses: LiDAR odometry poses.
        time_offset_s: ``t_imu = t_lidar + time_offset_s``.
        min_angle_deg: intervals turning less than this do not define the axis.
        smoothing_s: both accelerations are smoothed over about this time (odometry positions
            differentiated twice are noisy), seconds.

    Returns:
        The rotation and how well it is supported.

    Raises:
        ExcitationError: the rig hardly turns, the two sensors disagree on the axis, or the
            accelerations within the plane are too weak to fix the angle about it.
    """
    t_imu = poses.t_ns + np.int64(round(time_offset_s * 1e9))
    inside = (t_imu >= gyro.t_ns[0]) & (t_imu <= gyro.t_ns[-1])
    idx = np.flatnonzero(inside)
    if idx.size < 10:
        msg = (
            "Fewer than 10 LiDAR poses overlap the IMU data; check the topics, the segment and "
            "the clock offset between the sensors."
        )
        raise ExcitationError(msg)
    t_imu, T_ml = t_imu[idx], poses.T_map_lidar[idx]

    # The axis, in both frames, from the relative rotations of consecutive poses.
    r_i = np.asarray(relative_rotations(gyro, t_imu[:-1], t_imu[1:]).as_rotvec())
    rot_l = Rotation.from_matrix(T_ml[:, :3, :3])
    r_l = np.asarray((rot_l[:-1].inv() * rot_l[1:]).as_rotvec())
    moving = np.linalg.norm(r_i, axis=1) > np.radians(min_angle_deg)
    if np.count_nonzero(moving) < 5:
        msg = (
            "Rotation excitation is too weak: the rig hardly turns; record while turning (e.g. "
            "driving curves) and rotating about more than one axis where possible."
        )
        raise ExcitationError(msg)
    a_i = _axes_of(r_i[moving]).axes[:, 0]
    a_l = _axes_of(r_l[moving]).axes[:, 0]
    if np.sum((r_i[moving] @ a_i) * (r_l[moving] @ a_l)) < 0.0:
        a_l = -a_l
    r0 = _align(a_l, a_i)
    mapped = r_l[moving] @ r0.T
    cos = np.einsum("ij,ij->i", mapped, r_i[moving]) / np.maximum(
        np.linalg.norm(mapped, axis=1) * np.linalg.norm(r_i[moving], axis=1), 1e-15
    )
    axis_residual = float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cos, -1, 1)) ** 2))))
    relative = float(
        np.sqrt(np.mean(np.sum((mapped - r_i[moving]) ** 2, axis=1)))
        / np.sqrt(np.mean(np.sum(r_i[moving] ** 2, axis=1)))
    )

    # Accelerations, both in the frame of the IMU at the first pose.
    t0 = int(t_imu[0])
    t_s = (t_imu - t0) * 1e-9
    knots = UniformKnots.for_interval(0.0, float(t_s[-1]), smoothing_s / 2.0)
    spacing = float(np.median(np.diff(t_s)))
    acc_m = R3Spline.fit(knots, t_s, T_ml[:, :3, 3], smoothing=1e-3 * spacing).acceleration(t_s)
    u = (acc_m @ T_ml[0, :3, :3]) @ r0.T  # R0 R_M_L(first)^T acc_M, per row
    in_span = (imu.t_ns >= t_imu[0]) & (imu.t_ns <= t_imu[-1])
    r_first = gyro(t_imu[:1])
    f_ref = (r_first.inv() * gyro(imu.t_ns[in_span])).apply(imu.accel[in_span])
    f_fit = R3Spline.fit(knots, (imu.t_ns[in_span] - t0) * 1e-9, f_ref, smoothing=0.0)
    v = f_fit.position(t_s)

    u_c = u - u.mean(axis=0)
    v_c = v - v.mean(axis=0)
    u_p = u_c - np.outer(u_c @ a_i, a_i)
    v_p = v_c - np.outer(v_c @ a_i, a_i)
    planar = float(np.sqrt(np.mean(np.sum(u_p**2, axis=1))))
    psi = float(np.arctan2(np.sum(np.cross(u_p, v_p) @ a_i), np.sum(u_p * v_p)))
    rot_psi = np.asarray(Rotation.from_rotvec(psi * a_i).as_matrix())
    misfit = float(np.sqrt(np.mean(np.sum((u_c @ rot_psi.T - v_c) ** 2, axis=1))))
    result = SingleAxisRotation(
        R_imu_lidar=rot_psi @ r0,
        axis_imu=a_i,
        axis_lidar=a_l,
        axis_residual_deg=axis_residual,
        relative_residual=relative,
        planar_acceleration=planar,
        acceleration_residual=misfit,
    )
    logger.info(
        "single-axis rotation: axis %s (IMU), axis residual %.2f deg (the rotations differ by "
        "%.0f %% of their size), planar acceleration %.2f m/s^2, misfit %.2f m/s^2",
        np.array2string(a_i, precision=3),
        axis_residual,
        100 * relative,
        planar,
        misfit,
    )
    if relative > MAX_RELATIVE_RESIDUAL:
        msg = (
            "The gyro and the LiDAR odometry disagree on how the rig turned (the rotations "
            f"between scans differ by {100 * relative:.0f} % of their size, axis residual "
            f"{axis_residual:.1f} deg RMS); check that the odometry tracked the motion and that "
            "the topics belong to one rig."
        )
        raise ExcitationError(msg)
    if planar < misfit or planar < 0.05:
        msg = (
            "Rotation excitation is too weak: the rig turned about one axis only and its "
            f"accelerations within the plane ({planar:.2f} m/s^2 RMS against a misfit of "
            f"{misfit:.2f}) cannot fix the rotation about that axis; rotate the rig about more "
            "axes or drive curves with changing speed."
        )
        raise ExcitationError(msg)
    return result
