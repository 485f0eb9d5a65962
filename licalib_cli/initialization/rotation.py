"""Gyro integration and the hand-eye rotation extrinsic (paper Sec. IV-A, eq. initializeR).

Conventions:
    - Quaternions are Hamilton, stored ``[x, y, z, w]``; ``q ⊗ p`` composes like ``R_q @ R_p``.
    - ``R_imu_lidar`` maps LiDAR vectors into the IMU frame: ``p_I = R p_L + t``.
    - A relative rotation between times ``a`` and ``b`` is ``R_a_b = R_w(a)^T R_w(b)``: the frame
      at ``b`` expressed in the frame at ``a``. For the same interval the IMU and LiDAR relative
      rotations satisfy ``R_I_ab R_imu_lidar = R_imu_lidar R_L_ab``, i.e. in quaternions
      ``(L(q_I) - R(q_L)) q = 0`` with ``L``/``R`` the left/right multiplication matrices.
    - Gyro rates are rad/s in the IMU (gyro) frame; the integrated orientation ``R_ref_imu(t)`` is
      relative to the IMU frame at the first sample (the identity there).
    - Times are int64 nanoseconds at the interface and float seconds inside.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from licalib_cli.errors import DataError, ExcitationError, TimestampError
from licalib_cli.geometry.so3 import quat_left_matrix, quat_multiply, quat_right_matrix
from licalib_cli.measurements import ImuSamples
from licalib_cli.odometry import PoseSeries

__all__ = [
    "GyroIntegrator",
    "HandEyeConfig",
    "HandEyeRotation",
    "Handedness",
    "constant_velocity_error_deg",
    "estimate_rotation_extrinsic",
    "gyro_handedness",
    "lidar_rotation_at",
    "paired_rotations",
    "relative_rotations",
    "solve_hand_eye_rotation",
]

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
RotationAt = Callable[[npt.NDArray[np.int64]], Rotation]


def _prefix_product(q: FloatArray) -> FloatArray:
    """Inclusive prefix product ``q_0 ⊗ q_1 ⊗ ... ⊗ q_i`` of (N, 4) quaternions.

    Hillis-Steele scan: ``ceil(log2 N)`` vectorised passes instead of a loop over samples.
    """
    out = q.copy()
    d = 1
    while d < out.shape[0]:
        out[d:] = quat_multiply(out[:-d], out[d:])
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        d *= 2
    return out


@dataclass(frozen=True)
class GyroIntegrator:
    """Orientation ``R_ref_imu(t)`` integrated from gyro rates (no gravity, no accelerometer).

    The rate is taken as linear between samples (trapezoidal increments); the orientation at a
    query time continues from the previous sample with the integral of the linear rate.

    Attributes:
        t_ns: (N,) int64 sample times, nanoseconds, strictly increasing.
        omega: (N, 3) float64 bias-corrected angular rate, rad/s, IMU frame.
        q_ref_imu: (N, 4) float64 ``[x, y, z, w]`` orientation at each sample (first: identity).
    """

    t_ns: npt.NDArray[np.int64]
    omega: FloatArray
    q_ref_imu: FloatArray

    @classmethod
    def from_imu(cls, imu: ImuSamples, gyro_bias: FloatArray | None = None) -> GyroIntegrator:
        """Integrate ``imu.gyro - gyro_bias`` over the whole run.

        Args:
            imu: IMU samples; at least two, strictly increasing stamps.
            gyro_bias: optional (3,) rad/s bias subtracted from every sample.

        Raises:
            TimestampError: fewer than two samples or stamps not strictly increasing.
        """
        t = np.asarray(imu.t_ns, dtype=np.int64)
        if t.shape[0] < 2:
            msg = "Gyro integration needs at least two IMU samples; check the IMU topic and window."
            raise TimestampError(msg)
        dt = np.diff(t).astype(np.float64) * 1e-9
        if np.any(dt <= 0.0):
            msg = "IMU stamps are not strictly increasing; sort the samples and drop duplicates."
            raise TimestampError(msg)
        omega = np.asarray(imu.gyro, dtype=np.float64)
        if gyro_bias is not None:
            omega = omega - np.asarray(gyro_bias, dtype=np.float64)[None, :]
        dtheta = 0.5 * (omega[:-1] + omega[1:]) * dt[:, None]
        dq = Rotation.from_rotvec(dtheta).as_quat()
        q = np.empty((t.shape[0], 4))
        q[0] = (0.0, 0.0, 0.0, 1.0)
        q[1:] = _prefix_product(dq)
        return cls(t_ns=t, omega=omega, q_ref_imu=q)

    def __call__(self, t_ns: npt.NDArray[np.int64]) -> Rotation:
        """Orientation ``R_ref_imu`` at (M,) absolute times in nanoseconds.

        Raises:
            TimestampError: a query time lies outside the IMU samples.
        """
        tq = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        if tq.size and (tq.min() < self.t_ns[0] or tq.max() > self.t_ns[-1]):
            msg = (
                f"Gyro orientation requested at {tq.min()}..{tq.max()} ns, outside the IMU data "
                f"{self.t_ns[0]}..{self.t_ns[-1]} ns; restrict the window to where both sensors "
                "have data or fix the clock offset first."
            )
            raise TimestampError(msg)
        i = np.clip(np.searchsorted(self.t_ns, tq, side="right") - 1, 0, self.t_ns.shape[0] - 2)
        tau = (tq - self.t_ns[i]).astype(np.float64) * 1e-9
        dt = (self.t_ns[i + 1] - self.t_ns[i]).astype(np.float64) * 1e-9
        w0, w1 = self.omega[i], self.omega[i + 1]
        dtheta = w0 * tau[:, None] + 0.5 * (w1 - w0) * (tau**2 / dt)[:, None]
        q = quat_multiply(self.q_ref_imu[i], Rotation.from_rotvec(dtheta).as_quat())
        return Rotation.from_quat(q)


def lidar_rotation_at(
    gyro: GyroIntegrator, R_imu_lidar: FloatArray, time_offset_s: float = 0.0
) -> RotationAt:
    """LiDAR orientation ``R_ref_lidar(tau) = R_ref_imu(tau + t_c) R_imu_lidar`` at LiDAR times.

    Suitable as ``rotation_at`` of :func:`licalib_cli.odometry.run_odometry` (rotation
    pre-deskew of the scans with the gyro).

    Args:
        gyro: integrated gyro orientation.
        R_imu_lidar: (3, 3) rotation extrinsic.
        time_offset_s: ``t_imu = t_lidar + time_offset_s``, seconds.

    Returns:
        A function of (M,) int64 LiDAR times (ns) returning M rotations; times beyond the IMU
        data are clamped to its first or last sample.
    """
    r_x = Rotation.from_matrix(np.asarray(R_imu_lidar, dtype=np.float64))
    shift = np.int64(round(time_offset_s * 1e9))

    lo, hi = gyro.t_ns[0], gyro.t_ns[-1]

    def rotation_at(t_ns: npt.NDArray[np.int64]) -> Rotation:
        # Points a little outside the IMU data (first/last sweep) take the nearest orientation.
        return gyro(np.clip(np.asarray(t_ns, dtype=np.int64) + shift, lo, hi)) * r_x

    return rotation_at


def constant_velocity_error_deg(gyro: GyroIntegrator, t_ns: npt.NDArray[np.int64]) -> FloatArray:
    """How far a constant-velocity model mispredicts the rotation from one interval to the next.

    For consecutive intervals ``[t_{k-1}, t_k]`` and ``[t_k, t_{k+1}]`` of (K,) times, the angle
    of ``R_{k-1,k}^T R_{k,k+1}`` of the gyro's relative rotations: what a LiDAR odometry that
    predicts each scan's motion (and deskews it) with the previous one gets wrong in rotation.
    The angle does not depend on the rotation between the IMU and the LiDAR (it is conjugation
    invariant), so the gyro tells before any registration whether such odometry can follow.

    Args:
        gyro: integrated gyro orientation.
        t_ns: (K,) increasing absolute IMU times (e.g. the scans' latest point times plus the
            time offset); times outside the IMU data are dropped.

    Returns:
        (K', ) angles in degrees, one per pair of consecutive intervals (empty when fewer than
        three times lie inside the IMU data).
    """
    t = np.asarray(t_ns, dtype=np.int64)
    t = t[(t >= gyro.t_ns[0]) & (t <= gyro.t_ns[-1])]
    if t.shape[0] < 3:
        return np.zeros(0, dtype=np.float64)
    r = gyro(t)
    step = r[:-1].inv() * r[1:]
    return np.asarray(np.degrees((step[:-1].inv() * step[1:]).magnitude()), dtype=np.float64)


def relative_rotations(
    rotation_at: RotationAt,
    t_from_ns: npt.NDArray[np.int64],
    t_to_ns: npt.NDArray[np.int64],
) -> Rotation:
    """Relative rotations ``R_a_b = R_w(a)^T R_w(b)`` for (M,) interval starts a and ends b.

    Args:
        rotation_at: orientation ``R_w(t)`` of a frame at absolute times (for example a
            :class:`GyroIntegrator`, or a spline provided by the caller).
        t_from_ns: (M,) int64 interval starts, nanoseconds.
        t_to_ns: (M,) int64 interval ends, nanoseconds.

    Returns:
        M rotations; the frame at the end expressed in the frame at the start.
    """
    return rotation_at(np.asarray(t_from_ns)).inv() * rotation_at(np.asarray(t_to_ns))


@dataclass(frozen=True)
class HandEyeConfig:
    """Settings of the hand-eye rotation solve.

    Attributes:
        min_angle_deg: intervals whose IMU rotation is smaller than this are discarded.
        max_angle_mismatch_deg: intervals whose IMU and LiDAR rotation angles differ by more than
            ``max(this, 0.25 * angle)`` are discarded (the angle is frame independent).
        huber_deg: Huber threshold on the residual angle for the reweighting passes; intervals
            with residuals above ``max(10 * huber_deg, 5 * median)`` are dropped.
        reweight_passes: Huber reweighting passes after the first solve.
        min_pairs: fewest usable intervals.
        min_axis_ratio: the second-strongest rotation axis must carry at least this RMS angle
            relative to the strongest (rotation about a single axis leaves the extrinsic free).
        max_singular_ratio: largest accepted ratio of the smallest to the second-smallest
            singular value of the stacked system (near 1 means a two-dimensional null space).
        pair_stride: pair pose ``k`` with pose ``k + pair_stride`` when built from odometry.
    """

    min_angle_deg: float = 0.5
    max_angle_mismatch_deg: float = 1.0
    huber_deg: float = 0.3
    reweight_passes: int = 2
    min_pairs: int = 10
    min_axis_ratio: float = 0.1
    max_singular_ratio: float = 0.3
    pair_stride: int = 1


@dataclass(frozen=True)
class HandEyeRotation:
    """Result of the hand-eye rotation solve.

    Attributes:
        R_imu_lidar: (3, 3) rotation mapping LiDAR vectors into the IMU frame.
        q_imu_lidar: (4,) the same as ``[x, y, z, w]`` with ``w >= 0``.
        singular_values: (4,) singular values of the weighted stacked system, descending.
        conditioning: smallest / second-smallest singular value (small is well conditioned).
        axis_excitation_deg: (3,) RMS rotation angle per interval along the principal rotation
            axes in the IMU frame, degrees, descending (eigenvalues of the sum of ``r r^T`` of
            the interval rotation vectors, normalised by the weights).
        axes_imu: (3, 3) columns are those principal axes, IMU frame.
        n_pairs: intervals used (after filtering).
        n_pairs_total: intervals offered.
        residual_rms_deg: RMS angle of ``(R_I R)^T (R R_L)`` over the used intervals.
        std_deg: rough standard deviation of the weakest rotation direction, degrees,
            ``s_min / (s_second sqrt(n - 3))``.
    """

    R_imu_lidar: FloatArray
    q_imu_lidar: FloatArray
    singular_values: FloatArray
    conditioning: float
    axis_excitation_deg: FloatArray
    axes_imu: FloatArray
    n_pairs: int
    n_pairs_total: int
    residual_rms_deg: float
    std_deg: float


def _solve_weighted(
    q_i: FloatArray, q_l: FloatArray, w: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Smallest right singular vector of the stacked ``sqrt(w) (L(q_I) - R(q_L))``."""
    a = (quat_left_matrix(q_i) - quat_right_matrix(q_l)) * np.sqrt(w)[:, None, None]
    _, s, vt = np.linalg.svd(a.reshape(-1, 4), full_matrices=False)
    q = vt[-1]
    q = q / np.linalg.norm(q)
    return (q if q[3] >= 0.0 else -q), s


