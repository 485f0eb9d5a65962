"""Row-wise vector helpers for large point arrays (pure numpy)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["cross_rows", "elevations", "norms"]


def norms(v: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Euclidean norm of every row of an (N, D) array.

    ``np.linalg.norm(v, axis=1)`` reduces along the short axis of a row-major array; the
    row-wise dot product is two to three times faster on a LiDAR scan's points.

    Args:
        v: (N, D) rows.

    Returns:
        (N,) float64 norms.
    """
    a = np.asarray(v, dtype=np.float64)
    return np.sqrt(np.einsum("ij,ij->i", a, a))


def elevations(xyz: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(N,) elevation of every point of an (N, 3) array seen from the origin, rad (0 for the
    origin itself)."""
    return np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))


def cross_rows(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Row-wise ``a x b`` of (N, 3) arrays (several times faster than ``np.cross``)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.multiply(a[:, 1], b[:, 2], out=out[:, 0])
    out[:, 0] -= a[:, 2] * b[:, 1]
    np.multiply(a[:, 2], b[:, 0], out=out[:, 1])
    out[:, 1] -= a[:, 0] * b[:, 2]
    np.multiply(a[:, 0], b[:, 1], out=out[:, 2])
    out[:, 2] -= a[:, 1] * b[:, 0]
    return out
