"""Rotations SO(3), unit quaternions and rigid transforms, vectorised over leading axes.

Conventions:

* Rotation vectors ``phi`` are ``(..., 3)`` float64 in radians; ``exp(phi)`` is the rotation by
  ``|phi|`` about ``phi / |phi|`` (right-handed).
* Rotation matrices are ``(..., 3, 3)``; ``R_a_b`` maps vectors from frame ``b`` into frame ``a``.
* Quaternions are Hamilton ``[x, y, z, w]``, ``(..., 4)``; ``q`` and ``-q`` are the same rotation,
  functions returning quaternions from matrices pick ``w >= 0``.
* Jacobians of the exponential map: ``exp(phi + dphi) ~= exp(phi) @ exp(Jr(phi) @ dphi)``
  (right Jacobian) and ``exp(phi + dphi) ~= exp(Jl(phi) @ dphi) @ exp(phi)`` (left Jacobian),
  with ``Jl(phi) = Jr(-phi) = exp(phi) @ Jr(phi)``.
* Roll/pitch/yaw are radians here with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``; degrees are an
  I/O concern.
* A rigid transform is a pair ``(R_a_b (..., 3, 3), t_a_b (..., 3))`` with
  ``p_a = R_a_b p_b + t_a_b``.

The coefficient functions of ``|phi|`` use Taylor expansions below a small-angle threshold (the
same scheme as Sophus ``so3.hpp``), chosen so that values are accurate to about 1e-15 relative both
near the identity and up to angles close to pi. All functions are pure numpy and never loop in
Python over the leading axes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

__all__ = [
    "Jl",
    "Jl_inv",
    "Jr",
    "Jr_inv",
    "exp",
    "hat",
    "log",
    "matrix_to_quat",
    "matrix_to_rpy",
    "project_to_so3",
    "quat_conjugate",
    "quat_exp",
    "quat_left_matrix",
    "quat_log",
    "quat_multiply",
    "quat_normalize",
    "quat_right_matrix",
    "quat_rotate",
    "quat_to_matrix",
    "rpy_to_matrix",
    "se3_compose",
    "se3_from_matrix",
    "se3_inverse",
    "se3_to_matrix",
    "transform_points",
    "vee",
]

FloatArray = npt.NDArray[np.float64]

# Below this angle (radians) the coefficient functions use their Taylor polynomials (up to
# theta^8 or theta^10), whose truncation error is < 1e-19 relative. Above it the closed forms
# lose at most ~1e-13 relative through cancellation, and those coefficients multiply
# theta^2 >= 1e-2 in every matrix they enter, i.e. ~1e-15 relative to the identity. When every
# angle of a batch is small (the common case inside a spline segment) no trigonometric function
# is evaluated at all.
_SMALL_ANGLE = 0.1


def _as_float(x: npt.ArrayLike) -> FloatArray:
    return np.asarray(x, dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Scalar coefficient functions of theta (vectorised). All accept theta >= 0 of any shape.
# --------------------------------------------------------------------------------------------


def _series_or_closed(
    theta: FloatArray,
    series: Callable[[FloatArray], FloatArray],
    closed: Callable[[FloatArray], FloatArray],
) -> FloatArray:
    """``series(theta^2)`` below :data:`_SMALL_ANGLE`, ``closed(theta)`` above."""
    theta = np.asarray(theta, dtype=np.float64)
    small = theta < _SMALL_ANGLE
    if small.all():
        return series(theta * theta)
    out = closed(np.where(small, 1.0, theta))
    if small.any():
        out = np.where(small, series(theta * theta), out)
    return out


def _sin_over_theta(theta: FloatArray) -> FloatArray:
    """sin(theta) / theta."""
    return _series_or_closed(
        theta,
        lambda t: (
            1.0 + t * (-1 / 6 + t * (1 / 120 + t * (-1 / 5040 + t * (1 / 362880 - t / 39916800))))
        ),
        lambda x: np.sin(x) / x,
    )


def _one_minus_cos_over_theta2(theta: FloatArray) -> FloatArray:
    """(1 - cos theta) / theta^2, closed form 2 sin^2(theta/2) / theta^2 (no cancellation)."""

    def closed(x: FloatArray) -> FloatArray:
        s = np.sin(0.5 * x) / x
        return 2.0 * s * s

    return _series_or_closed(
        theta,
        lambda t: (
            0.5
            + t * (-1 / 24 + t * (1 / 720 + t * (-1 / 40320 + t * (1 / 3628800 - t / 479001600))))
        ),
        closed,
    )


def _theta_minus_sin_over_theta3(theta: FloatArray) -> FloatArray:
    """(theta - sin theta) / theta^3."""
    return _series_or_closed(
        theta,
        lambda t: (
            1 / 6
            + t
            * (-1 / 120 + t * (1 / 5040 + t * (-1 / 362880 + t * (1 / 39916800 - t / 6227020800))))
        ),
        lambda x: (x - np.sin(x)) / (x * x * x),
    )


def _jr_inv_coefficient(theta: FloatArray) -> FloatArray:
    """(1 - (theta/2) cot(theta/2)) / theta^2. Singular at theta = 2 pi."""

    def closed(x: FloatArray) -> FloatArray:
        half = 0.5 * x
        return (1.0 - half * np.cos(half) / np.sin(half)) / (x * x)

    return _series_or_closed(
        theta,
        # 1 - x cot x = sum 2^2n |B_2n| x^2n / (2n)!, x = theta / 2
        lambda t: (
            1 / 12
            + t
            * (
                1 / 720
                + t
                * (1 / 30240 + t * (1 / 1209600 + t * (1 / 47900160 + t * 1382 / 2615348736000)))
            )
        ),
        closed,
    )


def _half_sin_half_over_theta(theta: FloatArray) -> FloatArray:
    """sin(theta / 2) / theta."""
    return _series_or_closed(
        theta,
        lambda t: 0.5 + t * (-1 / 48 + t * (1 / 3840 + t * (-1 / 645120 + t / 185794560))),
        lambda x: np.sin(0.5 * x) / x,
    )


# --------------------------------------------------------------------------------------------
# so(3) <-> R^3 and the exponential / logarithm maps
# --------------------------------------------------------------------------------------------


def hat(v: npt.ArrayLike) -> FloatArray:
    """Skew-symmetric matrix of a vector: ``hat(v) @ w == cross(v, w)``.

    Args:
        v: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.
    """
    v = _as_float(v)
    out = np.zeros((*v.shape[:-1], 3, 3))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    out[..., 0, 1] = -z
    out[..., 0, 2] = y
    out[..., 1, 0] = z
    out[..., 1, 2] = -x
    out[..., 2, 0] = -y
    out[..., 2, 1] = x
    return out


def vee(m: npt.ArrayLike) -> FloatArray:
    """Inverse of :func:`hat`, using the antisymmetric part of ``m``.

    Args:
        m: (..., 3, 3) matrices (skew-symmetric up to round-off).

    Returns:
        (..., 3) vectors.
    """
    m = _as_float(m)
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


def _outer_plus_diag(
    phi: FloatArray, diag: FloatArray, outer: FloatArray, skew: FloatArray
) -> FloatArray:
    """``diag I + outer phi phi^T + skew hat(phi)``; (..., 3) phi, (...,) coefficients."""
    out = outer[..., None, None] * (phi[..., :, None] * phi[..., None, :])
    out += skew[..., None, None] * hat(phi)
    out[..., 0, 0] += diag
    out[..., 1, 1] += diag
    out[..., 2, 2] += diag
    return out


def exp(phi: npt.ArrayLike) -> FloatArray:
    """Rotation matrix of a rotation vector (Rodrigues' formula).

    ``R = I + a hat(phi) + b hat(phi)^2`` with ``a = sin(theta)/theta``,
    ``b = (1 - cos theta)/theta^2``.

    Args:
        phi: (..., 3) rotation vectors, radians.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    phi = _as_float(phi)
    theta = np.linalg.norm(phi, axis=-1)
    a = _sin_over_theta(theta)
    b = _one_minus_cos_over_theta2(theta)
    # hat^2 = phi phi^T - theta^2 I
    return _outer_plus_diag(phi, 1.0 - b * theta * theta, b, a)


def log(R: npt.ArrayLike) -> FloatArray:
    """Rotation vector of a rotation matrix, with ``|phi| <= pi``.

    Goes through a Shepperd quaternion extraction, which is accurate near the identity and
    near pi (where the trace-based formula fails).

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors, radians.
    """
    return quat_log(matrix_to_quat(R))


def Jr(phi: npt.ArrayLike) -> FloatArray:
    """Right Jacobian of SO(3): ``exp(phi + d) ~= exp(phi) exp(Jr(phi) d)``.

    ``Jr = I - b hat(phi) + c hat(phi)^2`` with ``b = (1 - cos theta)/theta^2``,
    ``c = (theta - sin theta)/theta^3``.

    Args:
        phi: (..., 3) rotation vectors.

    Returns:
        (..., 3, 3) Jacobians.
    """
    phi = _as_float(phi)
    theta = np.linalg.norm(phi, axis=-1)
    b = _one_minus_cos_over_theta2(theta)
    c = _theta_minus_sin_over_theta3(theta)
    return _outer_plus_diag(phi, 1.0 - c * theta * theta, c, -b)


def Jr_inv(phi: npt.ArrayLike) -> FloatArray:
    """Inverse right Jacobian: ``log(exp(phi) exp(d)) ~= phi + Jr_inv(phi) d``.

    ``Jr_inv = I + hat(phi)/2 + e hat(phi)^2`` with ``e = (1 - (theta/2) cot(theta/2))/theta^2``.
    Valid for ``|phi| < 2 pi``.

    Args:
        phi: (..., 3) rotation vectors.

    Returns:
        (..., 3, 3) matrices.
    """
    phi = _as_float(phi)
    theta = np.linalg.norm(phi, axis=-1)
    e = _jr_inv_coefficient(theta)
    return _outer_plus_diag(phi, 1.0 - e * theta * theta, e, np.full_like(theta, 0.5))


def Jl(phi: npt.ArrayLike) -> FloatArray:
    """Left Jacobian of SO(3): ``exp(phi + d) ~= exp(Jl(phi) d) exp(phi)``; ``Jl(phi) = Jr(-phi)``.

    Args:
        phi: (..., 3) rotation vectors.

    Returns:
        (..., 3, 3) Jacobians.
    """
    return Jr(-_as_float(phi))


def Jl_inv(phi: npt.ArrayLike) -> FloatArray:
    """Inverse left Jacobian: ``log(exp(d) exp(phi)) ~= phi + Jl_inv(phi) d``; ``= Jr_inv(-phi)``.

    Args:
        phi: (..., 3) rotation vectors.

    Returns:
        (..., 3, 3) matrices.
    """
    return Jr_inv(-_as_float(phi))


def project_to_so3(m: npt.ArrayLike) -> FloatArray:
    """Nearest rotation matrix in the Frobenius norm (SVD with determinant fix).

    Args:
        m: (..., 3, 3) matrices.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    m = _as_float(m)
    u, _, vt = np.linalg.svd(m)
    det = np.linalg.det(u @ vt)
    u = u.copy()
    u[..., :, 2] *= det[..., None]
    return u @ vt


# --------------------------------------------------------------------------------------------
# Quaternions [x, y, z, w]
# --------------------------------------------------------------------------------------------


def quat_normalize(q: npt.ArrayLike) -> FloatArray:
    """Unit quaternions with ``w >= 0``.

    Args:
        q: (..., 4) quaternions ``[x, y, z, w]``, non-zero.

    Returns:
        (..., 4) unit quaternions, canonical sign ``w >= 0``.
    """
    u = _as_float(q)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    return np.where(u[..., 3:4] < 0.0, -u, u)


def quat_conjugate(q: npt.ArrayLike) -> FloatArray:
    """Conjugate (the inverse for unit quaternions).

    Args:
        q: (..., 4) quaternions ``[x, y, z, w]``.

    Returns:
        (..., 4) ``[-x, -y, -z, w]``.
    """
    q = _as_float(q)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def quat_multiply(q1: npt.ArrayLike, q2: npt.ArrayLike) -> FloatArray:
    """Hamilton product ``q1 * q2`` (rotation ``q1`` after ``q2``: ``R(q1 q2) = R(q1) R(q2)``).

    Args:
        q1: (..., 4) quaternions ``[x, y, z, w]``.
        q2: (..., 4) quaternions ``[x, y, z, w]``; broadcast against ``q1``.

    Returns:
        (..., 4) products (not re-normalised).
    """
    q1 = _as_float(q1)
    q2 = _as_float(q2)
    v1, w1 = q1[..., :3], q1[..., 3:]
    v2, w2 = q2[..., :3], q2[..., 3:]
    v = w1 * v2 + w2 * v1 + np.cross(v1, v2)
    w = w1 * w2 - np.sum(v1 * v2, axis=-1, keepdims=True)
    return np.concatenate([v, w], axis=-1)


def quat_left_matrix(q: npt.ArrayLike) -> FloatArray:
    """Left-multiplication matrix: ``quat_multiply(q, p) == L(q) @ p``.

    Args:
        q: (..., 4) quaternions ``[x, y, z, w]``.

    Returns:
        (..., 4, 4) ``L(q)``.
    """
    q = _as_float(q)
    v, w = q[..., :3], q[..., 3]
    out = np.empty((*q.shape[:-1], 4, 4))
    out[..., :3, :3] = w[..., None, None] * np.eye(3) + hat(v)
    out[..., :3, 3] = v
    out[..., 3, :3] = -v
    out[..., 3, 3] = w
    return out


def quat_right_matrix(q: npt.ArrayLike) -> FloatArray:
    """Right-multiplication matrix: ``quat_multiply(p, q) == R(q) @ p``.

    Args:
        q: (..., 4) quaternions ``[x, y, z, w]``.

    Returns:
        (..., 4, 4) ``R(q)``.
    """
    q = _as_float(q)
    v, w = q[..., :3], q[..., 3]
    out = np.empty((*q.shape[:-1], 4, 4))
    out[..., :3, :3] = w[..., None, None] * np.eye(3) - hat(v)
    out[..., :3, 3] = v
    out[..., 3, :3] = -v
    out[..., 3, 3] = w
    return out


def quat_exp(phi: npt.ArrayLike) -> FloatArray:
    """Unit quaternion of a rotation vector: ``[sin(theta/2) phi/theta, cos(theta/2)]``.

    Args:
        phi: (..., 3) rotation vectors, radians.

    Returns:
        (..., 4) unit quaternions ``[x, y, z, w]`` (``w < 0`` when ``theta > pi``).
    """
    phi = _as_float(phi)
    theta = np.linalg.norm(phi, axis=-1)
    s = _half_sin_half_over_theta(theta)
    return np.concatenate([s[..., None] * phi, np.cos(0.5 * theta)[..., None]], axis=-1)


def quat_log(q: npt.ArrayLike) -> FloatArray:
    """Rotation vector of a unit quaternion, with ``|phi| <= pi`` (``q`` and ``-q`` agree).

    ``phi = 2 atan2(|v|, w) v / |v|`` after making ``w >= 0``; Taylor for ``|v| < 1e-8``
    (``2/w (1 - |v|^2 / (3 w^2))``, as in Sophus).

    Args:
        q: (..., 4) unit quaternions ``[x, y, z, w]``.

    Returns:
        (..., 3) rotation vectors, radians.
    """
    q = _as_float(q)
    q = np.where(q[..., 3:4] < 0.0, -q, q)
    v, w = q[..., :3], q[..., 3]
    n = np.linalg.norm(v, axis=-1)
    small = n < 1e-8
    safe_n = np.where(small, 1.0, n)
    safe_w = np.where(small, w, 1.0)
    taylor = 2.0 / safe_w * (1.0 - n * n / (3.0 * safe_w * safe_w))
    factor = np.where(small, taylor, 2.0 * np.arctan2(n, w) / safe_n)
    return factor[..., None] * v


def quat_to_matrix(q: npt.ArrayLike) -> FloatArray:
    """Rotation matrix of a quaternion (normalised first).

    Args:
        q: (..., 4) quaternions ``[x, y, z, w]``, non-zero.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    u = _as_float(q)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    x, y, z, w = u[..., 0], u[..., 1], u[..., 2], u[..., 3]
    out = np.empty((*u.shape[:-1], 3, 3))
    out[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[..., 0, 1] = 2.0 * (x * y - z * w)
    out[..., 0, 2] = 2.0 * (x * z + y * w)
    out[..., 1, 0] = 2.0 * (x * y + z * w)
    out[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[..., 1, 2] = 2.0 * (y * z - x * w)
    out[..., 2, 0] = 2.0 * (x * z - y * w)
    out[..., 2, 1] = 2.0 * (y * z + x * w)
    out[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return out


def matrix_to_quat(R: npt.ArrayLike) -> FloatArray:
    """Unit quaternion of a rotation matrix (Shepperd's method), canonical ``w >= 0``.

    Picks the largest of ``w, x, y, z`` to divide by, so the result is accurate for every
    rotation including angles near pi.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) unit quaternions ``[x, y, z, w]`` with ``w >= 0``.
    """
    R = _as_float(R)
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # 4 * (component)^2 for w, x, y, z
    cand = np.stack(
        [
            1.0 + r00 + r11 + r22,
            1.0 + r00 - r11 - r22,
            1.0 - r00 + r11 - r22,
            1.0 - r00 - r11 + r22,
        ],
        axis=-1,
    )
    k = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], axis=-1)[..., 0], 1e-300))
    # each row: [x, y, z, w] * s, for the four choices of pivot
    q_w = np.stack([r21 - r12, r02 - r20, r10 - r01, 0.25 * s * s], axis=-1)
    q_x = np.stack([0.25 * s * s, r01 + r10, r02 + r20, r21 - r12], axis=-1)
    q_y = np.stack([r01 + r10, 0.25 * s * s, r12 + r21, r02 - r20], axis=-1)
    q_z = np.stack([r02 + r20, r12 + r21, 0.25 * s * s, r10 - r01], axis=-1)
    cands = np.stack([q_w, q_x, q_y, q_z], axis=-2)
    q = np.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :] / s[..., None]
    return quat_normalize(q)