def _residual_angles(r_i: Rotation, r_l: Rotation, r_x: Rotation) -> FloatArray:
    return np.asarray(((r_i * r_x).inv() * (r_x * r_l)).magnitude(), dtype=np.float64)


def solve_hand_eye_rotation(
    rel_imu: Rotation,
    rel_lidar: Rotation,
    cfg: HandEyeConfig | None = None,
) -> HandEyeRotation:
    """Rotation extrinsic from paired relative rotations, with no initial guess.

    Args:
        rel_imu: M relative IMU rotations ``R_I_ab`` (IMU frame).
        rel_lidar: M relative LiDAR rotations ``R_L_ab`` over the same intervals.
        cfg: solve settings; defaults when None.

    Returns:
        The rotation extrinsic and its conditioning.

    Raises:
        ExcitationError: too few rotating intervals, rotation about one axis only, or an
            ill-conditioned system.
        DataError: the two inputs differ in length.
    """
    cfg = cfg or HandEyeConfig()
    if len(rel_imu) != len(rel_lidar):
        msg = (
            f"Hand-eye needs the same intervals for both sensors, got {len(rel_imu)} IMU and "
            f"{len(rel_lidar)} LiDAR rotations; pair them by time first."
        )
        raise DataError(msg)
    m_total = len(rel_imu)
    ang_i = np.asarray(rel_imu.magnitude(), dtype=np.float64)
    ang_l = np.asarray(rel_lidar.magnitude(), dtype=np.float64)
    keep = (ang_i > np.radians(cfg.min_angle_deg)) & (
        np.abs(ang_i - ang_l) <= np.maximum(np.radians(cfg.max_angle_mismatch_deg), 0.25 * ang_i)
    )
    n = int(keep.sum())
    if n < max(cfg.min_pairs, 4):
        msg = (
            f"Rotation excitation is too weak: only {n} of {m_total} scan intervals rotate more "
            f"than {cfg.min_angle_deg:g} deg consistently in both sensors (need {cfg.min_pairs}); "
            "rotate the rig about at least two axes during the recording."
        )
        raise ExcitationError(msg)
    r_i, r_l = rel_imu[keep], rel_lidar[keep]
    q_i = r_i.as_quat()
    q_l = r_l.as_quat()
    # Same rotation angle in both frames: pick the w >= 0 representative of each.
    q_i = np.where(q_i[:, 3:] < 0.0, -q_i, q_i)
    q_l = np.where(q_l[:, 3:] < 0.0, -q_l, q_l)

    rotvec = r_i.as_rotvec()
    w = np.ones(n)
    q, s = _solve_weighted(q_i, q_l, w)
    huber = np.radians(cfg.huber_deg)
    for _ in range(cfg.reweight_passes):
        e = _residual_angles(r_i, r_l, Rotation.from_quat(q))
        w = np.where(e <= huber, 1.0, huber / np.maximum(e, 1e-15))
        # Gross outliers (odometry slips) get no weight at all.
        w[e > max(10.0 * huber, 5.0 * float(np.median(e)))] = 0.0
        q, s = _solve_weighted(q_i, q_l, w)
    r_x = Rotation.from_quat(q)
    e = _residual_angles(r_i, r_l, r_x)

    excitation = (rotvec * w[:, None]).T @ rotvec / w.sum()
    lam, axes = np.linalg.eigh(excitation)
    lam, axes = lam[::-1].clip(min=0.0), axes[:, ::-1]
    axis_deg = np.degrees(np.sqrt(lam))
    cond = float(s[3] / s[2]) if s[2] > 0.0 else 1.0
    std = float(np.degrees(s[3] / s[2] / np.sqrt(max(n - 3, 1)))) if s[2] > 0.0 else np.inf
    result = HandEyeRotation(
        R_imu_lidar=r_x.as_matrix(),
        q_imu_lidar=q,
        singular_values=s,
        conditioning=cond,
        axis_excitation_deg=axis_deg,
        axes_imu=axes,
        n_pairs=n,
        n_pairs_total=m_total,
        residual_rms_deg=float(np.degrees(np.sqrt(np.mean(e**2)))),
        std_deg=std,
    )
    logger.info(
        "hand-eye rotation: %d/%d intervals, axis RMS %s deg, conditioning %.3g, residual %.3f deg",
        n,
        m_total,
        np.array2string(axis_deg, precision=2),
        cond,
        result.residual_rms_deg,
    )
    axis_ratio = axis_deg[1] / axis_deg[0] if axis_deg[0] > 0.0 else 0.0
    if axis_ratio < cfg.min_axis_ratio:
        ax = np.array2string(axes[:, 0], precision=2)
        msg = (
            f"Rotation excitation is too weak: the rig turned almost only about {ax} in the IMU "
            f"frame (second axis {axis_deg[1]:.2f} deg vs {axis_deg[0]:.2f} deg RMS per interval), "
            "which leaves the rotation extrinsic undetermined; rotate the rig about at least two "
            "axes during the recording."
        )
        raise ExcitationError(msg)
    if cond > cfg.max_singular_ratio:
        msg = (
            f"Rotation excitation is too weak: the hand-eye system is ill-conditioned "
            f"(singular value ratio {cond:.2f} > {cfg.max_singular_ratio:g}, residual "
            f"{result.residual_rms_deg:.2f} deg); rotate the rig about at least two axes and "
            "check that the odometry tracked the motion."
        )
        raise ExcitationError(msg)
    return result


