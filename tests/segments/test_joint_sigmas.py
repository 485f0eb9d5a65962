"""How the joint sigmas of a multi-segment calibration take over the segments' enlargements.

The segments' checks enlarge their solver sigmas by factors of their own (chi-square, split
halves), which the joint sigma takes over weighted by the segments' information, and by parts
every segment shares, which it must not shrink: the IMU priors (``model.imu_prior``; an IMU error
the data do not show moves every segment alike, so the joint keeps the best-determined
segment's part as it is) and the shift of an effect held fixed that the checks cover.
"""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from held_effects import imu_effect

from licalib_cli.consistency.score import EffectScore
from licalib_cli.pipeline.fitcheck import EffectEvidence
from licalib_cli.pipeline.joint import _growth
from licalib_cli.sections import Uncertainty

RAW = np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-5])


def _effect(prior_std: np.ndarray) -> EffectEvidence:
    # not shown (p = 0.8): covered by its prior, not by a shift
    return imu_effect(p_value=0.8, statistic=1.0, prior_std=prior_std)


def _segment(factor: float, prior_std: np.ndarray) -> SimpleNamespace:
    """A segment whose checks enlarged its solver sigmas ``factor`` times, then added the
    priors' ``prior_std`` in quadrature."""
    return _checked(np.sqrt((RAW * factor) ** 2 + prior_std**2), (_effect(prior_std),))


def _checked(shown: np.ndarray, effects: tuple[EffectEvidence, ...]) -> SimpleNamespace:
    """A segment whose checks report the (7,) sigmas ``shown`` and the ``effects``."""
    checks = SimpleNamespace(
        uncertainty=Uncertainty(tuple(shown[:3]), tuple(np.degrees(shown[3:6])), float(shown[6])),
        raw_sigma=RAW,
        consistency=SimpleNamespace(sensors=()),
        planes=None,
        effects=effects,
    )
    return SimpleNamespace(checks=checks)


def test_the_priors_part_is_kept_apart_and_not_scaled() -> None:
    big = np.array([2e-3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    small = np.array([1e-3, 5e-4, 0.0, 0.0, 0.0, 0.0, 0.0])
    grow, chi, planes, effects, prior = _growth([_segment(1.5, big), _segment(1.2, small)])  # type: ignore[list-item]
    # the factors alone, the priors taken out, weighted by the (equal) information
    np.testing.assert_allclose(grow, np.sqrt(2.0 / (1 / 1.5**2 + 1 / 1.2**2)))
    np.testing.assert_array_equal(effects, 0.0)
    np.testing.assert_allclose(prior, np.minimum(big, small) ** 2)  # the best-determined segment
    assert chi == pytest.approx(1.0) and planes is None


def test_a_covered_effects_shift_is_kept_apart_from_the_weighted_factors() -> None:
    """An effect the data hint at and that moves the extrinsic by more than its sigma is covered
    by its shift: the joint keeps the largest ratio of that variance to a segment's solver
    variance instead of weighting it down with the other segments' information."""
    shift = np.array([3e-3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # 3 raw sigmas on t_x
    covered = imu_effect(
        p_value=1e-5, statistic=30.0, selected=True, shift=shift, shift_std=np.full(7, 1e-4)
    )
    seg = _checked(np.sqrt((RAW * 1.2) ** 2 + shift**2 + 1e-4**2), (covered,))
    plain = _segment(1.2, np.zeros(7))
    grow, _, _, effects, prior = _growth([seg, plain])  # type: ignore[list-item]
    np.testing.assert_allclose(grow, 1.2)  # the own part: the effect taken out
    np.testing.assert_allclose(effects, (shift**2 + 1e-4**2) / RAW**2)  # from the one segment
    np.testing.assert_array_equal(prior, 0.0)


def _covering_segment(
    name: str, gradient: np.ndarray, information: np.ndarray, shift: np.ndarray
) -> SimpleNamespace:
    """A segment whose checks cover effect ``name`` (p < 1e-3, moving t_x by ``shift``) with
    the given profiled gradient and information; its sigmas are the solver's plus the shift."""
    inv = np.linalg.pinv(information)
    statistic = float(gradient @ inv @ gradient)
    score = EffectScore(
        name=name,
        statistic=statistic,
        rank=3,
        p_value=1e-6,
        estimate=inv @ gradient,
        sigma=np.ones(3),
        shift=np.zeros(7),
        shift_sigma=np.zeros(7),
        gradient=gradient,
        profiled_information=information,
    )
    covered = replace(
        imu_effect(name, p_value=1e-6, statistic=statistic, selected=True, shift=shift), score=score
    )
    return _checked(np.sqrt(RAW**2 + shift**2), (covered,))


def _quiet_segment(name: str, gradient: np.ndarray, information: np.ndarray) -> SimpleNamespace:
    """A segment whose test of ``name`` is not significant (not covered)."""
    seg = _covering_segment(name, gradient, information, np.zeros(7))
    (e,) = seg.checks.effects
    score = EffectScore(**{**e.score.__dict__, "p_value": 0.5})
    seg.checks.effects = (EffectEvidence(**{**e.__dict__, "score": score}),)
    return seg


SHIFT = np.array([3e-3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # 3 raw sigmas on t_x


@pytest.mark.parametrize("name", ["gyro_rotation", "accel_bias_walk"])
def test_a_hint_the_segments_together_do_not_show_counts_by_its_segments_share(
    name: str,
) -> None:
    """One window's checks show a gyro rotation (score 36 on 3), three others with as much
    information of it show nothing: the four together do not (score 9 on 3, p = 0.03), so the
    misfit is that window's and moves the joint estimate by the window's share of the
    information (a quarter here), not as if every window were moved by it. A bias drift
    differs between windows anyway and counts by its share too."""
    info = np.eye(3)
    hinted = _covering_segment(name, np.array([6.0, 0.0, 0.0]), info, SHIFT)
    others = [_quiet_segment(name, np.zeros(3), info) for _ in range(3)]
    _, _, _, effects, _ = _growth([hinted, *others])  # type: ignore[list-item]
    np.testing.assert_allclose(effects, 0.25 * SHIFT**2 / RAW**2)


def test_a_hint_the_segments_together_show_keeps_the_largest_ratio() -> None:
    """The same window, but the others' gradients point the same way (each below the checks'
    level alone): together they show the rig's gyro rotation, which moves every window alike,
    so the joint keeps the window's whole ratio."""
    info = np.eye(3)
    hinted = _covering_segment("gyro_rotation", np.array([6.0, 0.0, 0.0]), info, SHIFT)
    others = [_quiet_segment("gyro_rotation", np.array([2.0, 0.0, 0.0]), info) for _ in range(3)]
    _, _, _, effects, _ = _growth([hinted, *others])  # type: ignore[list-item]
    np.testing.assert_allclose(effects, SHIFT**2 / RAW**2)
