"""The benchmarks' information bound: units and the chances it reports."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from _information import LIMITS, information_bound, outside_limits

NAMES = [
    "ext.rotation.rx",
    "ext.rotation.ry",
    "ext.rotation.rz",
    "ext.translation.x",
    "ext.translation.y",
    "ext.translation.z",
    "ext.time_offset",
    "imu.accel_scale.x",
]


def _covariance(t_sd_m: float, r_sd_rad: float, dt_sd_s: float) -> np.ndarray:
    return np.diag([r_sd_rad**2] * 3 + [t_sd_m**2] * 3 + [dt_sd_s**2, 1e-8])


def test_isotropic_translation_gives_the_chi_mean_and_tail_in_mm() -> None:
    # 2 mm per axis: |t| is 2 mm times a chi variable with 3 dof (mean 2 sqrt(2/pi))
    out = information_bound(NAMES, _covariance(2e-3, 1e-7, 1e-9), seed=1)
    assert out["expected_translation_mm"] == pytest.approx(4.0 * math.sqrt(2.0 / math.pi), rel=0.01)
    # P(chi_3 > 1.5) = 0.5222
    assert out["p_translation_over"] == pytest.approx(0.5222, abs=0.01)
    assert out["solver_translation_sd_mm"] == pytest.approx([2.0, 2.0, 2.0], rel=1e-6)
    assert out["p_time_offset_over"] == 0.0


def test_time_offset_and_rotation_in_ms_and_degrees() -> None:
    # 0.05 ms: beyond 0.1 ms is beyond two sigmas (4.55 %); 0.01 deg per axis stays inside 0.05
    cov = _covariance(1e-5, math.radians(0.01), 5e-5)
    out = information_bound(NAMES, cov, seed=2)
    assert out["p_time_offset_over"] == pytest.approx(0.0455, abs=0.004)
    assert out["expected_time_offset_ms"] == pytest.approx(0.05 * math.sqrt(2 / math.pi), rel=0.02)
    assert out["expected_rotation_deg"] == pytest.approx(0.02 * math.sqrt(2 / math.pi), rel=0.02)
    assert out["p_outside"] == pytest.approx(out["p_time_offset_over"], abs=0.002)
    assert out["solver_time_offset_sd_ms"] == pytest.approx(0.05, rel=1e-6)


def test_names_the_coordinates_correlated_with_the_weakest_axis() -> None:
    cov = _covariance(1e-3, 1e-5, 1e-5)
    cov[4, 4] = 4e-6  # y is the weakest translation axis (2 mm)
    cov[4, 7] = cov[7, 4] = 0.9 * 2e-3 * 1e-4  # and 0.9 correlated with the accelerometer scale
    out = information_bound(NAMES, cov, seed=3)
    assert out["weakest_axis"] == "ext.translation.y"
    assert next(iter(out["weakest_axis_correlations"])) == "imu.accel_scale.x"
    assert out["weakest_axis_correlations"]["imu.accel_scale.x"] == pytest.approx(0.9)


def test_plane_factors_scale_the_sigmas_and_keep_the_correlations() -> None:
    from types import SimpleNamespace

    from _information import plane_factors

    cov = _covariance(2e-3, 1e-5, 5e-5)
    report = SimpleNamespace(calibration_names=NAMES, std=np.sqrt(np.diag(cov)))
    raw = np.array([3e-3, 2e-3, 2e-3, 1e-5, 1e-5, np.inf, 5e-5])  # x 1.5 times; rz not finite
    factors = plane_factors(report, raw)
    np.testing.assert_allclose(factors, [1.5, 1, 1, 1, 1, 1, 1])
    plain = information_bound(NAMES, cov, seed=4)
    wider = information_bound(NAMES, cov, seed=4, factors=factors)
    assert wider["solver_translation_sd_mm"] == pytest.approx([3.0, 2.0, 2.0])
    assert wider["expected_translation_mm"] > plain["expected_translation_mm"]


def test_a_run_is_outside_the_limits_when_any_of_its_three_errors_is_beyond_its_own() -> None:
    assert LIMITS == (3.0, 0.05, 0.1)  # the clean runs' 0.3 cm / 0.05 deg / 0.1 ms
    at = {"translation_mm": 3.0, "rotation_deg": 0.05, "time_offset_ms": 0.1}
    assert not outside_limits(at)  # on the limits is within them
    for key in at:
        assert outside_limits({**at, key: 1.01 * at[key]})
    assert not outside_limits({**at, "translation_mm": 9.0}, limits=(10.0, 0.05, 0.1))
    # the bound counts a draw by the same rule: all within the limits, never outside
    out = information_bound(NAMES, _covariance(1e-6, 1e-9, 1e-9), seed=5)
    assert out["p_outside"] == 0.0