def estimate_rotation_extrinsic(
    imu: ImuSamples | GyroIntegrator,
    poses: PoseSeries,
    time_offset_s: float = 0.0,
    cfg: HandEyeConfig | None = None,
    gyro_bias: FloatArray | None = None,
) -> HandEyeRotation:
    """Hand-eye rotation from gyro integration and LiDAR odometry poses.

    Pose ``k`` (LiDAR time ``tau_k``) is paired with pose ``k + cfg.pair_stride``; the IMU
    rotation is taken over ``[tau_k + t_c, tau_{k+s} + t_c]``. Poses whose IMU times fall
    outside the IMU data are skipped.

    Args:
        imu: IMU samples, or an already built :class:`GyroIntegrator`.
        poses: LiDAR odometry poses stamped with the times they refer to.
        time_offset_s: ``t_imu = t_lidar + time_offset_s``, seconds.
        cfg: solve settings; defaults when None.
        gyro_bias: (3,) rad/s subtracted before integrating (ignored for an integrator).

    Returns:
        See :func:`solve_hand_eye_rotation`.

    Raises:
        ExcitationError: see :func:`solve_hand_eye_rotation`.
        TimestampError: the IMU and LiDAR data do not overlap in time.
    """
    cfg = cfg or HandEyeConfig()
    gyro = imu if isinstance(imu, GyroIntegrator) else GyroIntegrator.from_imu(imu, gyro_bias)
    rel_i, rel_l = paired_rotations(gyro, poses, time_offset_s, cfg.pair_stride)
    return solve_hand_eye_rotation(rel_i, rel_l, cfg)


