"""Robust losses applied per residual group (a scalar point residual, or a 3-vector).

A loss maps the squared norm ``s = |r|^2`` of one whitened residual group to ``rho(s)``; the cost
is ``0.5 * sum rho(s)``. The solver uses iteratively reweighted least squares: each group's
residual and Jacobian rows are multiplied by ``sqrt(rho'(s))`` (the Triggs correction term is
omitted, which keeps the normal equations positive semi-definite and is exact for inliers).
Thresholds are in whitened units (multiples of the measurement standard deviation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

__all__ = ["CauchyLoss", "HuberLoss", "Loss"]

F64 = npt.NDArray[np.float64]


class Loss(Protocol):
    """A robust loss ``rho(s)`` of the squared whitened norm ``s``."""

    def __call__(self, s: F64) -> tuple[F64, F64]:
        """Evaluate the loss.

        Args:
            s: (n,) squared norms of the whitened residual groups, >= 0.

        Returns:
            ``(rho (n,), drho_ds (n,))``.
        """
        ...


@dataclass(frozen=True)
class HuberLoss:
    """Huber loss: ``rho(s) = s`` for ``s <= k^2``, else ``2 k sqrt(s) - k^2``.

    Attributes:
        threshold: ``k``, in whitened units (residual norms above it are downweighted by
            ``k / |r|``).
    """

    threshold: float = 1.0

    def __call__(self, s: F64) -> tuple[F64, F64]:
        """Evaluate ``(rho, rho')`` for (n,) squared norms ``s``."""
        k = float(self.threshold)
        root = np.sqrt(s)
        inlier = s <= k * k
        rho = np.where(inlier, s, 2.0 * k * root - k * k)
        drho = np.where(inlier, 1.0, k / np.where(inlier, 1.0, root))
        return rho, drho


@dataclass(frozen=True)
class CauchyLoss:
    """Cauchy loss: ``rho(s) = k^2 log(1 + s / k^2)``.

    Attributes:
        threshold: ``k``, in whitened units.
    """

    threshold: float = 1.0

    def __call__(self, s: F64) -> tuple[F64, F64]:
        """Evaluate ``(rho, rho')`` for (n,) squared norms ``s``."""
        c = float(self.threshold) ** 2
        return c * np.log1p(s / c), 1.0 / (1.0 + s / c)
