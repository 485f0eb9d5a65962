"""One spread for many small numbers: a per-beam effect as a random effect.

A per-beam intrinsic estimated as free numbers (one per beam) pays the BIC penalty ``ln n``
per beam; an effect of 150 ppm on each of 64 beams, each about twice its own sigma, shows
clearly in the score test and still does not pay. Treated as drawn from ``N(0, s^2)`` per beam,
the effect has one parameter, the spread ``s``, and the beams' values are estimated toward
nominal as far as the data leave them uncertain.

With the effect's profiled gradient ``g`` and information ``I``
(:class:`~licalib_cli.consistency.score.EffectScore`), the score is ``N(0, I)`` when the effect
is zero and ``N(0, I + s^2 I I)`` when it is drawn with spread ``s``. Along the eigenvectors of
``I`` (eigenvalues ``l_j``, ``c_j = (v_j^T g)^2 / l_j`` the statistic's part along each), the
log likelihood ratio is

    ``L(t) = 1/2 sum_j [c_j t l_j / (1 + t l_j) - ln(1 + t l_j)]``,  ``t = s^2``,

maximised over ``t`` (type-II maximum likelihood); ``L > 0`` only when the ``c_j`` exceed one on
average (weighted by ``l_j``). The marginal likelihood of a refit with the prior ``N(0, t)``
differs from that of the model without the effect by the refit's drop of the sum of squares (the
prior's own ``|d|^2 / t`` included) less ``ln det(1 + t I)`` (the Laplace approximation, exact
for a linear model); with one parameter the BIC adds ``ln n``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import optimize

__all__ = ["SharedSpread", "shared_spread"]


@dataclass(frozen=True)
class SharedSpread:
    """The spread that best explains a group's score as a random effect.

    Attributes:
        sigma: the spread per coordinate (the group's units); 0 when no spread explains the
            score better than none.
        log_ratio: the log likelihood ratio of that spread against none (at least 0).
        log_det: ``ln det(1 + sigma^2 I)``: what the marginal likelihood pays for the spread's
            freedom beyond the sum of squares.
        rank: directions of the group the data determine.
    """

    sigma: float
    log_ratio: float
    log_det: float
    rank: int

    def delta_bic(self, log_n: float) -> float:
        """The BIC change the linear model predicts for adding the group with this spread
        (one parameter): negative when it pays."""
        return -2.0 * self.log_ratio + log_n


def shared_spread(
    gradient: npt.ArrayLike, information: npt.ArrayLike, relative_rank: float = 1e-8
) -> SharedSpread:
    """The type-II maximum-likelihood spread of a group (module docstring).

    Args:
        gradient: (k,) the group's profiled gradient (divided by the fit's variance factor).
        information: (k, k) its profiled information (likewise).
        relative_rank: eigenvalues below this fraction of the largest do not count.
    """
    g = np.asarray(gradient, dtype=np.float64)
    info = np.asarray(information, dtype=np.float64)
    if g.size == 0:
        return SharedSpread(0.0, 0.0, 0.0, 0)
    lam, vec = np.linalg.eigh(0.5 * (info + info.T))
    keep = lam > relative_rank * max(float(lam.max()), 1e-300)
    lam, proj = lam[keep], vec[:, keep].T @ g
    if lam.size == 0:
        return SharedSpread(0.0, 0.0, 0.0, 0)
    c = proj**2 / lam

    def ratio(log_t: float) -> float:
        a = math.exp(log_t) * lam
        return float(0.5 * np.sum(c * a / (1.0 + a) - np.log1p(a)))

    lo, hi = math.log(1e-4 / lam.max()), math.log(1e4 / lam.min())
    grid = np.linspace(lo, hi, 121)
    values = np.array([ratio(x) for x in grid])
    best = int(np.argmax(values))
    if values[best] <= 0.0:
        return SharedSpread(0.0, 0.0, 0.0, int(lam.size))
    a_lo, a_hi = grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)]
    found = optimize.minimize_scalar(
        lambda x: -ratio(x), bounds=(a_lo, a_hi), method="bounded", options={"xatol": 1e-6}
    )
    log_t = float(found.x) if -float(found.fun) >= values[best] else float(grid[best])
    t = math.exp(log_t)
    return SharedSpread(
        sigma=math.sqrt(t),
        log_ratio=ratio(log_t),
        log_det=float(np.sum(np.log1p(t * lam))),
        rank=int(lam.size),
    )
