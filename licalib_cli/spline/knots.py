"""Uniform knot vectors and the cubic B-spline blending functions in cumulative form.

Conventions:

* Times are float seconds relative to the problem's reference time (callers convert int64 ns).
* A spline with ``N`` control points ``c_0 .. c_{N-1}`` and spacing ``dt`` is defined on
  ``[t0, t0 + (N - 3) dt]``. A time ``t`` falls in segment ``i = floor((t - t0) / dt)`` with
  normalised time ``u = (t - t0) / dt - i`` in ``[0, 1)``; the active control points are
  ``c_i .. c_{i+3}``. The end time itself is evaluated in the last segment with ``u = 1``.
* Control point ``c_k`` is centred at time ``t0 + (k - 1) dt`` (where its basis function peaks).
* Cubic uniform B-spline, matrix form (paper Sec. III-A): the non-cumulative weights are
  ``w_j(u) = [1, u, u^2, u^3] @ M[:, j]`` and the cumulative ones
  ``lambda_j(u) = sum_{l >= j} w_l(u) = [1, u, u^2, u^3] @ M_cum[:, j]``, so ``lambda_0 = 1`` and
  ``x(t) = c_i + sum_{j=1}^{3} lambda_j(u) (c_{i+j} - c_{i+j-1})``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "BASIS_MATRIX",
    "CUMULATIVE_BASIS_MATRIX",
    "UniformKnots",
    "blending",
    "cumulative_blending",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Cubic uniform B-spline basis matrix M^(4); rows: powers of u (1, u, u^2, u^3); columns: j.
BASIS_MATRIX: FloatArray = (
    np.array(
        [
            [1.0, 4.0, 1.0, 0.0],
            [-3.0, 0.0, 3.0, 0.0],
            [3.0, -6.0, 3.0, 0.0],
            [-1.0, 3.0, -3.0, 1.0],
        ]
    )
    / 6.0
)
BASIS_MATRIX.setflags(write=False)

#: Cumulative basis matrix M~^(4) of the paper (eq. p_curve_cumu); column j = sum of columns >= j
#: of :data:`BASIS_MATRIX`.
CUMULATIVE_BASIS_MATRIX: FloatArray = (
    np.array(
        [
            [6.0, 5.0, 1.0, 0.0],
            [0.0, 3.0, 3.0, 0.0],
            [0.0, -3.0, 3.0, 0.0],
            [0.0, 1.0, -2.0, 1.0],
        ]
    )
    / 6.0
)
CUMULATIVE_BASIS_MATRIX.setflags(write=False)

# Slack, in units of dt, with which a query may fall outside [t0, t_end] because of round-off.
_EDGE_TOLERANCE = 1e-9


def _weights_by_row(
    u: FloatArray, derivative: int, matrix: FloatArray, out: FloatArray | None = None
) -> FloatArray:
    """Rows ``j`` of ``d^k/du^k [1, u, u^2, u^3] @ matrix`` as a contiguous (4, M) array.

    Written as broadcasting products (not a BLAS matmul, whose per-call threading overhead
    dominates for a (M, 4) @ (4, 4) product). ``out``, a (4, M) array (e.g. the columns of one
    evaluation block in a larger buffer), receives the weights instead of a new array.
    """
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    if out is None:
        out = np.empty((4, u.shape[0]))
    if derivative == 0:
        powers = [None, u, u * u, u * u * u]
        coef = [1.0, 1.0, 1.0, 1.0]
    elif derivative == 1:
        powers = [None, None, u, u * u]
        coef = [0.0, 1.0, 2.0, 3.0]
    elif derivative == 2:
        powers = [None, None, None, u]
        coef = [0.0, 0.0, 2.0, 6.0]
    elif derivative == 3:
        powers = [None, None, None, None]
        coef = [0.0, 0.0, 0.0, 6.0]
    else:
        out[...] = 0.0
        return out
    # the constant term of the derivative is the coefficient of u^derivative
    out[...] = (coef[derivative] * matrix[derivative])[:, None]
    for p in range(derivative + 1, 4):
        out += (coef[p] * matrix[p])[:, None] * powers[p]
    return out


def blending(u: npt.ArrayLike, derivative: int = 0) -> FloatArray:
    """Non-cumulative cubic blending weights ``w_j(u)`` or their u-derivatives.

    Args:
        u: (M,) normalised times in [0, 1].
        derivative: order of the derivative with respect to ``u`` (0 = values).

    Returns:
        (M, 4) weights of control points ``c_i .. c_{i+3}`` (divide by ``dt^k`` for time
        derivatives). The array is a transposed view of (4, M) storage.
    """
    return _weights_by_row(np.asarray(u, dtype=np.float64), derivative, BASIS_MATRIX).T


def cumulative_blending(u: npt.ArrayLike, derivative: int = 0) -> FloatArray:
    """Cumulative cubic blending functions ``lambda_j(u)`` or their u-derivatives.

    Args:
        u: (M,) normalised times in [0, 1].
        derivative: order of the derivative with respect to ``u`` (0 = values).

    Returns:
        (M, 4) ``lambda_0 .. lambda_3`` (``lambda_0 = 1`` for the values, 0 for derivatives).
        The array is a transposed view of (4, M) storage.
    """
    return _weights_by_row(np.asarray(u, dtype=np.float64), derivative, CUMULATIVE_BASIS_MATRIX).T


@dataclass(frozen=True)
class UniformKnots:
    """Uniform knot vector of a cubic B-spline.

    Attributes:
        t0_s: start of the valid time range, seconds (relative to the problem's reference).
        dt_s: knot spacing, seconds (> 0).
        num_control_points: number of control points ``N`` (>= 4).
    """

    t0_s: float
    dt_s: float
    num_control_points: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.t0_s) and math.isfinite(self.dt_s) and self.dt_s > 0.0):
            msg = f"knot spacing must be positive and finite, got t0={self.t0_s}, dt={self.dt_s}"
            raise ValueError(msg)
        if int(self.num_control_points) != self.num_control_points or self.num_control_points < 4:
            msg = f"a cubic spline needs at least 4 control points, got {self.num_control_points}"
            raise ValueError(msg)

    @classmethod
    def for_interval(
        cls, start_s: float, end_s: float, dt_s: float, padding_s: float = 0.0
    ) -> UniformKnots:
        """Smallest knot vector with spacing ``dt_s`` covering ``[start - pad, end + pad]``.

        Args:
            start_s: first time that must be evaluable, seconds.
            end_s: last time that must be evaluable, seconds (>= start_s).
            dt_s: knot spacing, seconds.
            padding_s: extra margin on both sides, seconds (>= 0), e.g. for time-offset search.

        Returns:
            Knots with ``t0 = start - pad`` and ``t_end >= end + pad``.

        Raises:
            ValueError: on a reversed interval, negative padding or non-positive spacing.
        """
        if not (end_s >= start_s and padding_s >= 0.0 and dt_s > 0.0):
            msg = (
                f"invalid spline interval [{start_s}, {end_s}] with dt={dt_s}, padding={padding_s}"
            )
            raise ValueError(msg)
        t0 = start_s - padding_s
        span = (end_s + padding_s) - t0
        segments = max(1, math.ceil(span / dt_s - _EDGE_TOLERANCE))
        return cls(float(t0), float(dt_s), segments + 3)

    @property
    def num_segments(self) -> int:
        """Number of polynomial segments, ``N - 3``."""
        return self.num_control_points - 3

    @property
    def t_end_s(self) -> float:
        """End of the valid time range, ``t0 + (N - 3) dt``, seconds."""
        return self.t0_s + self.num_segments * self.dt_s

    def control_point_times_s(self) -> FloatArray:
        """(N,) times at which each control point's basis function peaks, ``t0 + (k - 1) dt``."""
        return self.t0_s + (np.arange(self.num_control_points, dtype=np.float64) - 1.0) * self.dt_s

    def clamp(self, t_s: npt.ArrayLike) -> FloatArray:
        """Query times moved into the valid range: a time before ``t0`` (after ``t_end``) is
        evaluated at ``t0`` (``t_end``).

        Args:
            t_s: (M,) times, seconds.

        Returns:
            (M,) float64 times within ``[t0, t_end]``.
        """
        return np.clip(np.asarray(t_s, dtype=np.float64), self.t0_s, self.t_end_s)

    def contains(self, t_s: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Mask of query times inside the valid range (with round-off slack).

        Args:
            t_s: (M,) times, seconds.

        Returns:
            (M,) bool.
        """
        s = (np.asarray(t_s, dtype=np.float64) - self.t0_s) / self.dt_s
        return (s >= -_EDGE_TOLERANCE) & (s <= self.num_segments + _EDGE_TOLERANCE)

    def locate(self, t_s: npt.ArrayLike) -> tuple[IntArray, FloatArray]:
        """Segment index and normalised time of query times.

        Args:
            t_s: (M,) times, seconds (scalars are treated as shape (1,)).

        Returns:
            ``(index, u)``: (M,) int64 first active control point ``i`` in ``[0, N - 4]`` and
            (M,) float64 ``u`` in ``[0, 1]`` (``u = 1`` only at the very end of the range).

        Raises:
            ValueError: if any time is NaN or outside ``[t0, t_end]``.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        s = (t - self.t0_s) / self.dt_s
        n_seg = self.num_segments
        bad = ~((s >= -_EDGE_TOLERANCE) & (s <= n_seg + _EDGE_TOLERANCE))
        if np.any(bad):
            first = t[np.argmax(bad)]
            msg = (
                f"{int(bad.sum())} query time(s) outside the spline range "
                f"[{self.t0_s:.9f}, {self.t_end_s:.9f}] s (first: {first!r}); "
                "extend the spline or drop those samples"
            )
            raise ValueError(msg)
        index = np.clip(np.floor(s), 0, n_seg - 1).astype(np.int64)
        u = np.clip(s - index, 0.0, 1.0)
        return index, u
