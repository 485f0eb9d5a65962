"""Which fixed effects the reported sigmas cover (``licalib_cli.pipeline.inflation.inflate``).

An effect the fit holds fixed biases the extrinsic by about the shift estimating it would cause.
A significant one (the stricter level that names effects) that moves the extrinsic beyond its
sigma is covered, and so is one the data only hint at (p below ``COVER_P_VALUE``): simulated
accelerometer scales just short of being named left the extrinsic 3.3 of its sigmas off. The
added variance is the shift squared plus the spread the effect's estimate would add.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from held_effects import imu_effect

from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, EffectEvidence
from licalib_cli.pipeline.inflation import COVER_P_VALUE, effect_to_cover, inflate
from licalib_cli.sections import EffectCheck

RAW = np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-5])


def evidence(
    p_value: float, shift_z_mm: float, *, selected: bool = False, prior_z_mm: float = 0.0
) -> EffectEvidence:
    """An accelerometer scale moving t_z by ``shift_z_mm``, with a shift sigma of 0.5 mm (and,
    known to within its prior, adding ``prior_z_mm`` to the sigma of t_z)."""
    std = np.zeros(7)
    std[2] = 0.5e-3
    return imu_effect(
        p_value=p_value,
        statistic=10.0,
        selected=selected,
        shift=np.array([0.0, 0.0, 1e-3 * shift_z_mm, 0.0, 0.0, 0.0, 0.0]),
        shift_std=std,
        prior_std=np.array([0.0, 0.0, 1e-3 * prior_z_mm, 0.0, 0.0, 0.0, 0.0]),
    )


def run(effects: list[EffectEvidence]) -> tuple[np.ndarray, tuple[str, ...]]:
    return inflate(RAW, (), effects, SimpleNamespace(ran=False), SimpleNamespace(jitter=False))


@pytest.mark.parametrize(
    ("p_value", "selected", "shift_mm", "covered"),
    [
        (0.1 * EFFECT_P_VALUE, True, 3.0, True),  # named and material
        (0.5 * COVER_P_VALUE, False, 3.0, True),  # hinted at, moves beyond the sigma
        (2.0 * COVER_P_VALUE, False, 3.0, False),  # nothing the data show
        (0.5 * COVER_P_VALUE, False, 0.5, False),  # hinted at, moves less than the sigma
    ],
)
def test_which_effects_are_covered(
    p_value: float, selected: bool, shift_mm: float, covered: bool
) -> None:
    e = evidence(p_value, shift_mm, selected=selected)
    assert effect_to_cover(e, RAW) is covered
    sigma, why = run([e])
    if covered:
        expected = np.sqrt(1.0 + shift_mm**2 + 0.25) * 1e-3
        assert sigma[2] == pytest.approx(expected)
        assert any("accel_scale" in w for w in why)
        np.testing.assert_allclose(np.delete(sigma, 2), np.delete(RAW, 2))
    else:
        np.testing.assert_array_equal(sigma, RAW)
        assert why == ()


def test_a_hinted_effect_is_named_as_such() -> None:
    _, why = run([evidence(0.5 * COVER_P_VALUE, 3.0)])
    assert "hint" in why[0] and "p = " in why[0]
    _, why = run([evidence(0.1 * EFFECT_P_VALUE, 3.0, selected=True)])
    assert "hint" not in why[0]


def _effect_check(name: str, p_value: float, covered: bool, statistic: float = 20.0) -> EffectCheck:
    """An IMU effect's line of the checks (3 degrees of freedom, a 1 mm shift in z)."""
    return EffectCheck(
        name=name,
        sensor="imu",
        statistic=statistic,
        dof=3,
        p_value=p_value,
        shift_translation_m=(0.0, 0.0, 1e-3),
        shift_rotation_deg=(0.0, 0.0, 0.0),
        shift_time_offset_s=0.0,
        covered=covered,
    )


