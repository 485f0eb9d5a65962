"""Priors a recording cannot check (``licalib_cli.pipeline.unchecked_priors``): the sigmas hold
while the IMU is within ``model.imu_prior`` (the LiDAR within ``model.lidar_prior``); when the
recording would name an effect only at several times its prior and an effect it cannot show
would move the extrinsic beyond its sigma, the sigmas' reason says so, and from three sigmas the
verdict warns. An effect held without a prior, taken as exact, that could hide three sigmas is
said in a note."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from held_effects import imu_effect

from licalib_cli.consistency.distributions import chi2_isf
from licalib_cli.consistency.power import detectable_noncentrality, detectable_rms
from licalib_cli.pipeline.crawl import COORDINATES
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, EffectEvidence
from licalib_cli.pipeline.inflation import COVER_P_VALUE, inflate
from licalib_cli.pipeline.unchecked_priors import (
    HIDDEN_SHIFT,
    UNCHECKED_FACTOR,
    UNCHECKED_WARN,
    assumed_note,
    combined_unchecked_priors,
    unchecked_priors,
    unchecked_sections,
    unchecked_text,
    unchecked_warning,
)
from licalib_cli.sections import Consistency, UncheckedPriorCheck

RAW = np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-5])
INFO = [3e5, 1e6, 1e7]  # names the effect from about 8.6 times a prior of 1e-3


def held(
    information: list[float],
    spread_z: float,
    *,
    name: str = "accel_scale",
    prior: float = 1e-3,
    rank: int | None = None,
    p_value: float = 0.3,
    shift_z_mm: float = 0.0,
) -> EffectEvidence:
    """An IMU effect of three coordinates the data do not show (p = 0.3 by default), known to
    within ``prior`` per coordinate, whose estimate would add ``spread_z`` of t_z's sigma
    (``RAW``) to t_z (its ``shift_std``; its prior spread the same, none without a prior), and
    whose shift moves t_z by ``shift_z_mm``."""
    spread = np.array([0.0, 0.0, 1e-3 * spread_z, 0.0, 0.0, 0.0, 0.0])
    return imu_effect(
        name,
        p_value=p_value,
        statistic=3.0,
        rank=rank,
        shift=np.array([0.0, 0.0, 1e-3 * shift_z_mm, 0.0, 0.0, 0.0, 0.0]),
        shift_std=spread,
        prior_std=spread if prior > 0.0 else np.zeros(7),
        prior_sigma=prior,
        information=information,
    )


def weakest(information: list[float]) -> float:
    return detectable_rms(chi2_isf(EFFECT_P_VALUE, len(information)), 3, information)[0]


def root_c(rank: int = 3) -> float:
    """The root of the non-centrality the score test names an effect from, nine times in ten."""
    return float(np.sqrt(detectable_noncentrality(chi2_isf(EFFECT_P_VALUE, rank), rank)))


def test_a_prior_the_recording_cannot_check_is_named_with_the_size_it_would_need() -> None:
    size = weakest(INFO)
    assert UNCHECKED_FACTOR * 1e-3 < size < 1e-2
    (u,) = unchecked_priors([held(INFO, 0.35)], RAW)
    assert u.effect == "accel_scale" and u.detectable == pytest.approx(size)
    assert u.hidden_shift == pytest.approx(0.35 * root_c())
    text = unchecked_text([u])
    assert text.startswith(", which this recording cannot check: it would show accel_scale only")
    assert f"{1e6 * size:.2g} ppm RMS (prior 1e+03)" in text
    assert text.endswith("the sigmas hold while the IMU is within those priors")


def test_the_hidden_shift_is_the_largest_move_of_an_effect_the_recording_cannot_show() -> None:
    """Over every effect ``d`` inside the ellipsoid ``d^T I d = c`` the score test names nine
    times in ten, the largest move of a coordinate: not the prior's reach times the detectable
    RMS along the worst direction, which is too small where the move lies along that direction
    (an effect of that RMS is sqrt(3) times as long) and too large where it lies along a
    direction the recording determines well."""
    rng = np.random.default_rng(5)
    info = np.array([2e5, 3e6, 4e7])
    shift_map = rng.normal(size=(7, 3)) * RAW[:, None] * 1e3  # per unit effect
    spread = np.sqrt(np.einsum("ij,j,ij->i", shift_map, 1.0 / info, shift_map))
    e = imu_effect(
        p_value=0.3,
        statistic=3.0,
        shift_std=spread,
        prior_std=spread,
        prior_sigma=1e-3,
        information=list(info),
    )
    (u,) = unchecked_priors([e], RAW)
    # effects on the ellipsoid's surface, in every direction
    d = rng.normal(size=(200_000, 3))
    d *= root_c() / np.sqrt(np.einsum("ij,j,ij->i", d, info, d))[:, None]
    moved = np.abs(d @ shift_map.T) / RAW
    assert moved.max() == pytest.approx(u.hidden_shift, rel=0.02)
    assert moved.max() <= u.hidden_shift * (1 + 1e-9)
    assert int(np.argmax(moved.max(axis=0))) == u.coordinate


def test_priors_the_recording_checks_or_that_cannot_hide_an_error_are_not_named() -> None:
    checked = [3e7, 1e8, 1e9]  # named from about 0.7 of its prior
    assert weakest(checked) < UNCHECKED_FACTOR * 1e-3
    assert unchecked_priors([held(checked, 0.9)], RAW) == []
    # unchecked, but even the largest effect it cannot show moves t_z by less than its sigma
    small = HIDDEN_SHIFT / root_c() / 2
    assert unchecked_priors([held(INFO, small)], RAW) == []
    # no prior: taken as exact, listed only from what could break a PASS
    assert unchecked_priors([held(INFO, 0.35, prior=0.0)], RAW) == []


def test_an_effect_with_an_undetermined_direction_is_never_checked() -> None:
    e = held([1e6, 1e7], 0.1, name="gyro_rotation", prior=np.radians(0.05), rank=2)
    (u,) = unchecked_priors([e], RAW)
    assert np.isinf(u.detectable) and np.isinf(u.hidden_shift)
    assert "gyro_rotation not in every direction (prior 0.05 deg)" in unchecked_text([u])


def test_the_order_is_by_the_error_each_could_hide_and_the_list_reads_as_a_sentence() -> None:
    a = held(INFO, 0.35)
    b = held(INFO, 0.7, name="accel_misalignment")
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

    assert "cannot check" in reason([held(INFO, 0.35)])
    assert "cannot check" not in reason([held([3e7, 1e8, 1e9], 0.9)])
    # an effect the data hint at is covered by its shift, not by its prior: not listed
    hinted = held(INFO, 0.35, p_value=0.5 * COVER_P_VALUE, shift_z_mm=3.0)
    _, why = inflate(RAW, (), [hinted], SimpleNamespace(ran=False), SimpleNamespace(jitter=False))
    assert not any("cannot check" in w for w in why)


def test_segments_calibrated_together_check_a_prior_with_their_information_summed() -> None:
    """The joint result's line: the segments' profiled informations add up (as their combined
    score test), and the spread the effect would add is at most the best-determined
    segment's."""
    one = [held(INFO, 0.35)]
    (u,) = combined_unchecked_priors([one, [held(INFO, 0.3)]], RAW)
    twice = detectable_rms(chi2_isf(EFFECT_P_VALUE, 3), 3, [2 * x for x in INFO])[0]
    assert u.detectable == pytest.approx(twice) and twice < weakest(INFO)
    assert u.hidden_shift == pytest.approx(0.3 * root_c())
    # forty segments name it from below three times its prior: checked together
    assert combined_unchecked_priors([one] * 40, RAW) == []
    # an effect one segment does not test is left out
    assert combined_unchecked_priors([one, []], RAW) == []
    # a direction no segment determines: never checked
    flat = held([1e6, 1e7], 0.3, name="gyro_rotation", prior=np.radians(0.05), rank=2)
    (g,) = combined_unchecked_priors([[flat], [flat]], RAW)
    assert np.isinf(g.detectable)