def quat_rotate(q: npt.ArrayLike, v: npt.ArrayLike) -> FloatArray:
    """Rotate vectors by unit quaternions: ``R(q) v``.

    Args:
        q: (..., 4) unit quaternions ``[x, y, z, w]``.
        v: (..., 3) vectors; broadcast against ``q``.

    Returns:
        (..., 3) rotated vectors.
    """
    q = _as_float(q)
    v = _as_float(v)
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


# --------------------------------------------------------------------------------------------
# Roll / pitch / yaw (radians), R = Rz(yaw) Ry(pitch) Rx(roll)
# --------------------------------------------------------------------------------------------


def rpy_to_matrix(rpy: npt.ArrayLike) -> FloatArray:
    """Rotation matrix ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Args:
        rpy: (..., 3) ``[roll, pitch, yaw]`` in radians.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    rpy = _as_float(rpy)
    cr, sr = np.cos(rpy[..., 0]), np.sin(rpy[..., 0])
    cp, sp = np.cos(rpy[..., 1]), np.sin(rpy[..., 1])
    cy, sy = np.cos(rpy[..., 2]), np.sin(rpy[..., 2])
    out = np.empty((*rpy.shape[:-1], 3, 3))
    out[..., 0, 0] = cy * cp
    out[..., 0, 1] = cy * sp * sr - sy * cr
    out[..., 0, 2] = cy * sp * cr + sy * sr
    out[..., 1, 0] = sy * cp
    out[..., 1, 1] = sy * sp * sr + cy * cr
    out[..., 1, 2] = sy * sp * cr - cy * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


def matrix_to_rpy(R: npt.ArrayLike) -> FloatArray:
    """Roll, pitch, yaw (radians) with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Pitch is in ``[-pi/2, pi/2]``, roll and yaw in ``(-pi, pi]``. At gimbal lock
    (``|pitch| = pi/2``, detected as ``cos(pitch) < 1e-10``) roll is set to 0 and the whole
    rotation about the vertical is reported as yaw.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) ``[roll, pitch, yaw]`` in radians.
    """
    R = _as_float(R)
    cp = np.hypot(R[..., 0, 0], R[..., 1, 0])
    pitch = np.arctan2(-R[..., 2, 0], cp)
    lock = cp < 1e-10
    roll = np.where(lock, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(
        lock,
        np.arctan2(-R[..., 0, 1], R[..., 1, 1]),
        np.arctan2(R[..., 1, 0], R[..., 0, 0]),
    )
    return np.stack([roll, pitch, yaw], axis=-1)


# --------------------------------------------------------------------------------------------
# Rigid transforms as (R, t) pairs
# --------------------------------------------------------------------------------------------


def transform_points(R_a_b: npt.ArrayLike, t_a_b: npt.ArrayLike, p_b: npt.ArrayLike) -> FloatArray:
    """Map points from frame ``b`` to frame ``a``: ``p_a = R_a_b p_b + t_a_b``.

    Args:
        R_a_b: (..., 3, 3) rotations; broadcast against the points.
        t_a_b: (..., 3) translations, metres.
        p_b: (..., 3) points in frame ``b``, e.g. (N, 3) with a single (3, 3) rotation.

    Returns:
        (..., 3) points in frame ``a``.
    """
    R_a_b = _as_float(R_a_b)
    p_b = _as_float(p_b)
    return np.einsum("...ij,...j->...i", R_a_b, p_b) + _as_float(t_a_b)


def se3_compose(
    R_a_b: npt.ArrayLike, t_a_b: npt.ArrayLike, R_b_c: npt.ArrayLike, t_b_c: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Compose ``T_a_c = T_a_b T_b_c``.

    Args:
        R_a_b: (..., 3, 3).
        t_a_b: (..., 3).
        R_b_c: (..., 3, 3).
        t_b_c: (..., 3).

    Returns:
        ``(R_a_c (..., 3, 3), t_a_c (..., 3))``.
    """
    R_a_b = _as_float(R_a_b)
    R_a_c = R_a_b @ _as_float(R_b_c)
    t_a_c = np.einsum("...ij,...j->...i", R_a_b, _as_float(t_b_c)) + _as_float(t_a_b)
    return R_a_c, t_a_c


