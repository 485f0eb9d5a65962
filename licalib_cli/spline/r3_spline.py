"""Uniform cubic B-spline in R^3 (the position part of the trajectory, paper eq. p_curve_cumu).

Conventions:

* ``p(t) = G p_I(t)``: position of the IMU origin in the global frame ``{G}``, metres; velocity
  in m/s and acceleration in m/s^2, all in ``{G}``. The specific force ``a_I = R^T (p_ddot - g)``
  is formed by the models layer, not here.
* Times are float seconds relative to the problem's reference time, see
  :class:`~licalib_cli.spline.knots.UniformKnots`.
* The map from control points to values is linear: with active control points ``c_i .. c_{i+3}``
  and weights ``w_j``, ``p(t) = sum_j w_j(t) c_{i+j}`` and ``d p / d c_{i+j} = w_j(t) I_3``. The
  Jacobians are therefore returned as (M, 4) scalar weights together with the index ``i``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from licalib_cli.parallel.threads import map_slices
from licalib_cli.spline.knots import BASIS_MATRIX, UniformKnots, _weights_by_row, blending

__all__ = ["R3Spline", "R3SplineEval"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_OFFSETS = np.arange(4, dtype=np.int64)


@dataclass(frozen=True)
class R3SplineEval:
    """Values, derivatives and Jacobians of an :class:`R3Spline` at M query times.

    Attributes:
        index: (M,) int64 first active control point ``i``; the weights refer to ``c_i .. c_{i+3}``.
        position: (M, 3) ``p(t)``, metres, frame ``{G}``.
        velocity: (M, 3) ``p_dot(t)``, m/s, or None when not requested.
        acceleration: (M, 3) ``p_ddot(t)``, m/s^2, or None.
        jerk: (M, 3) third derivative, m/s^3 (piecewise constant), or None.
        weights: (M, 4) ``d p / d c_{i+j}`` (times ``I_3``); the weight arrays are views of
            (4, M) storage.
        velocity_weights: (M, 4) ``d p_dot / d c_{i+j}``, 1/s, or None.
        acceleration_weights: (M, 4) ``d p_ddot / d c_{i+j}``, 1/s^2, or None.

    Jacobians with respect to the query time are ``velocity`` (for position), ``acceleration``
    (for velocity) and ``jerk`` (for acceleration).
    """

    index: IntArray
    position: FloatArray
    velocity: FloatArray | None
    acceleration: FloatArray | None
    jerk: FloatArray | None
    weights: FloatArray
    velocity_weights: FloatArray | None
    acceleration_weights: FloatArray | None


@dataclass(frozen=True)
class R3Spline:
    """Uniform cubic B-spline with R^3 control points.

    Attributes:
        knots: knot vector (time range and spacing).
        control_points: (N, 3) float64 control points, metres, frame ``{G}``.
    """

    knots: UniformKnots
    control_points: FloatArray
    _cp_soa: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        cp = np.asarray(self.control_points, dtype=np.float64)
        if cp.shape != (self.knots.num_control_points, 3):
            msg = (
                f"control_points must have shape ({self.knots.num_control_points}, 3), "
                f"got {cp.shape}"
            )
            raise ValueError(msg)
        cp = cp.copy()
        cp.setflags(write=False)
        object.__setattr__(self, "control_points", cp)
        object.__setattr__(self, "_cp_soa", np.ascontiguousarray(cp.T))

    def with_control_points(self, control_points: npt.ArrayLike) -> R3Spline:
        """Same knots, new (N, 3) control points."""
        return R3Spline(self.knots, np.asarray(control_points, dtype=np.float64))

    def evaluate(self, t_s: npt.ArrayLike, order: int = 2) -> R3SplineEval:
        """Evaluate the spline and its derivatives up to ``order`` at M times.

        Args:
            t_s: (M,) query times, seconds.
            order: highest time derivative returned: 0 position, 1 + velocity,
                2 + acceleration, 3 + jerk.

        Returns:
            :class:`R3SplineEval` (fields above ``order`` are None).

        Raises:
            ValueError: if a time is outside the spline range.
        """
        index, u = self.knots.locate(t_s)
        m = index.shape[0]
        inv_dt = 1.0 / self.knots.dt_s
        orders = range(min(order, 3) + 1)
        outs: list[FloatArray | None] = [np.empty((m, 3)) if k <= order else None for k in range(4)]
        # weights of derivative k: (M, 4) views of (4, M) storage
        wbuf = [np.empty((4, m)) for _ in orders]

        def block(sl: slice) -> None:
            """Weights and values of the queries ``sl`` into their columns/rows of the outputs."""
            idx = index[sl]
            # component-major gathers (3, m) of the 4 active control points
            cps = [np.take(self._cp_soa, idx + j, axis=1) for j in range(4)]
            for k in orders:
                w = _weights_by_row(u[sl], k, BASIS_MATRIX, out=wbuf[k][:, sl])
                if k:
                    w *= inv_dt**k
                value = w[0] * cps[0]
                for j in range(1, 4):
                    value += w[j] * cps[j]
                out = outs[k]
                assert out is not None
                out[sl] = value.T

        # blocks write disjoint slices; see licalib_cli.parallel.threads
        map_slices(block, m)
        ws: list[FloatArray | None] = [wbuf[k].T if k < len(wbuf) else None for k in range(4)]
        assert outs[0] is not None and ws[0] is not None
        return R3SplineEval(
            index=index,
            position=outs[0],
            velocity=outs[1],
            acceleration=outs[2],
            jerk=outs[3],
            weights=ws[0],
            velocity_weights=ws[1],
            acceleration_weights=ws[2],
        )

    def position(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M, 3) positions, metres, ``{G}``."""
        return self.evaluate(t_s, order=0).position

    def velocity(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M, 3) velocities, m/s, ``{G}``."""
        v = self.evaluate(t_s, order=1).velocity
        assert v is not None
        return v

    def acceleration(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M, 3) accelerations, m/s^2, ``{G}`` (gravity not removed)."""
        a = self.evaluate(t_s, order=2).acceleration
        assert a is not None
        return a

    def design_matrix(self, t_s: npt.ArrayLike, derivative: int = 0) -> sp.csr_matrix:
        """Sparse (M, N) matrix ``B`` with ``d^k p / dt^k (t_m) = sum_n B[m, n] c_n``.

        Args:
            t_s: (M,) query times, seconds.
            derivative: time derivative order ``k``.

        Returns:
            CSR matrix, 4 non-zeros per row (units 1/s^k).
        """
        return _design_matrix(self.knots, t_s, derivative)

    @classmethod
    def fit(
        cls,
        knots: UniformKnots,
        t_s: npt.ArrayLike,
        values: npt.ArrayLike,
        weights: npt.ArrayLike | None = None,
        smoothing: float = 0.0,
    ) -> R3Spline:
        """Weighted linear least-squares fit of the control points to sampled positions.

        Minimises ``sum_m weights_m |p(t_m) - values_m|^2 + smoothing * sum_k
        |c_{k-1} - 2 c_k + c_{k+1}|^2 / dt^3`` (the penalty approximates
        ``smoothing * integral |p_ddot|^2 dt``). A negligible curvature term
        (1e-10 of the data scale) is always added so that control points without data are
        continued smoothly instead of making the system singular.

        Args:
            knots: knot vector; every ``t_s`` must lie in its range.
            t_s: (M,) sample times, seconds.
            values: (M, 3) sampled positions, metres.
            weights: (M,) non-negative sample weights (e.g. inverse variances), default ones.
            smoothing: curvature penalty weight (>= 0), units of weights * s^4.

        Returns:
            The fitted spline.

        Raises:
            ValueError: on shape mismatches, times outside the knot range, negative weights or
                fewer than two distinct sample times.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        y = np.asarray(values, dtype=np.float64)
        if y.shape != (t.shape[0], 3):
            msg = f"values must have shape ({t.shape[0]}, 3), got {y.shape}"
            raise ValueError(msg)
        w = np.ones_like(t) if weights is None else np.asarray(weights, dtype=np.float64)
        if w.shape != t.shape or np.any(w < 0) or not np.all(np.isfinite(w)):
            msg = "weights must be finite, non-negative and one per sample"
            raise ValueError(msg)
        if smoothing < 0:
            msg = f"smoothing must be non-negative, got {smoothing}"
            raise ValueError(msg)
        if np.unique(t[w > 0]).size < 2:
            msg = "fitting a spline needs samples at two or more distinct times"
            raise ValueError(msg)
        B = _design_matrix(knots, t, 0)
        normal = (B.T @ sp.diags(w) @ B).tocsc()
        rhs = B.T @ (w[:, None] * y)
        n = knots.num_control_points
        D = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
        scale = float(normal.diagonal().max())
        reg = smoothing / knots.dt_s**3 + 1e-10 * scale
        system = (normal + reg * (D.T @ D)).tocsc()
        cp = spla.spsolve(system, rhs)
        return cls(knots, np.asarray(cp, dtype=np.float64).reshape(n, 3))


def _design_matrix(knots: UniformKnots, t_s: npt.ArrayLike, derivative: int) -> sp.csr_matrix:
    index, u = knots.locate(t_s)
    w = blending(u, derivative) / knots.dt_s**derivative
    m = index.shape[0]
    rows = np.repeat(np.arange(m), 4)
    cols = (index[:, None] + _OFFSETS).ravel()
    return sp.csr_matrix((w.ravel(), (rows, cols)), shape=(m, knots.num_control_points))
