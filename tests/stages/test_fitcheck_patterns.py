"""A residual pattern is material only when it matters against the noise the fit is weighted
with, not merely against residuals far quieter than that noise."""

from __future__ import annotations

import numpy as np

from licalib_cli.pipeline.fitcheck import _patterns


def _gyro(scale_error: float, noise: float, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rate = rng.normal(scale=1.0, size=(20_000, 3))
    residual = scale_error * rate + rng.normal(scale=noise, size=rate.shape)
    return residual, rate


def test_a_pattern_far_below_the_weighted_noise_is_not_material() -> None:
    """Residuals of 1e-6 rad/s with a 1e-5 rad/s rate pattern (a noise-free recording's spline
    approximation), the fit weighted with 3.5e-3 rad/s: significant, most of the residual
    variance, and still 0.3 % of the noise the fit assumes."""
    residual, rate = _gyro(1e-5, 1e-6)
    (p,) = _patterns(residual, [("angular rate", rate, False)], np.full(3, 3.5e-3))
    assert p.p_value < 1e-9 and p.explained > 0.9
    assert not p.material


def test_a_pattern_of_a_tenth_of_the_noise_and_more_is_material() -> None:
    residual, rate = _gyro(1e-3, 3.5e-3)  # a 0.1 % gyro scale error at 1 rad/s
    (p,) = _patterns(residual, [("angular rate", rate, False)], np.full(3, 3.5e-3))
    assert p.material
    # the same residuals with the weighted noise as small as they are: material as before
    (q,) = _patterns(residual, [("angular rate", rate, False)], np.full(3, 1e-3))
    assert q.material
    # no pattern: not material whatever the noise
    clean, _ = _gyro(0.0, 3.5e-3, seed=6)
    (c,) = _patterns(clean, [("angular rate", rate, False)], np.full(3, 3.5e-3))
    assert not c.material