def test_a_prior_that_could_hide_two_sigmas_makes_the_verdict_warn_and_says_what_to_record() -> (
    None
):
    """Below :data:`UNCHECKED_WARN` the sigmas' line names the prior; from it the verdict
    warns, naming the block, the size the recording would need, the coordinate it moves and
    how to record or model it."""
    size = weakest(INFO)
    below = held(INFO, 0.9 * UNCHECKED_WARN / root_c(), name="accel_misalignment")
    (u,) = unchecked_priors([below], RAW)
    assert HIDDEN_SHIFT <= u.hidden_shift < UNCHECKED_WARN
    assert unchecked_warning([u]) is None
    over = held(INFO, 1.1 * UNCHECKED_WARN / root_c(), name="accel_misalignment")
    (u,) = unchecked_priors([over], RAW)
    assert u.hidden_shift >= UNCHECKED_WARN and COORDINATES[u.coordinate] == "t_z"
    text = unchecked_warning([u])
    assert text is not None
    assert text.startswith("The extrinsic rests on the IMU's own calibration of accel_misalignment")
    assert f"only from {np.degrees(size):.2g} deg RMS" in text
    assert f"an effect it cannot show would move t_z by up to {u.hidden_shift:.1f}" in text
    assert "tilted by tens of degrees" in text and "(model.imu: [accel_misalignment])" in text
    assert text.endswith(
        "set model.imu_prior.accel_misalignment to 0 and the result assumes it exact."
    )
    (section,) = unchecked_sections([u])
    assert section.warns and section.coordinate == "t_z" and section.unit == "deg"
    assert section.detectable == pytest.approx(np.degrees(size))


