"""Central finite differences and the entry-wise check of analytic Jacobians against them.

Every analytic derivative in ``tests/core`` is checked entry by entry::

    |analytic - numeric| <= RTOL * max(|numeric|, floor),   RTOL = 1e-6

with ``floor = SAFETY * EPS * value_scale / (h * RTOL)``.

Why a floor: a central difference with step ``h`` of values of magnitude ``value_scale`` carries a
round-off error of about ``EPS * value_scale / h`` (``EPS`` = 2.2e-16; both values are rounded,
and so is every operation of the function on the way to them, hence the factor ``SAFETY`` = 20),
next to a truncation error ``h^2 |f'''| / 6`` (about 1e-13 relative at ``h = 1e-6``:
negligible). A derivative entry much smaller than ``value_scale`` cannot be resolved to a relative
``RTOL`` by the difference itself, so entries below the floor are held to the absolute error
``RTOL * floor = SAFETY * EPS * value_scale / h`` instead (4.4e-9 ``value_scale`` at
``h = 1e-6``; the floor itself is 4.4e-3 ``value_scale``). ``value_scale`` is the magnitude of the
differentiated values *and of the terms they are computed from* (a whitened residual is the
difference of a prediction and a reading divided by sigma: its rounding follows those terms, not
the small difference).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

EPS = float(np.finfo(np.float64).eps)
STEP = 1e-6
RTOL = 1e-6
SAFETY = 20.0


def floor_for(value_scale: float, h: float = STEP, rtol: float = RTOL) -> float:
    """Smallest derivative magnitude checked relatively (see the module docstring)."""
    return SAFETY * EPS * float(value_scale) / (h * rtol)


def central_difference(
    f: Callable[[np.ndarray], np.ndarray], x: npt.ArrayLike, h: float = STEP
) -> np.ndarray:
    """Central differences of ``f`` with respect to every coordinate of ``x``.

    Args:
        f: Function of an array shaped like ``x`` returning an array of shape S.
        x: Point of evaluation.
        h: Step.

    Returns:
        (*S, x.size) derivatives (coordinate ``j`` of the flattened ``x`` last).
    """
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for j in range(x.size):
        d = np.zeros(x.size)
        d[j] = h
        d = d.reshape(x.shape)
        cols.append((np.asarray(f(x + d)) - np.asarray(f(x - d))) / (2.0 * h))
    return np.stack(cols, axis=-1)


def assert_jacobian(
    analytic: npt.ArrayLike,
    numeric: npt.ArrayLike,
    value_scale: float,
    *,
    h: float = STEP,
    rtol: float = RTOL,
    what: str = "",
) -> None:
    """Assert that every entry of ``analytic`` matches its central difference ``numeric``.

    Args:
        analytic: Analytic derivatives.
        numeric: Central differences of the same shape (step ``h``).
        value_scale: Magnitude of the differentiated values and the terms they come from.
        h: Step of the differences.
        rtol: Relative tolerance per entry.
        what: Label for the failure message.

    Raises:
        AssertionError: With the worst entry when any entry is off.
    """
    a = np.asarray(analytic, dtype=np.float64)
    b = np.asarray(numeric, dtype=np.float64)
    assert a.shape == b.shape, f"{what}: shapes {a.shape} and {b.shape}"
    floor = floor_for(value_scale, h, rtol)
    err = np.abs(a - b)
    tol = rtol * np.maximum(np.abs(b), floor)
    bad = ~(err <= tol)  # NaN fails
    if np.any(bad):
        ratio = np.where(bad, np.nan_to_num(err / tol, nan=np.inf), -1.0)
        worst = np.unravel_index(int(np.argmax(ratio)), a.shape)
        msg = (
            f"{what}: {int(bad.sum())} of {a.size} entries differ; worst at {worst}: analytic "
            f"{a[worst]:.12g}, numeric {b[worst]:.12g}, |diff| {err[worst]:.3g} > "
            f"{tol[worst]:.3g} (rtol {rtol:g}, floor {floor:.3g})"
        )
        raise AssertionError(msg)
