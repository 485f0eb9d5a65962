"""How the joint sigmas of a multi-segment calibration take over the segments' enlargements.

The segments' checks enlarge their solver sigmas by factors (map planes, chi-square, split
halves, covered effects), which the joint sigma takes over as factors, and by the IMU priors
(``model.imu_prior``), which it must not shrink: an IMU error the data do not show moves every
segment alike, so the joint keeps the best-determined segment's part as it is.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from licalib_cli.consistency.score import EffectScore
from licalib_cli.pipeline.fitcheck import EffectEvidence
from licalib_cli.pipeline.joint import _growth

RAW = np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-5])


def _effect(prior_std: np.ndarray) -> EffectEvidence:
    score = EffectScore(
        name="accel_scale",
        statistic=1.0,
        rank=3,
        p_value=0.8,  # not shown: covered by its prior, not by a shift
        estimate=np.zeros(3),
        sigma=np.ones(3),
        shift=np.zeros(7),
        shift_sigma=np.zeros(7),
    )
    return EffectEvidence(
        score=score,
        sensor="imu",
        selected=False,
        shift_translation_m=np.zeros(3),
        shift_rotation_rad=np.zeros(3),
        shift_time_offset_s=0.0,
        prior_std=prior_std,
    )


def _segment(factor: float, prior_std: np.ndarray) -> SimpleNamespace:
    """A segment whose checks enlarged its solver sigmas ``factor`` times, then added the
    priors' ``prior_std`` in quadrature."""
    shown = np.sqrt((RAW * factor) ** 2 + prior_std**2)
    uncertainty = SimpleNamespace(
        translation_std_m=shown[:3],
        rotation_std_deg=np.degrees(shown[3:6]),
        time_offset_std_s=float(shown[6]),
    )
    checks = SimpleNamespace(
        uncertainty=uncertainty,
        raw_sigma=RAW,
        consistency=SimpleNamespace(sensors=()),
        planes=None,
        effects=(_effect(prior_std),),
    )
    return SimpleNamespace(checks=checks)


def test_the_priors_part_is_kept_apart_and_not_scaled() -> None:
    big = np.array([2e-3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    small = np.array([1e-3, 5e-4, 0.0, 0.0, 0.0, 0.0, 0.0])
    grow, chi, planes, prior = _growth([_segment(1.5, big), _segment(1.2, small)])  # type: ignore[list-item]
    np.testing.assert_allclose(grow, 1.5)  # the factors alone, the priors taken out
    np.testing.assert_allclose(prior, np.minimum(big, small) ** 2)  # the best-determined segment
    assert chi == pytest.approx(1.0) and planes is None
