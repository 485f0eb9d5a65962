"""Gyroscope and accelerometer residual blocks (method.md section 3).

Each IMU sample gives a 3-vector residual ``(prediction - reading) / sigma`` (one robust-loss
group per sample), with ``sigma`` the discrete noise standard deviation
``noise_density * sqrt(rate)`` per axis, supplied by the caller. Sample times are IMU-clock
seconds relative to the problem's reference time; they do not depend on the time offset.
Predictions follow :mod:`licalib_cli.models.imu`; trajectory Jacobians chain the model derivatives
with the spline's control-point Jacobians (right perturbations for ``traj.so3``, linear weights for
``traj.r3``) and gravity uses the s2 retraction Jacobian of the solver. A gyroscope and an
accelerometer block built with the same :class:`~licalib_cli.spline.SO3EvaluationCache` (as
:func:`licalib_cli.estimation.build_problem` does) evaluate the rotation spline once per state.

The splines' time axis is the IMU's clock. An IMU clock that runs at another rate than the
LiDAR's (``ext.time_drift`` ``k``: IMU time ``tau + t_c + k (tau - t_ref)`` of a LiDAR time
``tau``) does not change what the IMU measures, rates per second of the world: the splines'
derivatives on the IMU clock are ``1 + k`` times too slow, so the angular velocity is scaled by
``1 + k`` and the acceleration by ``(1 + k)^2`` before the sensor model (without it a 250 ppm
drift left a gyro scale of that size for ``diagnose`` to name).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from licalib_cli.models.imu import accel_model, bias_drift_basis, gyro_model, specific_force
from licalib_cli.residuals import (
    ACCEL_BIAS,
    ACCEL_BIAS_DRIFT,
    ACCEL_MISALIGNMENT,
    ACCEL_SCALE,
    GRAVITY,
    GYRO_BIAS,
    GYRO_BIAS_DRIFT,
    GYRO_G_SENSITIVITY,
    GYRO_MISALIGNMENT,
    GYRO_ROTATION,
    GYRO_SCALE,
    TIME_DRIFT,
    TRAJ_R3,
    TRAJ_SO3,
)
from licalib_cli.solver.parameters import s2_retraction_jacobian
from licalib_cli.solver.problem import DenseJacobian, ResidualEval
from licalib_cli.spline import R3Spline, SO3EvaluationCache, UniformKnots

__all__ = ["AccelResidual", "GyroResidual"]

F64 = npt.NDArray[np.float64]

_OFFSETS = np.arange(4, dtype=np.intp)
_IDENTITY_QUAT = np.array([0.0, 0.0, 0.0, 1.0])


def _per_axis_inverse(sigma: float | npt.ArrayLike, what: str) -> F64:
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (3,)).copy()
    if not np.all(np.isfinite(s) & (s > 0.0)):
        msg = f"{what} noise sigma must be positive and finite, got {sigma!r}"
        raise ValueError(msg)
    return 1.0 / s


def _check_samples(t_s: npt.ArrayLike, values: npt.ArrayLike, what: str) -> tuple[F64, F64]:
    t = np.ascontiguousarray(t_s, dtype=np.float64).reshape(-1)
    v = np.ascontiguousarray(values, dtype=np.float64)
    if v.shape != (t.shape[0], 3):
        msg = f"{what} readings must have shape ({t.shape[0]}, 3), got {v.shape}"
        raise ValueError(msg)
    return t, v


def _get(params: Mapping[str, F64], name: str, default: F64) -> F64:
    value = params.get(name)
    return default if value is None else np.asarray(value, dtype=np.float64)


def _clock_rate(params: Mapping[str, F64]) -> float | None:
    """``1 + k`` of an IMU clock drift ``k`` in ``params`` (None without the block)."""
    if TIME_DRIFT not in params:
        return None
    return 1.0 + float(np.asarray(params[TIME_DRIFT], dtype=np.float64).reshape(-1)[0])


class GyroResidual:
    """Gyro residuals ``(S_w M_w R_wI w_I(t) [+ A_w a_I(t)] + b_w - w_m) / sigma_w``.

    Touches ``traj.so3`` (4 control points per sample), ``imu.gyro_bias``, ``imu.gyro_scale``,
    ``imu.gyro_misalignment``, ``imu.gyro_rotation`` and, with g-sensitivity, ``traj.r3``,
    ``gravity`` and ``imu.gyro_g_sensitivity``.
    """

    def __init__(
        self,
        knots: UniformKnots,
        t_s: npt.ArrayLike,
        gyro: npt.ArrayLike,
        sigma: float | npt.ArrayLike,
        *,
        g_sensitivity: bool = False,
        t_ref_s: float = 0.0,
        name: str = "imu.gyro",
        so3_cache: SO3EvaluationCache | None = None,
    ) -> None:
        """Create the block.

        Args:
            knots: knot vector of the trajectory splines.
            t_s: (N,) sample times, IMU-clock seconds relative to the reference time.
            gyro: (N, 3) gyro readings, rad/s.
            sigma: discrete noise standard deviation, rad/s (scalar or (3,) per axis).
            g_sensitivity: include the ``A_w a_I`` term.
            t_ref_s: reference time of the bias drift: ``b_w(t) = b_w + d_w (t - t_ref)``, or
                piecewise linear over ``[0, 2 t_ref]`` with a ``(K, 3)`` drift block
                (:func:`~licalib_cli.models.imu.bias_drift_basis`).
            name: residual block name.
            so3_cache: rotation-spline evaluation shared with an :class:`AccelResidual` at the
                same sample times (see :class:`~licalib_cli.spline.SO3EvaluationCache`);
                default: a private one.

        Raises:
            ValueError: on shape mismatches, a bad sigma or times outside the spline range.
        """
        self.name = name
        self.knots = knots
        self.t_s, self.gyro = _check_samples(t_s, gyro, "gyro")
        knots.locate(self.t_s)  # range check
        self.inv_sigma = _per_axis_inverse(sigma, "gyro")
        self.g_sensitivity = g_sensitivity
        self.drift = _Drift(self.t_s, float(t_ref_s))
        self.so3_cache = SO3EvaluationCache() if so3_cache is None else so3_cache
        self._zeros = np.zeros((self.t_s.shape[0], 1), dtype=np.intp)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def evaluate(self, params: Mapping[str, F64], jacobians: bool = True) -> ResidualEval:
        """Whitened residuals (N, 3) and their Jacobians (see :class:`GyroResidual`)."""
        n = self.t_s.shape[0]
        ev = self.so3_cache.evaluate(self.knots, params[TRAJ_SO3], self.t_s, 1, jacobians)
        assert ev.angular_velocity is not None
        rate = _clock_rate(params)
        omega = ev.angular_velocity if rate is None else rate * ev.angular_velocity
        use_gs = self.g_sensitivity and GYRO_G_SENSITIVITY in params
        sf = None
        pos = None
        if use_gs:
            pos = R3Spline(self.knots, params[TRAJ_R3]).evaluate(self.t_s, order=2)
            assert pos.acceleration is not None
            acc = pos.acceleration if rate is None else rate**2 * pos.acceleration
            sf = specific_force(ev.rotation, acc, params[GRAVITY])
        model = gyro_model(
            omega,
            None if sf is None else sf.value,
            _get(params, GYRO_SCALE, np.ones(3)),
            _get(params, GYRO_MISALIGNMENT, np.zeros(3)),
            _get(params, GYRO_ROTATION, _IDENTITY_QUAT),
            _get(params, GYRO_BIAS, np.zeros(3)),
            params[GYRO_G_SENSITIVITY] if use_gs else None,
            jacobians=jacobians,
        )
        w = self.inv_sigma
        value = model.value
        if GYRO_BIAS_DRIFT in params:
            value = value + self.drift.value(params[GYRO_BIAS_DRIFT])
        r = (value - self.gyro) * w
        if not jacobians:
            return ResidualEval(r)
        assert ev.jac_angular_velocity is not None and ev.jac_rotation is not None
        dw = w[:, None] * model.d_omega  # (3, 3) whitened
        j_so3 = _left_multiply(dw if rate is None else rate * dw, ev.jac_angular_velocity)
        elements = ev.index[:, None] + _OFFSETS
        jacs: list[DenseJacobian] = [DenseJacobian(TRAJ_SO3, elements, j_so3)]
        j_rate = None if rate is None else ev.angular_velocity @ dw.T  # d r / d k, (n, 3)
        if use_gs:
            assert sf is not None and pos is not None and pos.acceleration_weights is not None
            assert pos.acceleration is not None
            da = w[:, None] * model.d_accel  # A_w, whitened
            j_so3 += _left_multiply(_matmul_const(da, sf.d_rotation), ev.jac_rotation)
            a_rt = _matmul_const(da, sf.d_acceleration)  # (n, 3, 3)
            if rate is not None and j_rate is not None:
                j_rate = j_rate + 2.0 * rate * np.einsum("nij,nj->ni", a_rt, pos.acceleration)
            if TRAJ_R3 in params:
                scaled = a_rt if rate is None else rate**2 * a_rt
                j_r3 = _times_weights(scaled, pos.acceleration_weights)
                jacs.append(DenseJacobian(TRAJ_R3, elements, j_r3))
            if GRAVITY in params:
                j_g = -_times_const(a_rt, s2_retraction_jacobian(params[GRAVITY]))[:, :, None]
                jacs.append(DenseJacobian(GRAVITY, self._zeros, j_g))
            assert model.d_g_sensitivity is not None
            jacs.append(
                DenseJacobian(
                    GYRO_G_SENSITIVITY,
                    self._zeros,
                    (model.d_g_sensitivity * w[None, :, None])[:, :, None, :],
                )
            )
        if j_rate is not None:
            jacs.append(DenseJacobian(TIME_DRIFT, self._zeros, j_rate[:, :, None, None]))
        if GYRO_BIAS in params:
            jacs.append(DenseJacobian(GYRO_BIAS, self._zeros, _bias_jacobian(n, w)))
        if GYRO_BIAS_DRIFT in params:
            jacs.append(self.drift.jacobian(GYRO_BIAS_DRIFT, params[GYRO_BIAS_DRIFT], w))
        for block, d in (
            (GYRO_SCALE, model.d_scale),
            (GYRO_MISALIGNMENT, model.d_misalignment),
            (GYRO_ROTATION, model.d_rotation),
        ):
            if block in params:
                assert d is not None
                jacs.append(
                    DenseJacobian(block, self._zeros, (d * w[None, :, None])[:, :, None, :])
                )
        return ResidualEval(r, tuple(jacs))


class AccelResidual:
    """Accelerometer residuals ``(S_a M_a R(t)^T (p_ddot(t) - g) + b_a - a_m) / sigma_a``.

    Touches ``traj.so3`` and ``traj.r3`` (4 control points each per sample), ``gravity``,
    ``imu.accel_bias``, ``imu.accel_scale`` and ``imu.accel_misalignment``.
    """

    def __init__(
        self,
        knots: UniformKnots,
        t_s: npt.ArrayLike,
        accel: npt.ArrayLike,
        sigma: float | npt.ArrayLike,
        *,
        t_ref_s: float = 0.0,
        name: str = "imu.accel",
        so3_cache: SO3EvaluationCache | None = None,
    ) -> None:
        """Create the block.

        Args:
            knots: knot vector of the trajectory splines.
            t_s: (N,) sample times, IMU-clock seconds relative to the reference time.
            accel: (N, 3) accelerometer readings, m/s^2.
            sigma: discrete noise standard deviation, m/s^2 (scalar or (3,) per axis).
            t_ref_s: reference time of the bias drift ``b_a(t) = b_a + d_a (t - t_ref)`` (or
                piecewise linear, as for :class:`GyroResidual`).
            name: residual block name.
            so3_cache: rotation-spline evaluation shared with a :class:`GyroResidual` at the
                same sample times; default: a private one.

        Raises:
            ValueError: on shape mismatches, a bad sigma or times outside the spline range.
        """
        self.name = name
        self.knots = knots
        self.t_s, self.accel = _check_samples(t_s, accel, "accelerometer")
        knots.locate(self.t_s)
        self.inv_sigma = _per_axis_inverse(sigma, "accelerometer")
        self.drift = _Drift(self.t_s, float(t_ref_s))
        self.so3_cache = SO3EvaluationCache() if so3_cache is None else so3_cache
        self._zeros = np.zeros((self.t_s.shape[0], 1), dtype=np.intp)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def evaluate(self, params: Mapping[str, F64], jacobians: bool = True) -> ResidualEval:
        """Whitened residuals (N, 3) and their Jacobians (see :class:`AccelResidual`)."""
        n = self.t_s.shape[0]
        ev = self.so3_cache.evaluate(self.knots, params[TRAJ_SO3], self.t_s, 0, jacobians)
        pos = R3Spline(self.knots, params[TRAJ_R3]).evaluate(self.t_s, order=2)
        assert pos.acceleration is not None
        rate = _clock_rate(params)
        acc = pos.acceleration if rate is None else rate**2 * pos.acceleration
        sf = specific_force(ev.rotation, acc, params[GRAVITY])
        model = accel_model(
            sf.value,
            _get(params, ACCEL_SCALE, np.ones(3)),
            _get(params, ACCEL_MISALIGNMENT, np.zeros(3)),
            _get(params, ACCEL_BIAS, np.zeros(3)),
            jacobians=jacobians,
        )
        w = self.inv_sigma
        value = model.value
        if ACCEL_BIAS_DRIFT in params:
            value = value + self.drift.value(params[ACCEL_BIAS_DRIFT])
        r = (value - self.accel) * w
        if not jacobians:
            return ResidualEval(r)
        assert ev.jac_rotation is not None and pos.acceleration_weights is not None
        k = w[:, None] * model.d_accel  # whitened S_a M_a
        elements = ev.index[:, None] + _OFFSETS
        j_so3 = _left_multiply(_matmul_const(k, sf.d_rotation), ev.jac_rotation)
        k_rt = _matmul_const(k, sf.d_acceleration)  # (n, 3, 3)
        j_r3 = _times_weights(k_rt if rate is None else rate**2 * k_rt, pos.acceleration_weights)
        jacs: list[DenseJacobian] = [
            DenseJacobian(TRAJ_SO3, elements, j_so3),
            DenseJacobian(TRAJ_R3, elements, j_r3),
        ]
        if rate is not None:
            j_rate = 2.0 * rate * np.einsum("nij,nj->ni", k_rt, pos.acceleration)
            jacs.append(DenseJacobian(TIME_DRIFT, self._zeros, j_rate[:, :, None, None]))
        if GRAVITY in params:
            j_g = -_times_const(k_rt, s2_retraction_jacobian(params[GRAVITY]))[:, :, None]
            jacs.append(DenseJacobian(GRAVITY, self._zeros, j_g))
        if ACCEL_BIAS in params:
            jacs.append(DenseJacobian(ACCEL_BIAS, self._zeros, _bias_jacobian(n, w)))
        if ACCEL_BIAS_DRIFT in params:
            jacs.append(self.drift.jacobian(ACCEL_BIAS_DRIFT, params[ACCEL_BIAS_DRIFT], w))
        for block, d in ((ACCEL_SCALE, model.d_scale), (ACCEL_MISALIGNMENT, model.d_misalignment)):
            if block in params:
                assert d is not None
                jacs.append(
                    DenseJacobian(block, self._zeros, (d * w[None, :, None])[:, :, None, :])
                )
        return ResidualEval(r, tuple(jacs))


class _Drift:
    """A bias walk's term at the samples: ``B(t) d`` for a ``(3,)`` or ``(K, 3)`` drift block
    (:func:`~licalib_cli.models.imu.bias_drift_basis`), its basis kept per piece count."""

    def __init__(self, t_s: F64, t_ref_s: float) -> None:
        self.t_s = t_s
        self.t_ref_s = t_ref_s
        self._basis: dict[int, tuple[F64, npt.NDArray[np.intp]]] = {}

    def basis(self, pieces: int) -> F64:
        """(N, K) basis for ``pieces`` pieces."""
        return self._cached(pieces)[0]

    def _cached(self, pieces: int) -> tuple[F64, npt.NDArray[np.intp]]:
        out = self._basis.get(pieces)
        if out is None:
            basis = bias_drift_basis(self.t_s, self.t_ref_s, pieces)
            elements = np.tile(np.arange(pieces, dtype=np.intp), (basis.shape[0], 1))
            out = self._basis[pieces] = (basis, elements)
        return out

    def value(self, drift: F64) -> F64:
        """(N, 3) the bias's change from its value at ``t_ref``."""
        d = np.asarray(drift, dtype=np.float64).reshape(-1, 3)
        return self.basis(d.shape[0]) @ d

    def jacobian(self, block: str, drift: F64, w: F64) -> DenseJacobian:
        """Whitened Jacobian of :meth:`value` (one element of 3 per piece)."""
        basis, elements = self._cached(np.asarray(drift).size // 3)
        j = np.diag(w)[None, :, None, :] * basis[:, None, :, None]  # (n, 3, K, 3)
        return DenseJacobian(block, elements, j)


def _bias_jacobian(n: int, w: F64) -> F64:
    """(n, 3, 1, 3) whitened identity."""
    return np.broadcast_to(np.diag(w)[None, :, None, :], (n, 3, 1, 3)).copy()


def _left_multiply(m: F64, jac: F64) -> F64:
    """(n, 3, 4, 3) ``out[n, i, k] = m[n] @ jac[n, k]`` for (3, 3) or (n, 3, 3) ``m``.

    ``jac`` is a spline Jacobian, an (n, 4, 3, 3) view of component-major (4, 3, 3, n) storage;
    the products run on that storage and the result is written query-major once.
    """
    jc = np.moveaxis(jac, 0, -1)  # (4, 3, 3, n)
    if m.ndim == 2:
        out = np.tensordot(m, jc, axes=([1], [1]))  # (3, 4, 3, n)
    else:
        out = np.einsum("ijn,kjln->ikln", np.ascontiguousarray(np.moveaxis(m, 0, -1)), jc)
    return np.ascontiguousarray(np.moveaxis(out, -1, 0))


def _times_weights(m: F64, weights: F64) -> F64:
    """(n, 3, 4, 3) ``out[n, :, k, :] = weights[n, k] m[n]`` (linear spline Jacobians)."""
    out = np.empty((m.shape[0], 3, 4, 3))
    np.multiply(m[:, :, None, :], np.ascontiguousarray(weights)[:, None, :, None], out=out)
    return out


def _matmul_const(k: F64, m: F64) -> F64:
    """(n, 3, 3) ``k @ m[n]`` for a constant (3, 3) ``k``, as one BLAS product."""
    # k m_n = (m_n^T k^T)^T: stack the m_n^T as rows
    n = m.shape[0]
    prod = np.swapaxes(m, 1, 2).reshape(n * 3, 3) @ k.T
    return np.ascontiguousarray(np.swapaxes(prod.reshape(n, 3, 3), 1, 2))


def _times_const(m: F64, b: F64) -> F64:
    """(n, 3, q) ``m[n] @ b`` for a constant (3, q) ``b``, as one BLAS product."""
    return (m.reshape(-1, 3) @ b).reshape(m.shape[0], 3, b.shape[1])