def test_every_block_that_could_hide_two_sigmas_is_named_the_worst_with_its_figures() -> None:
    step = UNCHECKED_WARN / root_c()
    items = unchecked_priors(
        [held(INFO, 1.2 * step), held(INFO, 2.0 * step, name="gyro_scale"), held(INFO, 0.6 * step)],
        RAW,
    )
    text = unchecked_warning(items)
    assert text is not None and "calibration of gyro_scale and accel_scale" in text
    assert "turned faster about every axis" in text
    assert "(model.imu: [gyro_scale, accel_scale])" in text
    assert "set model.imu_prior.gyro_scale and model.imu_prior.accel_scale to 0" in text
    assert text.endswith("the result assumes them exact.")
    # a direction the recording does not determine at all hides any size
    flat = held([1e6, 1e7], 0.1, name="gyro_rotation", prior=np.radians(0.05), rank=2)
    text = unchecked_warning(unchecked_priors([flat], RAW))
    assert text is not None and "does not show gyro_rotation in every direction" in text
    assert "set model.imu_prior.gyro_rotation_deg to 0" in text


def test_the_result_file_and_the_checks_table_carry_the_unchecked_priors() -> None:
    step = UNCHECKED_WARN / root_c()
    sections = unchecked_sections(
        unchecked_priors([held(INFO, 1.5 * step), held(INFO, 0.7 * step, name="gyro_scale")], RAW)
    )
    c = Consistency(unchecked_priors=sections)
    assert Consistency.from_dict(c.to_dict()).unchecked_priors == tuple(
        UncheckedPriorCheck.from_dict(s.to_dict()) for s in sections
    )
    (row,) = [r for r in c.rows() if r[0] == "IMU priors"]
    assert row[1].startswith("accel_scale shows from") and row[1].endswith("; 1 more")
    assert row[2] == f"unchecked: could move t_z {1.5 * UNCHECKED_WARN:.1f} sigma" and row[3]
    assert not [r for r in Consistency().rows() if r[0] == "IMU priors"]


def test_an_effect_taken_as_exact_is_noted_from_three_sigmas_and_never_warns() -> None:
    """Without a prior nothing says how large the effect may be: from what could break a PASS
    (:data:`UNCHECKED_WARN` sigmas) the checks note that the result assumes it, with the size
    the recording would need and how to estimate it or give its size; the verdict stays."""
    step = UNCHECKED_WARN / root_c()
    below = held(INFO, 0.95 * step, name="lidar_point_time", prior=0.0)
    assert unchecked_priors([below], RAW) == []
    over = held(INFO, 1.4 * step, name="lidar_point_time", prior=0.0)
    (u,) = unchecked_priors([over], RAW)
    assert u.assumed and not u.warns and u.hidden_shift == pytest.approx(1.4 * UNCHECKED_WARN)
    assert unchecked_warning([u]) is None and unchecked_text([u]) == ""
    note = assumed_note([u])
    assert note is not None
    size = 100 * weakest(INFO)
    assert (
        f"lidar_point_time (an error below {size:.2g} % of the sweep time RMS could move t_z"
        in (note)
    )
    assert "(model.lidar: [point_time])" in note and "model.lidar_prior.point_time" in note
    # a bias walk has no prior to give: only estimating it is offered
    walk = unchecked_priors([held(INFO, 1.4 * step, name="gyro_bias_walk", prior=0.0)], RAW)
    text = assumed_note(walk)
    assert text is not None and text.endswith("estimate it (model.imu: [gyro_bias_walk]).")
    # a size measured apart from the fit (the clock's rate from the record times) is known
    measured = held(INFO, 1.4 * step, name="imu_clock_drift", prior=0.0)
    measured = replace(measured, prior_std=np.full(7, 1e-4))
    assert unchecked_priors([measured], RAW) == []
    assert combined_unchecked_priors([[measured]], RAW) == []
    assert assumed_note([]) is None
    # the table's own row, apart from the priors', and the result file
    c = Consistency(unchecked_priors=unchecked_sections([u]))
    (row,) = [r for r in c.rows() if r[0] == "taken as exact"]
    assert row[1] == f"lidar_point_time shows from {size:.2g} % of the sweep time"
    assert row[2] == f"assumed: could move t_z {1.4 * UNCHECKED_WARN:.1f} sigma" and not row[3]
    (back,) = Consistency.from_dict(c.to_dict()).unchecked_priors
    assert back.prior == 0.0 and not back.warns and back.name == "lidar_point_time"


