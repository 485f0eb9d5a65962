"""Tail probabilities of the chi-square, non-central chi-square and F distributions.

The checks need a few of them. :mod:`scipy.stats` gives them too, but importing it costs about
0.7 s on a small machine, more than some checks take; the :mod:`scipy.special` functions below
are what it calls for these distributions.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy import special

__all__ = ["chi2_isf", "chi2_logsf", "chi2_sf", "f_sf", "ncx2_sf"]

F64 = npt.NDArray[np.float64]

_SMALLEST = 1e-300
"""Below this the survival function is taken from its asymptotic series (log scale)."""


def chi2_sf(x: float | F64, dof: float | F64) -> float | F64:
    """``P(X > x)`` for ``X ~ chi2(dof)`` (``scipy.stats.chi2.sf``)."""
    return special.chdtrc(dof, np.maximum(x, 0.0))  # type: ignore[no-any-return]


def chi2_isf(p: float, dof: float) -> float:
    """The ``x`` with ``P(X > x) = p`` for ``X ~ chi2(dof)`` (``scipy.stats.chi2.isf``)."""
    return float(special.chdtri(dof, p))


def chi2_logsf(x: float, dof: float) -> float:
    """``log P(X > x)`` for ``X ~ chi2(dof)``, finite far in the tail (``chi2.logsf``).

    Where the probability underflows, the upper incomplete gamma function's asymptotic series
    ``Q(a, z) ~ z^(a-1) e^-z / Gamma(a) (1 + (a-1)/z + (a-1)(a-2)/z^2)`` with ``a = dof/2``,
    ``z = x/2`` gives its logarithm (relative error below 1e-3 there, where ``z`` is hundreds),
    so that statistics far beyond any level still rank by size.
    """
    p = float(chi2_sf(x, dof))
    if p > _SMALLEST:
        return float(np.log(p))
    a, z = 0.5 * dof, 0.5 * x
    series = 1.0 + (a - 1.0) / z + (a - 1.0) * (a - 2.0) / z**2
    return float((a - 1.0) * np.log(z) - z - special.gammaln(a) + np.log(max(series, _SMALLEST)))


def f_sf(f: float, dfn: float, dfd: float) -> float:
    """``P(X > f)`` for ``X ~ F(dfn, dfd)`` (``scipy.stats.f.sf``)."""
    return float(special.fdtrc(dfn, dfd, max(f, 0.0)))


def ncx2_sf(x: float, dof: float, nc: float) -> float:
    """``P(X > x)`` for a non-central ``X ~ chi2(dof, nc)`` (``scipy.stats.ncx2.sf``)."""
    return 1.0 - float(special.chndtr(max(x, 0.0), dof, nc))
