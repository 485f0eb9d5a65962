"""The shift of an effect the data show beyond doubt, measured by a refit
(``licalib_cli.pipeline.effect_refit``).

One linear step predicts how far estimating a fixed effect would move the extrinsic; for an
effect the data leave no doubt about, that step can be a fraction of the real move (a VLP-16
shake with horizontal offsets left out: 7.5 mm predicted, 54.6 mm off). Such an effect is
refitted, the larger of the two moves per coordinate becomes its shift, and the checks judge
again: the sigmas cover the move and the verdict says a refit measured it.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from held_effects import scored_effect as evidence

from licalib_cli.config import CalibConfig
from licalib_cli.geometry import so3
from licalib_cli.pipeline.checks import _effects
from licalib_cli.pipeline.effect_models import with_effect
from licalib_cli.pipeline.effect_refit import (
    REFIT_STATISTIC_PER_DOF,
    refit_shifts,
    unmistakable,
    with_move,
)
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE
from licalib_cli.pipeline.inflation import inflate
from licalib_cli.pipeline.round import extrinsic_of

RAW = np.array([1e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 1e-5])


def state(t: list[float], rpy_deg: list[float], dt: float) -> SimpleNamespace:
    return SimpleNamespace(
        t_imu_lidar=np.asarray(t),
        R_imu_lidar=so3.exp(np.radians(rpy_deg)),
        time_offset_s=dt,
    )


def test_only_a_selected_effect_far_beyond_its_degrees_of_freedom_is_refitted() -> None:
    strong = evidence("lidar_horizontal_offset", 2.0 * REFIT_STATISTIC_PER_DOF, rank=15)
    stronger_total = evidence("accel_bias_walk", 1.5 * REFIT_STATISTIC_PER_DOF, rank=30)
    weak = evidence("gyro_scale", 0.5 * REFIT_STATISTIC_PER_DOF)
    unselected = evidence("accel_scale", 10.0 * REFIT_STATISTIC_PER_DOF, selected=False)
    # the largest per degree of freedom, not the largest statistic
    assert unmistakable([stronger_total, weak, unselected, strong]) is strong
    assert unmistakable([weak, unselected]) is None
    assert unmistakable([]) is None
    assert evidence("x", 2.0 * REFIT_STATISTIC_PER_DOF).score.p_value < EFFECT_P_VALUE


def test_the_move_is_translation_rotation_about_the_lidar_axes_and_time_offset() -> None:
    before = state([0.1, 0.2, 0.3], [10.0, -20.0, 30.0], 0.010)
    delta = np.array([0.002, -0.001, 0.003])
    after = SimpleNamespace(
        t_imu_lidar=before.t_imu_lidar + np.array([0.01, -0.02, 0.03]),
        R_imu_lidar=before.R_imu_lidar @ so3.exp(delta),
        time_offset_s=0.0101,
    )
    move = extrinsic_of(before).moved_to(extrinsic_of(after))  # type: ignore[arg-type]
    np.testing.assert_allclose(move[:3], [0.01, -0.02, 0.03], atol=1e-12)
    np.testing.assert_allclose(move[3:6], delta, atol=1e-12)
    assert move[6] == pytest.approx(1e-4)


def test_the_shift_takes_the_larger_move_per_coordinate() -> None:
    e = evidence("lidar_horizontal_offset", 500.0, rank=15, shift_z_mm=7.5)
    move = np.array([-0.036, 0.0002, -0.040, 1e-5, 0.0, 0.0, -9e-5])
    out = with_move(e, move)
    np.testing.assert_allclose(out.shift_translation_m, [-0.036, 0.0002, -0.040])
    np.testing.assert_allclose(out.shift_rotation_rad, [1e-5, 0.0, 0.0])
    assert out.shift_time_offset_s == pytest.approx(-9e-5)
    assert out.refitted and not e.refitted
    small = with_move(e, np.zeros(7))  # a refit that barely moves keeps the step's shift
    np.testing.assert_allclose(small.shift, e.shift)


def test_refit_replaces_only_the_unmistakable_effect_and_keeps_the_order() -> None:
    top = evidence("lidar_horizontal_offset", 2400.0, rank=15, shift_z_mm=7.5)
    other = evidence("accel_bias_walk", 50.0)
    before = state([0.9, -0.5, -1.5], [83.0, 66.0, -91.0], -0.023)
    after = state([0.95, -0.5, -1.45], [83.0, 66.0, -91.0], -0.023)
    asked: list[str] = []

    def refit(name: str) -> SimpleNamespace:
        asked.append(name)
        return after

    out = refit_shifts([other, top], before, refit)  # type: ignore[arg-type]
    assert asked == ["lidar_horizontal_offset"]
    assert out is not None and out[0] is other and out[1].refitted
    np.testing.assert_allclose(out[1].shift_translation_m, [0.05, 0.0, 0.05], atol=1e-12)
    assert refit_shifts([other], before, refit) is None  # nothing unmistakable: no refit
    assert asked == ["lidar_horizontal_offset"]
    assert refit_shifts([top], before, lambda name: None) is None  # the refit failed


def test_a_refitted_shift_widens_the_sigmas_and_is_named_in_the_verdict() -> None:
    e = evidence("lidar_horizontal_offset", 2400.0, rank=15, shift_z_mm=7.5)
    refitted = with_move(e, np.array([0.0, 0.0, -0.040, 0.0, 0.0, 0.0, 0.0]))
    split, fit = SimpleNamespace(ran=False), SimpleNamespace(jitter=False)
    sigma_step, _ = inflate(RAW, (), [e], split, fit)  # type: ignore[arg-type]
    sigma, why = inflate(RAW, (), [refitted], split, fit)  # type: ignore[arg-type]
    assert sigma_step[2] < 0.008 < 0.040 < sigma[2]
    assert any("refit with lidar_horizontal_offset" in w for w in why)
    (finding,) = _effects([refitted], RAW)
    assert "a refit with it estimated moved the extrinsic by 40.0 mm" in finding.text
    (step_finding,) = _effects([e], RAW)
    assert "would move the extrinsic by about 7.5 mm" in step_finding.text


def test_the_refit_estimates_the_effect_on_top_of_the_configured_model() -> None:
    cfg = CalibConfig.model_validate({"model": {"imu": ["gyro_scale"], "lidar": ["range_offset"]}})
    out = with_effect(cfg, "lidar_horizontal_offset")
    assert out.model.lidar == ["range_offset", "horizontal_offset"]
    assert out.model.imu == ["gyro_scale"]
    assert cfg.model.lidar == ["range_offset"]  # the configuration itself is untouched
    assert with_effect(out, "lidar_horizontal_offset").model.lidar == out.model.lidar
    drift = with_effect(cfg, "imu_clock_drift")
    assert drift.model.imu == ["gyro_scale", "clock_drift"]
    assert drift.model.lidar == ["range_offset"]