def test_a_lidar_prior_the_recording_cannot_check_warns_with_the_lidar_s_remedy() -> None:
    """``model.lidar_prior`` works as the IMU's: the same rule, the LiDAR's words, and with both
    sensors' priors warning, one sentence group each, the one that could hide most first."""
    step = UNCHECKED_WARN / root_c()
    azimuth = held(INFO, 2.0 * step, name="lidar_azimuth", prior=np.radians(0.001))
    (u,) = unchecked_priors([azimuth], RAW)
    text = unchecked_warning([u])
    assert text is not None
    assert text.startswith(
        "The extrinsic rests on the LiDAR's factory calibration of lidar_azimuth "
        "(model.lidar_prior: 0.001 deg), which this recording cannot check"
    )
    assert "Estimate it (model.lidar: [azimuth])" in text
    assert text.endswith("set model.lidar_prior.azimuth_deg to 0 and the result assumes it exact.")
    point = held(INFO, 1.5 * step, name="lidar_point_time", prior=2e-4)
    text = unchecked_warning(unchecked_priors([point], RAW))
    assert text is not None and text.startswith(
        "The extrinsic rests on the per-point times of the LiDAR's driver (lidar_point_time) "
        "(model.lidar_prior: 0.02 % of the sweep time)"
    )
    both = unchecked_priors([held(INFO, 1.2 * step), azimuth], RAW)
    text = unchecked_warning(both)
    assert text is not None
    lidar_at, imu_at = text.index("LiDAR's factory"), text.index("IMU's own calibration")
    assert lidar_at < imu_at and "(model.imu: [accel_scale])" in text[imu_at:]
    rows = Consistency(unchecked_priors=unchecked_sections(both)).rows()
    assert [r[0] for r in rows] == ["split halves", "priors"]
    rows = Consistency(unchecked_priors=unchecked_sections([u])).rows()
    assert rows[-1][0] == "LiDAR priors" and rows[-1][3]
    assert "the sigmas hold while the LiDAR is within those priors" in unchecked_text([u])
    assert "the sensors are within those priors" in unchecked_text(both)


def test_the_sigmas_reason_names_whose_priors_they_are() -> None:
    def reason(effects: list[EffectEvidence]) -> str:
        _, why = inflate(
            RAW, (), effects, SimpleNamespace(ran=False), SimpleNamespace(jitter=False)
        )
        return next(w for w in why if "held fixed, each known" in w)

    lidar = held(INFO, 0.35, name="lidar_range_offset", prior=1e-3)
    assert reason([lidar]).startswith(
        "by the LiDAR intrinsics held fixed, each known to within model.lidar_prior"
    )
    assert "IMU and LiDAR intrinsics held fixed, each known to within model.imu_prior and " in (
        reason([lidar, held(INFO, 0.35)])
    )


def test_an_effect_the_data_show_names_the_model_entry_that_estimates_it() -> None:
    """The warning of an effect held fixed that the data show says how to estimate it, by its
    entry in the ``model:`` section: a per-point time error is not among ``--intrinsics
    lidar``'s blocks, so "calibrate the LiDAR intrinsics too" sent users the wrong way."""
    from licalib_cli.pipeline.checks import _effects

    shown = replace(
        imu_effect(
            "lidar_point_time",
            p_value=1e-12,
            statistic=81.0,
            rank=1,
            selected=True,
            shift=np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3e-5]),
        ),
        sensor="lidar",
    )
    (finding,) = _effects([shown], RAW)
    assert finding.severity == "warn" and finding.text.startswith(
        "The LiDAR data show an effect the model holds fixed, lidar_point_time"
    )
    assert "Estimate it (model.lidar: [point_time] in the config; licalib diagnose" in (
        finding.text
    )


def test_segments_together_list_what_they_take_as_exact_from_their_information_summed() -> None:
    """The joint result's list: an effect without a prior is listed as taken as exact when it
    could hide three of the joint sigmas (the spread its estimate would add, at most the
    best-determined segment's); below that it is not listed."""
    step = UNCHECKED_WARN / root_c()
    one = [held(INFO, 1.5 * step, name="lidar_point_time", prior=0.0)]
    (u,) = combined_unchecked_priors([one, one], RAW)
    assert u.assumed and not u.warns and u.hidden_shift == pytest.approx(1.5 * UNCHECKED_WARN)
    small = [held(INFO, 0.9 * step, name="lidar_point_time", prior=0.0)]
    assert combined_unchecked_priors([small, small], RAW) == []