def paired_rotations(
    gyro: GyroIntegrator, poses: PoseSeries, time_offset_s: float = 0.0, pair_stride: int = 1
) -> tuple[Rotation, Rotation]:
    """The IMU's and the LiDAR's rotations over the same intervals: pose ``k`` paired with pose
    ``k + pair_stride``, the IMU's over ``[tau_k + t_c, tau_{k+s} + t_c]`` from the gyro; poses
    whose IMU times fall outside the IMU data are skipped.

    Raises:
        TimestampError: the IMU and LiDAR data do not overlap in time.
    """
    t_imu = poses.t_ns + np.int64(round(time_offset_s * 1e9))
    inside = (t_imu >= gyro.t_ns[0]) & (t_imu <= gyro.t_ns[-1])
    s = max(int(pair_stride), 1)
    k0 = np.flatnonzero(inside[:-s] & inside[s:]) if len(poses) > s else np.zeros(0, np.int64)
    if k0.size == 0:
        msg = (
            "The IMU and LiDAR data do not overlap in time; check the topics, the time window "
            "and the clock offset between the sensors."
        )
        raise TimestampError(msg)
    rot_l = poses.rotations
    return relative_rotations(gyro, t_imu[k0], t_imu[k0 + s]), rot_l[k0].inv() * rot_l[k0 + s]