def se3_inverse(R_a_b: npt.ArrayLike, t_a_b: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverse transform ``T_b_a = T_a_b^-1``.

    Args:
        R_a_b: (..., 3, 3).
        t_a_b: (..., 3).

    Returns:
        ``(R_b_a (..., 3, 3), t_b_a (..., 3))`` with ``t_b_a = -R_a_b^T t_a_b``.
    """
    R_b_a = np.swapaxes(_as_float(R_a_b), -1, -2)
    return R_b_a, -np.einsum("...ij,...j->...i", R_b_a, _as_float(t_a_b))


def se3_to_matrix(R_a_b: npt.ArrayLike, t_a_b: npt.ArrayLike) -> FloatArray:
    """Homogeneous 4x4 matrices from ``(R, t)``.

    Args:
        R_a_b: (..., 3, 3).
        t_a_b: (..., 3).

    Returns:
        (..., 4, 4) with last row ``[0, 0, 0, 1]``.
    """
    R_a_b = _as_float(R_a_b)
    t_a_b = _as_float(t_a_b)
    shape = np.broadcast_shapes(R_a_b.shape[:-2], t_a_b.shape[:-1])
    out = np.zeros((*shape, 4, 4))
    out[..., :3, :3] = R_a_b
    out[..., :3, 3] = t_a_b
    out[..., 3, 3] = 1.0
    return out


def se3_from_matrix(T_a_b: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Split homogeneous 4x4 matrices into ``(R (..., 3, 3), t (..., 3))`` (copies).

    Args:
        T_a_b: (..., 4, 4).

    Returns:
        ``(R_a_b, t_a_b)``.
    """
    T_a_b = _as_float(T_a_b)
    return T_a_b[..., :3, :3].copy(), T_a_b[..., :3, 3].copy()
