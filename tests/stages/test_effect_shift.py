"""The planes-free effect shift: which planes stay held; the priors' spread with them free."""

from __future__ import annotations

import numpy as np
from held_effects import prior_held

from licalib_cli.pipeline.effect_shift import _degenerate


def _block(jac: np.ndarray) -> np.ndarray:
    return jac.T @ jac


def test_planes_whose_own_information_is_singular_or_indefinite_are_held() -> None:
    rng = np.random.default_rng(4)
    healthy = _block(np.column_stack([rng.normal(size=(40, 2)), np.ones(40)]))
    # points along one scan line: the normal's turn about the line is not determined
    line = rng.normal(size=40)
    collinear = _block(np.column_stack([line, 0.0 * line, np.ones(40)]))
    one_point = _block(np.array([[0.3, -0.2, 1.0]]))
    indefinite = healthy - np.diag([0.0, 0.0, 2.0 * healthy[2, 2]])
    empty = np.zeros((3, 3))
    got = _degenerate(np.stack([healthy, collinear, one_point, indefinite, empty]))
    assert got.tolist() == [False, True, True, True, True]


def _held_block_z(rng: np.random.Generator, planes_free: bool, prior: float = 0.1) -> float:
    """One linear recording: an estimated coordinate ``x_b`` (truth 0), a nuisance ``x_p``
    estimated with it (a map plane), and a block ``x_e`` drawn from its prior and held at zero
    that the nuisance partly takes up. Returns the squared error of ``x_b`` over its sigma with
    what the prior adds (its spread and the move to its posterior mean), computed with the
    nuisance eliminated or held; the solver's own sigma with the nuisance free either way."""
    from licalib_cli.pipeline.fitcheck import _planes_free_prior
    from licalib_cli.pipeline.inflation import prior_variance

    n = 400
    u, v, w = rng.normal(size=(3, n))
    a = np.column_stack([u + w, u + 0.3 * v, w + 0.2 * v])  # x_b, x_e, x_p
    y = a[:, 1] * rng.normal(0.0, prior) + rng.normal(size=n)
    fitted = np.linalg.lstsq(a[:, [0, 2]], y, rcond=None)[0]  # x_b and x_p, x_e held at zero
    r = a[:, [0, 2]] @ fitted - y
    s_full, g = a.T @ a, -(a.T @ r)
    raw2 = np.linalg.inv(s_full[np.ix_([0, 2], [0, 2])])[0, 0]  # x_b's variance, x_p free
    held_s, b = s_full[:2, :2], g[:2]  # the nuisance held where the fit put it
    keep = [0, 1]  # or eliminated (the right-hand side the planes-fixed one, as the checks take)
    free_s = s_full[np.ix_(keep, keep)] - np.outer(s_full[keep, 2], s_full[2, keep]) / s_full[2, 2]
    system = (free_s if planes_free else held_s, np.full(2, np.nan), np.arange(2))
    spread, joint = _planes_free_prior(
        system, b, [0], {"e": [1]}, {"e": np.array([prior])}, [], 1.0
    )
    assert joint is not None
    evidence = prior_held(joint, spread["e"][0])
    sigma2 = raw2 + prior_variance([evidence], np.full(7, np.inf))[0]
    return float(fitted[0] ** 2 / sigma2)


def test_the_priors_spread_with_the_planes_free_covers_what_the_planes_took_up() -> None:
    """With the nuisance eliminated, the sigma with the held block's prior covers the error
    (unit spread: 1.02); with it held where the fit put it, the error is 1.77 times its sigma."""
    rng = np.random.default_rng(8)
    free = [_held_block_z(rng, True) for _ in range(500)]
    held = [_held_block_z(rng, False) for _ in range(500)]
    assert 0.9 < np.sqrt(np.mean(free)) < 1.1
    assert np.sqrt(np.mean(held)) > 1.4
