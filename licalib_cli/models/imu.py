"""IMU measurement model with analytic Jacobians (method.md sections 2-3).

Conventions::

    a_I = R(t)^T (p_ddot(t) - g_G)                       specific force, IMU frame, m/s^2
    w_m = S_w M_w R_wI w_I(t) + A_w a_I(t) + b_w          gyro reading, rad/s
    a_m = S_a M_a a_I(t) + b_a                            accelerometer reading, m/s^2

``R(t) = R_G_I(t)``, ``w_I`` the body rate (IMU frame), ``g_G`` gravity in ``{G}`` (e.g.
``[0, 0, -9.81]`` when z is up). ``S = diag(scale)``, ``M = [[1, m0, m1], [0, 1, m2], [0, 0, 1]]``
from ``misalignment = [m0, m1, m2]``, ``R_wI`` (quaternion ``[x, y, z, w]``) rotates IMU-frame
vectors into the gyro frame and is perturbed on the right (``R_wI Exp(delta)``), ``A_w`` is the
(3, 3) g-sensitivity flattened row-major into 9 numbers. :func:`gyro_model` and
:func:`accel_model` are the one forward model (with derivatives); :func:`imu_measure` applies
them to an :class:`~licalib_cli.models.intrinsics.ImuIntrinsics` (the simulator's readings).

A bias that walks over the segment (``diagnose``'s ``gyro_bias_walk`` / ``accel_bias_walk``)
is ``b(t) = b + sum_k d_k B_k(t)``: continuous and piecewise linear, with drift ``d_k`` (per axis,
per second) over piece ``k`` of ``K`` equal pieces of the segment ``[0, 2 t_ref]`` and the value
``b`` at ``t_ref`` (:func:`bias_drift_basis`). With one piece it is the linear drift
``b + d (t - t_ref)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry.so3 import hat, quat_to_matrix
from licalib_cli.models.intrinsics import ImuIntrinsics, misalignment_matrix

__all__ = [
    "AccelModel",
    "GyroModel",
    "SpecificForce",
    "accel_model",
    "bias_drift_basis",
    "drift_pieces",
    "gyro_model",
    "imu_measure",
    "resample_drift",
    "specific_force",
]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SpecificForce:
    """Specific force ``a_I = R^T (p_ddot - g)`` and its derivatives.

    Attributes:
        value: (N, 3) ``a_I``, m/s^2, IMU frame.
        d_rotation: (N, 3, 3) derivative w.r.t. a right perturbation ``R Exp(eps)``
            (``hat(a_I)``).
        d_acceleration: (N, 3, 3) derivative w.r.t. ``p_ddot`` (``R^T``); that w.r.t. gravity
            is its negative.
    """

    value: F64
    d_rotation: F64
    d_acceleration: F64


def specific_force(rotation: F64, acceleration: F64, gravity: F64) -> SpecificForce:
    """Specific force in the IMU frame with derivatives.

    Args:
        rotation: (N, 3, 3) ``R_G_I(t)``.
        acceleration: (N, 3) ``p_ddot(t)`` in ``{G}``, m/s^2.
        gravity: (3,) ``g_G``, m/s^2.

    Returns:
        :class:`SpecificForce`.
    """
    rt = np.swapaxes(rotation, -1, -2)
    a = np.einsum("nij,nj->ni", rt, acceleration - gravity)
    # (R Exp(eps))^T v = Exp(-eps) R^T v ~= a - eps x a = a + hat(a) eps
    return SpecificForce(a, hat(a), rt)


def _scale_misalignment_jacobians(scale: F64, misalignment: F64, v: F64) -> tuple[F64, F64, F64]:
    """``y = S M v`` and its derivatives w.r.t. ``scale`` and ``misalignment`` (each (N, 3, 3))."""
    mv = v @ misalignment_matrix(misalignment).T
    y = mv * scale
    n = v.shape[0]
    d_scale = np.zeros((n, 3, 3))
    d_scale[:, 0, 0] = mv[:, 0]
    d_scale[:, 1, 1] = mv[:, 1]
    d_scale[:, 2, 2] = mv[:, 2]
    d_mis = np.zeros((n, 3, 3))
    d_mis[:, 0, 0] = scale[0] * v[:, 1]
    d_mis[:, 0, 1] = scale[0] * v[:, 2]
    d_mis[:, 1, 2] = scale[1] * v[:, 2]
    return y, d_scale, d_mis


@dataclass(frozen=True)
class GyroModel:
    """Predicted gyro readings and derivatives.

    Attributes:
        value: (N, 3) predicted readings, rad/s.
        d_omega: (3, 3) derivative w.r.t. ``w_I`` (``S_w M_w R_wI``).
        d_accel: (3, 3) derivative w.r.t. ``a_I`` (``A_w``).
        d_scale: (N, 3, 3) w.r.t. ``gyro_scale``, or None.
        d_misalignment: (N, 3, 3) w.r.t. ``gyro_misalignment``, or None.
        d_rotation: (N, 3, 3) w.r.t. the right perturbation of ``R_wI``, rad/s per rad, or None.
        d_g_sensitivity: (N, 3, 9) w.r.t. the row-major ``A_w``, or None.
    """

    value: F64
    d_omega: F64
    d_accel: F64
    d_scale: F64 | None
    d_misalignment: F64 | None
    d_rotation: F64 | None
    d_g_sensitivity: F64 | None


def gyro_model(
    omega: F64,
    accel: F64 | None,
    scale: F64,
    misalignment: F64,
    rotation: F64,
    bias: F64,
    g_sensitivity: F64 | None = None,
    jacobians: bool = True,
) -> GyroModel:
    """Gyro prediction ``S_w M_w R_wI w_I + A_w a_I + b_w``.

    Args:
        omega: (N, 3) body rate ``w_I``, rad/s.
        accel: (N, 3) specific force ``a_I``, m/s^2 (needed only with g-sensitivity).
        scale: (3,) ``S_w`` diagonal.
        misalignment: (3,) ``[m0, m1, m2]`` of ``M_w``.
        rotation: (4,) quaternion ``[x, y, z, w]`` of ``R_wI``.
        bias: (3,) ``b_w``, rad/s (derivative: identity).
        g_sensitivity: (9,) or (3, 3) ``A_w`` (rad/s per m/s^2), or None for none.
        jacobians: also return the intrinsic derivatives.

    Returns:
        :class:`GyroModel`.
    """
    r_wi = quat_to_matrix(rotation)
    v = omega @ r_wi.T
    y, d_scale, d_mis = _scale_misalignment_jacobians(scale, misalignment, v)
    k = np.diag(scale) @ misalignment_matrix(misalignment)
    a_w = np.zeros((3, 3)) if g_sensitivity is None else np.reshape(g_sensitivity, (3, 3))
    if g_sensitivity is not None and accel is not None:
        y = y + accel @ a_w.T
    y = y + bias
    if not jacobians:
        return GyroModel(y, k @ r_wi, a_w, None, None, None, None)
    # R_wI Exp(d) w ~= R_wI (w + d x w) = R_wI w - R_wI hat(w) d
    d_rot = -np.einsum("ij,njk->nik", k @ r_wi, hat(omega))
    d_gs = None
    if g_sensitivity is not None and accel is not None:
        n = omega.shape[0]
        d_gs = np.zeros((n, 3, 9))
        for i in range(3):  # the three rows of A_w
            d_gs[:, i, 3 * i : 3 * i + 3] = accel
    return GyroModel(y, k @ r_wi, a_w, d_scale, d_mis, d_rot, d_gs)


@dataclass(frozen=True)
class AccelModel:
    """Predicted accelerometer readings and derivatives.

    Attributes:
        value: (N, 3) predicted readings, m/s^2.
        d_accel: (3, 3) derivative w.r.t. ``a_I`` (``S_a M_a``).
        d_scale: (N, 3, 3) w.r.t. ``accel_scale``, or None.
        d_misalignment: (N, 3, 3) w.r.t. ``accel_misalignment``, or None.
    """

    value: F64
    d_accel: F64
    d_scale: F64 | None
    d_misalignment: F64 | None


def accel_model(
    accel: F64, scale: F64, misalignment: F64, bias: F64, jacobians: bool = True
) -> AccelModel:
    """Accelerometer prediction ``S_a M_a a_I + b_a``.

    Args:
        accel: (N, 3) specific force ``a_I``, m/s^2.
        scale: (3,) ``S_a`` diagonal.
        misalignment: (3,) ``[m0, m1, m2]`` of ``M_a``.
        bias: (3,) ``b_a``, m/s^2 (derivative: identity).
        jacobians: also return the intrinsic derivatives.

    Returns:
        :class:`AccelModel`.
    """
    y, d_scale, d_mis = _scale_misalignment_jacobians(scale, misalignment, accel)
    k = np.diag(scale) @ misalignment_matrix(misalignment)
    if not jacobians:
        return AccelModel(y + bias, k, None, None)
    return AccelModel(y + bias, k, d_scale, d_mis)


def imu_measure(intrinsics: ImuIntrinsics, omega_imu: F64, accel_imu: F64) -> tuple[F64, F64]:
    """Noise-free IMU readings from the true body rate and specific force.

    Args:
        intrinsics: the IMU model parameters (biases included).
        omega_imu: (N, 3) angular velocity of the IMU frame, in the IMU frame, rad/s.
        accel_imu: (N, 3) specific force ``R^T (p_ddot - g)`` in the IMU frame, m/s^2.

    Returns:
        ``(gyro_m, accel_m)``, each (N, 3): :func:`gyro_model` and :func:`accel_model`.
    """
    k = intrinsics
    gyro = gyro_model(
        omega_imu,
        accel_imu,
        k.gyro_scale,
        k.gyro_misalignment,
        k.gyro_rotation,
        k.gyro_bias,
        k.gyro_g_sensitivity,
        jacobians=False,
    )
    accel = accel_model(accel_imu, k.accel_scale, k.accel_misalignment, k.accel_bias, False)
    return gyro.value, accel.value


def drift_pieces(t_ref_s: float, piece_s: float | None) -> int:
    """Number of equal pieces of a bias walk over the segment ``[0, 2 t_ref_s]`` with pieces of
    about ``piece_s`` seconds (None: one piece, a linear drift)."""
    if piece_s is None or not piece_s > 0.0:
        return 1
    return max(1, round(2.0 * float(t_ref_s) / float(piece_s)))


def bias_drift_basis(t_s: npt.ArrayLike, t_ref_s: float, pieces: int) -> F64:
    """(N, K) ``B_k(t)``: how the bias at ``t`` moves per unit drift of piece ``k``.

    The segment ``[0, 2 t_ref_s]`` is cut into ``pieces`` equal pieces; ``B_k(t)`` is the time
    spent in piece ``k`` between ``t_ref_s`` and ``t`` (negative before ``t_ref_s``), the first
    piece reaching back and the last forward without end. The bias ``b + sum_k d_k B_k(t)`` is
    therefore continuous, linear within each piece with slope ``d_k``, and ``b`` at ``t_ref_s``;
    one piece gives ``t - t_ref_s``.
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    k = max(int(pieces), 1)
    edges = np.linspace(0.0, 2.0 * float(t_ref_s), k + 1)
    lo = edges[:-1].copy()
    hi = edges[1:].copy()
    lo[0], hi[-1] = -np.inf, np.inf
    return np.clip(t[:, None], lo, hi) - np.clip(float(t_ref_s), lo, hi)[None, :]


def resample_drift(drift: npt.ArrayLike, pieces: int) -> F64:
    """A bias walk's drifts ``(3,)`` (one piece) or ``(K, 3)`` given with ``pieces`` pieces: the
    same when the count matches, every piece at the one drift when going from one piece (the same
    bias), else every piece at the mean drift. Returns ``(3,)`` for one piece, ``(pieces, 3)``
    otherwise."""
    d = np.asarray(drift, dtype=np.float64).reshape(-1, 3)
    k = max(int(pieces), 1)
    if d.shape[0] != k:
        d = np.repeat(d.mean(axis=0, keepdims=True), k, axis=0)
    return d.reshape(3).copy() if k == 1 else d.copy()
