"""Robust losses: ``rho'`` is the derivative of ``rho`` (central differences, entry by entry, see
:mod:`fd_check`), and the Huber loss joins its two branches continuously."""

from __future__ import annotations

import numpy as np
import pytest
from fd_check import STEP, assert_jacobian

from licalib_cli.solver import CauchyLoss, HuberLoss


@pytest.mark.parametrize("loss", [HuberLoss(1.3), HuberLoss(0.2), CauchyLoss(0.7), CauchyLoss(3.0)])
def test_loss_derivative_matches_finite_differences(loss: HuberLoss | CauchyLoss) -> None:
    k2 = loss.threshold**2
    # both sides of the Huber kink at s = k^2 (the kink itself has no derivative)
    s = np.concatenate([np.linspace(1e-3, 0.95, 25) * k2, np.linspace(1.05, 400.0, 25) * k2])
    rho, drho = loss(s)
    fd = (loss(s + STEP)[0] - loss(s - STEP)[0]) / (2 * STEP)
    assert_jacobian(drho, fd, float(np.abs(rho).max()), what=type(loss).__name__)
    assert np.all(drho > 0.0) and np.all(drho <= 1.0)
    np.testing.assert_allclose(loss(np.zeros(1))[1], 1.0)  # quadratic near zero


def test_huber_branches_join_at_the_threshold() -> None:
    loss = HuberLoss(1.7)
    k2 = 1.7**2
    below, above = loss(np.array([k2 * (1 - 1e-12)])), loss(np.array([k2 * (1 + 1e-12)]))
    np.testing.assert_allclose(below[0], above[0], rtol=1e-10)
    np.testing.assert_allclose(below[1], above[1], rtol=1e-10)
    rho, drho = loss(np.array([4.0 * k2]))
    np.testing.assert_allclose(rho, 2 * 1.7 * (2 * 1.7) - k2)  # 2 k |r| - k^2 at |r| = 2 k
    np.testing.assert_allclose(drho, 0.5)  # k / |r|
