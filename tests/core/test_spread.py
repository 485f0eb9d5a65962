"""One spread for many small per-beam numbers (consistency/spread.py): the type-II maximum
likelihood spread, its BIC, and what it does where free numbers do not pay."""

from __future__ import annotations

import math

import numpy as np
import pytest

from licalib_cli.consistency.spread import shared_spread


def _score(rng: np.random.Generator, info: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The profiled gradient of a linear model with information ``info`` whose true effect is
    ``delta`` (unit noise): ``N(I delta, I)``."""
    return info @ delta + np.linalg.cholesky(info) @ rng.normal(size=delta.size)


def _information(rng: np.random.Generator, k: int) -> np.ndarray:
    a = 0.1 * rng.normal(size=(k, k))
    return np.diag(rng.uniform(0.5, 3.0, k)) + a @ a.T


@pytest.mark.parametrize("spread", [0.5, 1.0, 2.0])
def test_the_spread_is_recovered(spread: float) -> None:
    rng = np.random.default_rng(31)
    found = []
    for _ in range(60):
        info = _information(rng, 64)
        found.append(shared_spread(_score(rng, info, spread * rng.normal(size=64)), info).sigma)
    assert np.median(found) == pytest.approx(spread, rel=0.15)


def test_no_effect_rarely_pays() -> None:
    """Without an effect the ratio is at most that of one parameter on its boundary: twice it
    beyond ln n = 12 in well under 1 % of draws (1/2 P(chi2_1 > 12) = 3e-4)."""
    rng = np.random.default_rng(32)
    ratios = []
    for _ in range(400):
        info = _information(rng, 64)
        ratios.append(shared_spread(_score(rng, info, np.zeros(64)), info).log_ratio)
    ratios = np.array(ratios)
    assert np.mean(2.0 * ratios > 12.0) < 0.01
    assert np.mean(ratios == 0.0) > 0.3  # most draws: no spread at all


def test_one_spread_pays_where_free_numbers_do_not() -> None:
    """64 per-beam numbers of about 1.7 of their sigma each (the score about 3 per degree of
    freedom, as a 150 ppm per-beam range scale on a 10 s OS1-64 shake): free, the BIC (ln n =
    12.3) refuses them nearly always; as one spread, it takes them nearly always."""
    rng = np.random.default_rng(33)
    log_n = 12.3
    free_pays, spread_pays = [], []
    for _ in range(100):
        info = _information(rng, 64)
        g = _score(rng, info, 1.0 * rng.normal(size=64))
        statistic = float(g @ np.linalg.solve(info, g))
        free_pays.append(64 * log_n - statistic < 0.0)
        spread_pays.append(shared_spread(g, info).delta_bic(log_n) < 0.0)
    assert np.mean(free_pays) < 0.05
    assert np.mean(spread_pays) > 0.95


def test_the_ratio_is_the_marginal_likelihood_of_a_refit_with_the_prior() -> None:
    """For a linear model, what ``diagnose`` computes from a refit with the prior ``N(0, s^2)``
    (the drop of the sum of squares, the prior's term included, less ``ln det(1 + s^2 I)``)
    is twice the ratio the spread was chosen by, and its ``log_det`` that determinant."""
    rng = np.random.default_rng(34)
    info = _information(rng, 40)
    g = _score(rng, info, 0.8 * rng.normal(size=40))
    found = shared_spread(g, info)
    t = found.sigma**2
    # S(d) = S0 - 2 g.d + d I d; with the prior the minimum drops by g (I + 1/t)^-1 g
    drop = float(g @ np.linalg.solve(info + np.eye(40) / t, g))
    _, log_det = np.linalg.slogdet(np.eye(40) + t * info)
    assert found.log_det == pytest.approx(log_det, rel=1e-9)
    assert drop - log_det == pytest.approx(2.0 * found.log_ratio, rel=1e-9)
    # and the spread maximises it
    for factor in (0.8, 1.25):
        tt = t * factor**2
        other = float(g @ np.linalg.solve(info + np.eye(40) / tt, g))
        other -= np.linalg.slogdet(np.eye(40) + tt * info)[1]
        assert other < drop - log_det


def test_undetermined_directions_and_empty_groups() -> None:
    assert shared_spread(np.zeros(0), np.zeros((0, 0))).sigma == 0.0
    info = np.diag([4.0, 2.0, 0.0])  # the third direction undetermined
    found = shared_spread(np.array([12.0, 8.0, 5.0]), info)
    assert found.rank == 2
    assert found.sigma > 0.0
    assert found.log_det == pytest.approx(
        math.log1p(4 * found.sigma**2) + math.log1p(2 * found.sigma**2)
    )
    assert shared_spread(np.zeros(3), info).sigma == 0.0