def test_the_checks_table_names_a_hinted_effect() -> None:
    """The console and report table say which effect the sigmas cover though it is not named,
    instead of "none that moves the extrinsic"."""
    from licalib_cli.sections import Consistency

    check = _effect_check

    def outcome(effects: tuple[EffectCheck, ...]) -> str:
        rows = Consistency(effects=effects).rows()
        return next(r[2] for r in rows if r[0] == "effects held fixed")

    quiet = check("gyro_scale", 0.4, False)
    assert outcome((quiet,)) == "none that moves the extrinsic"
    hinted = check("accel_scale", 1e-5, True)
    assert "accel_scale" in outcome((quiet, hinted)) and "hinted" in outcome((quiet, hinted))


def test_a_p_value_that_underflows_is_printed_as_a_bound() -> None:
    """A statistic far in the tail has a chi-square p-value of exactly 0.0 in floating point;
    the tables and sentences say "p < 1e-300" rather than a probability of zero."""
    from licalib_cli.consistency.distributions import chi2_sf
    from licalib_cli.sections import Consistency, p_is, p_text

    assert float(chi2_sf(1520.0, 3)) == 0.0  # the gyro scale of the README's diagnose example
    assert p_text(0.0) == "< 1e-300" and p_is(0.0) == "p < 1e-300"
    assert p_text(0.1234) == "0.12" and p_is(0.1234) == "p = 0.12"
    assert p_is(4e-293, 1) == "p = 4e-293"
    effect = _effect_check("gyro_scale", 0.0, False, statistic=1522.0)
    figure = next(
        r[1] for r in Consistency(effects=(effect,)).rows() if r[0] == "effects held fixed"
    )
    assert figure == "strongest gyro_scale: p < 1e-300"


def test_every_material_effect_is_covered() -> None:
    """A named effect is also one the data hint at: the covering level is the looser one."""
    assert EFFECT_P_VALUE <= COVER_P_VALUE


def test_an_effect_the_data_do_not_show_adds_its_prior_spread() -> None:
    """Not shown, an IMU intrinsic held fixed is still only known to within model.imu_prior:
    its posterior spread enters the sigmas, once (a covered effect adds its shift instead)."""
    quiet = evidence(2.0 * COVER_P_VALUE, 3.0, prior_z_mm=2.0)
    sigma, why = run([quiet])
    assert sigma[2] == pytest.approx(np.sqrt(1.0 + 4.0) * 1e-3)
    np.testing.assert_allclose(np.delete(sigma, 2), np.delete(RAW, 2))
    assert len(why) == 1 and "model.imu_prior" in why[0] and "accel_scale" in why[0]
    assert "2.24" in why[0]  # times up to sqrt(5)
    covered = evidence(0.5 * COVER_P_VALUE, 3.0, prior_z_mm=2.0)
    sigma, why = run([covered])
    assert sigma[2] == pytest.approx(np.sqrt(1.0 + 9.0 + 0.25) * 1e-3)  # the shift, not the prior
    assert not any("imu_prior" in w for w in why)
    sigma, _ = run([quiet, evidence(2.0 * COVER_P_VALUE, 0.0, prior_z_mm=1.0)])
    assert sigma[2] == pytest.approx(np.sqrt(1.0 + 4.0 + 1.0) * 1e-3)  # variances add


def test_an_uncertain_translation_names_the_effects_that_made_it_so() -> None:
    from licalib_cli.config import CalibConfig
    from licalib_cli.pipeline.checks import uncertainty_findings

    limits = CalibConfig().checks

    sigma = np.array([2e-3, 2e-3, 15e-3, 1e-4, 1e-4, 1e-4, 1e-5])
    # 15 mm only through the shift of a covered effect: the effect is the cause
    by_effect = uncertainty_findings(sigma, RAW, limits, ["lidar_range_offset"])
    assert len(by_effect) == 1
    assert "lidar_range_offset" in by_effect[0].text
    assert "more rotation" not in by_effect[0].text
    # 15 mm without any effect: the motion is
    by_motion = uncertainty_findings(sigma, sigma, limits, ["lidar_range_offset"])
    assert "more rotation" in by_motion[0].text
    assert "lidar_range_offset" not in by_motion[0].text
    assert "more rotation" in uncertainty_findings(sigma, RAW, limits, [])[0].text
    # within the limits: nothing
    assert uncertainty_findings(RAW, RAW, limits, ["lidar_range_offset"]) == []


