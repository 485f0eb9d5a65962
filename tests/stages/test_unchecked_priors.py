"""IMU priors a recording cannot check (``licalib_cli.pipeline.unchecked_priors``): the sigmas
hold while the IMU is within ``model.imu_prior``; when the recording would name an effect only
at several times its prior and such an effect would move the extrinsic beyond its sigma, the
sigmas' reason says so."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from held_effects import imu_effect

from licalib_cli.consistency.distributions import chi2_isf
from licalib_cli.consistency.power import detectable_rms
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, EffectEvidence
from licalib_cli.pipeline.inflation import COVER_P_VALUE, inflate
from licalib_cli.pipeline.unchecked_priors import (
    HIDDEN_SHIFT,
    UNCHECKED_FACTOR,
    combined_unchecked_priors,
    unchecked_priors,
    unchecked_text,
)

RAW = np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-5])


def held(
    information: list[float],
    prior_z_mm: float,
    *,
    name: str = "accel_scale",
    prior: float = 1e-3,
    rank: int | None = None,
    p_value: float = 0.3,
    shift_z_mm: float = 0.0,
) -> EffectEvidence:
    """An IMU effect of three coordinates the data do not show (p = 0.3 by default), known to
    within ``prior`` per coordinate, whose prior spread adds ``prior_z_mm`` to the sigma of t_z
    (and whose shift moves t_z by ``shift_z_mm``)."""
    return imu_effect(
        name,
        p_value=p_value,
        statistic=3.0,
        rank=rank,
        shift=np.array([0.0, 0.0, 1e-3 * shift_z_mm, 0.0, 0.0, 0.0, 0.0]),
        prior_std=np.array([0.0, 0.0, 1e-3 * prior_z_mm, 0.0, 0.0, 0.0, 0.0]),
        prior_sigma=prior,
        information=information,
    )


def weakest(information: list[float]) -> float:
    return detectable_rms(chi2_isf(EFFECT_P_VALUE, len(information)), 3, information)[0]


def test_a_prior_the_recording_cannot_check_is_named_with_the_size_it_would_need() -> None:
    info = [3e5, 1e6, 1e7]
    e = held(info, 0.35)
    size = weakest(info)
    assert UNCHECKED_FACTOR * 1e-3 < size < 1e-2
    (u,) = unchecked_priors([e], RAW)
    assert u.effect == "accel_scale" and u.detectable == pytest.approx(size)
    assert u.hidden_shift == pytest.approx(0.35 * size / 1e-3)
    text = unchecked_text([u])
    assert text.startswith(", which this recording cannot check: it would show accel_scale only")
    assert f"{1e6 * size:.2g} ppm RMS (prior 1e+03)" in text
    assert text.endswith("the sigmas hold while the IMU is within those priors")


def test_the_hidden_shift_scales_the_reach_not_the_posterior_spread() -> None:
    """An effect as large as the recording can hide moves the estimate by its whole shift map
    (the reach), not by the prior's spread given the data, which the data narrow: with a reach
    of 0.8 of a sigma per prior sigma and a posterior spread of 0.35, the hidden shift is the
    reach's (where the data say nothing of the effect, the two agree)."""
    info = [3e5, 1e6, 1e7]
    size = weakest(info)
    e = replace(held(info, 0.35), prior_reach=np.array([0.0, 0.0, 0.8e-3, 0.0, 0.0, 0.0, 0.0]))
    (u,) = unchecked_priors([e], RAW)
    assert u.hidden_shift == pytest.approx(0.8 * size / 1e-3)
    (old,) = unchecked_priors([held(info, 0.35)], RAW)
    assert old.hidden_shift == pytest.approx(0.35 * size / 1e-3)
    # below a sigma by its spread, beyond it by its reach: named
    small = HIDDEN_SHIFT / (size / 1e-3) / 2
    reach = replace(
        held(info, small), prior_reach=np.array([0.0, 0.0, 4 * small * 1e-3, 0, 0, 0, 0])
    )
    assert unchecked_priors([held(info, small)], RAW) == []
    assert [u.effect for u in unchecked_priors([reach], RAW)] == ["accel_scale"]


