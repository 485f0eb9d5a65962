"""Uniform cubic B-splines in cumulative form for the continuous-time trajectory ``T_G_I(t)``.

Position (:class:`R3Spline`) and rotation (:class:`SO3Spline`) share one
:class:`UniformKnots`. Times are float seconds relative to the problem's reference time.
"""

from __future__ import annotations

from licalib_cli.spline.knots import (
    BASIS_MATRIX,
    CUMULATIVE_BASIS_MATRIX,
    UniformKnots,
    blending,
    cumulative_blending,
)
from licalib_cli.spline.r3_spline import R3Spline, R3SplineEval
from licalib_cli.spline.so3_spline import (
    SO3EvaluationCache,
    SO3RotationVJP,
    SO3Spline,
    SO3SplineEval,
)

__all__ = [
    "BASIS_MATRIX",
    "CUMULATIVE_BASIS_MATRIX",
    "R3Spline",
    "R3SplineEval",
    "SO3EvaluationCache",
    "SO3RotationVJP",
    "SO3Spline",
    "SO3SplineEval",
    "UniformKnots",
    "blending",
    "cumulative_blending",
]