LEFT_HANDED_RATIO = 0.3
"""A reflection must fit the paired rotations at least this much better than any rotation."""
LEFT_HANDED_MAX_DEG = 1.0
"""... and to within this RMS per interval, degrees, to be taken as a left-handed gyro frame."""


@dataclass(frozen=True)
class Handedness:
    """How well the gyro's rotations follow the LiDAR's through a rotation and a reflection.

    The rotation vector of each interval's IMU rotation is ``R phi_L`` for a right-handed IMU
    frame (``R`` the extrinsic rotation). An IMU whose driver flips the sign of one axis (a
    frame convention mixed up, NED against ENU) publishes ``S R phi_L`` with ``S`` a reflection:
    no rotation fits, and hand-eye fails or refuses as if the motion were poor, while an
    orthogonal matrix of determinant -1 fits as well as a rotation fits a right-handed IMU.

    Attributes:
        rotation_rms_deg: RMS of ``|phi_I - M phi_L|`` for the best rotation ``M``, degrees.
        reflection_rms_deg: the same for the best orthogonal ``M`` of determinant -1.
        intervals: intervals compared.
    """

    rotation_rms_deg: float
    reflection_rms_deg: float
    intervals: int

    @property
    def left_handed(self) -> bool:
        """Whether a reflection fits beyond doubt and a rotation does not."""
        return (
            self.intervals >= 10
            and self.reflection_rms_deg <= LEFT_HANDED_MAX_DEG
            and self.reflection_rms_deg < LEFT_HANDED_RATIO * self.rotation_rms_deg
        )


def gyro_handedness(
    gyro: GyroIntegrator, poses: PoseSeries, time_offset_s: float = 0.0, pair_stride: int = 1
) -> Handedness:
    """Fit the IMU's interval rotation vectors to the LiDAR odometry's by the best rotation and
    by the best reflection (orthogonal Procrustes, each determinant; see :class:`Handedness`).

    Raises:
        TimestampError: the IMU and LiDAR data do not overlap in time.
    """
    rel_i, rel_l = paired_rotations(gyro, poses, time_offset_s, pair_stride)
    phi_i = np.degrees(rel_i.as_rotvec())
    phi_l = np.degrees(rel_l.as_rotvec())
    u, _, vt = np.linalg.svd(phi_i.T @ phi_l)
    sign = float(np.sign(np.linalg.det(u @ vt))) or 1.0
    rms = []
    for det in (1.0, -1.0):
        m = u @ np.diag([1.0, 1.0, det * sign]) @ vt
        rms.append(float(np.sqrt(np.mean(np.sum((phi_i - phi_l @ m.T) ** 2, axis=1)))))
    return Handedness(rms[0], rms[1], int(phi_i.shape[0]))