def test_priors_the_recording_checks_or_that_cannot_hide_an_error_are_not_named() -> None:
    checked = [3e7, 1e8, 1e9]  # named from about 0.7 of its prior
    assert weakest(checked) < UNCHECKED_FACTOR * 1e-3
    assert unchecked_priors([held(checked, 0.9)], RAW) == []
    # unchecked, but even at the size it would need it moves t_z by less than its sigma
    info = [3e5, 1e6, 1e7]
    small = HIDDEN_SHIFT / (weakest(info) / 1e-3) / 2
    assert unchecked_priors([held(info, small)], RAW) == []
    assert unchecked_priors([held(info, 0.35, prior=0.0)], RAW) == []  # no prior: known exactly


def test_an_effect_with_an_undetermined_direction_is_never_checked() -> None:
    e = held([1e6, 1e7], 0.1, name="gyro_rotation", prior=np.radians(0.05), rank=2)
    (u,) = unchecked_priors([e], RAW)
    assert np.isinf(u.detectable) and np.isinf(u.hidden_shift)
    assert "gyro_rotation not in every direction (prior 0.05 deg)" in unchecked_text([u])


def test_the_order_is_by_the_error_each_could_hide_and_the_list_reads_as_a_sentence() -> None:
    info = [3e5, 1e6, 1e7]
    a = held(info, 0.35)
    b = held(info, 0.7, name="accel_misalignment")
    names = [u.effect for u in unchecked_priors([a, b], RAW)]
    assert names == ["accel_misalignment", "accel_scale"]
    text = unchecked_text(unchecked_priors([a, b], RAW))
    assert "accel_misalignment only from" in text and " and accel_scale only from " in text
    assert unchecked_text([]) == ""


def test_the_sigmas_reason_carries_it() -> None:
    def reason(effects: list[EffectEvidence]) -> str:
        _, why = inflate(
            RAW, (), effects, SimpleNamespace(ran=False), SimpleNamespace(jitter=False)
        )
        return next(w for w in why if "model.imu_prior" in w)

    assert "cannot check" in reason([held([3e5, 1e6, 1e7], 0.35)])
    assert "cannot check" not in reason([held([3e7, 1e8, 1e9], 0.9)])
    # an effect the data hint at is covered by its shift, not by its prior: not listed
    hinted = held([3e5, 1e6, 1e7], 0.35, p_value=0.5 * COVER_P_VALUE, shift_z_mm=3.0)
    _, why = inflate(RAW, (), [hinted], SimpleNamespace(ran=False), SimpleNamespace(jitter=False))
    assert not any("cannot check" in w for w in why)


def test_segments_calibrated_together_check_a_prior_with_their_information_summed() -> None:
    """The joint result's line: the segments' profiled informations add up (as their combined
    score test), and the prior moves the joint estimate as in the best-determined segment."""
    info = [3e5, 1e6, 1e7]
    one = [held(info, 0.35)]
    (u,) = combined_unchecked_priors([one, [held(info, 0.3)]], RAW)
    twice = detectable_rms(chi2_isf(EFFECT_P_VALUE, 3), 3, [2 * x for x in info])[0]
    assert u.detectable == pytest.approx(twice) and twice < weakest(info)
    assert u.hidden_shift == pytest.approx(0.3 * twice / 1e-3)
    # forty segments name it from below three times its prior: checked together
    assert combined_unchecked_priors([one] * 40, RAW) == []
    # an effect one segment does not test is left out
    assert combined_unchecked_priors([one, []], RAW) == []
    # a direction no segment determines: never checked
    flat = held([1e6, 1e7], 0.3, name="gyro_rotation", prior=np.radians(0.05), rank=2)
    (g,) = combined_unchecked_priors([[flat], [flat]], RAW)
    assert np.isinf(g.detectable)