def test_a_clock_drift_the_stamps_measure_is_covered_and_told_whatever_its_score() -> None:
    """The IMU's stamps drift against the LiDAR's (record times) and the model holds the drift
    fixed: its score test may show nothing (with the IMU scales free, a drift looks like a
    scale), but its measured size moves the extrinsic: covered, material, and told with the
    rate and the advice; the same shift unmeasured and unshown is neither."""
    from dataclasses import replace

    from licalib_cli.pipeline.checks import _effects
    from licalib_cli.pipeline.inflation import effect_is_material

    quiet = replace(
        imu_effect("imu_clock_drift", p_value=0.3, statistic=1.0, rank=1),
        shift_translation_m=np.array([3e-3, 0.0, 0.0]),
    )
    measured = replace(quiet, measured=True, measured_value=50e-6)
    assert not effect_to_cover(quiet, RAW) and not effect_is_material(quiet, RAW)
    assert effect_to_cover(measured, RAW) and effect_is_material(measured, RAW)
    sigma, why = run([measured])
    assert sigma[0] == pytest.approx(np.hypot(1e-3, 3e-3))
    assert why == ("by the shift of imu_clock_drift held at zero, at its measured size",)
    (finding,) = _effects([measured], RAW)
    assert finding.severity == "warn"
    assert "+50.0 ppm" in finding.text and "Add clock_drift to model.imu" in finding.text
    assert "3.0 mm" in finding.text
    # measured but moving the extrinsic less than its sigma: nothing to cover or tell
    small = replace(measured, shift_translation_m=np.array([0.5e-3, 0.0, 0.0]))
    assert not effect_to_cover(small, RAW) and _effects([small], RAW) == []


def test_a_measured_effect_the_data_hint_at_keeps_the_larger_shift() -> None:
    """Measured apart from the fit, an effect's shift is its measurement's; when the data hint
    at it too, each coordinate keeps the larger of that and the data's own shift (the sigmas
    covered the data's before), and the larger spread."""
    from licalib_cli.pipeline.fitcheck import with_measured

    data = (np.array([3.0, -0.5, 0.0]), np.array([0.2, 0.2, 0.2]))
    measured = (np.array([1.0, -2.0, 0.1]), np.array([0.1, 0.3, 0.1]))
    shift, spread = with_measured(data, measured, hinted=False)
    np.testing.assert_array_equal(shift, measured[0])
    np.testing.assert_array_equal(spread, measured[1])
    shift, spread = with_measured(data, measured, hinted=True)
    np.testing.assert_array_equal(shift, [3.0, -2.0, 0.1])
    np.testing.assert_array_equal(spread, [0.2, 0.3, 0.2])


def test_the_checks_table_says_a_measured_drift_got_its_size_from_the_stamps() -> None:
    """A clock drift whose shift comes from the stamps' rate has an unremarkable score test; the
    table says where its size came from instead of printing that score."""
    from dataclasses import replace

    from licalib_cli.sections import Consistency

    drift = replace(
        _effect_check("imu_clock_drift", 0.3, True, statistic=1.0), material=True, measured=True
    )
    row = next(r for r in Consistency(effects=(drift,)).rows() if r[0] == "effects held fixed")
    assert row[1] == "imu_clock_drift: its size from the stamps, moves 1.0 mm / 0.000 deg"
    assert row[2] == "imu_clock_drift" and row[3]
    scored = replace(drift, measured=False)
    row = next(r for r in Consistency(effects=(scored,)).rows() if r[0] == "effects held fixed")
    assert row[1].startswith("imu_clock_drift: score 1 (dof 3)")


@pytest.mark.parametrize(("chi2", "said"), [(1.004, False), (1.21, True)])
def test_the_residuals_chi_square_enlarges_and_is_said_when_it_shows(
    chi2: float, said: bool
) -> None:
    sensors = (SimpleNamespace(sensor="lidar", chi2_per_sample=chi2),)
    sigma, why = inflate(
        RAW, sensors, [], SimpleNamespace(ran=False), SimpleNamespace(jitter=False)
    )
    np.testing.assert_allclose(sigma, RAW * np.sqrt(chi2), rtol=1e-12)
    # "times 1.00" says nothing; "times 1.10" names the sensor whose residuals set it
    expected = ("times 1.10, the root of the lidar residuals' chi-square per sample",)
    assert why == (expected if said else ())
