"""A residual pattern is material only when it matters against the noise the fit is weighted
with, not merely against residuals far quieter than that noise."""

from __future__ import annotations

from pathlib import Path

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


def test_a_noisy_gyro_on_a_clean_recording_shows_no_dependence_on_the_angular_rate(
    tmp_path: Path,
) -> None:
    """A reading carries the noise of its own residual: regressed on the readings, the residuals
    of a clean sinusoid with a gyro ten times noisier than the default showed a "dependence on
    the angular rate" (about 9 % of their variance). Against the fit's predicted rate they show
    none, while the table still holds the residuals prediction minus reading."""
    from licalib_cli.config import load_config
    from licalib_cli.pipeline import calibrate
    from licalib_cli.pipeline.fitcheck import residual_table, sensor_checks
    from licalib_cli.simulation import SimulationSpec, simulate
    from licalib_cli.simulation.spec import ACCEL_NOISE_DENSITY, GYRO_NOISE_DENSITY

    spec = SimulationSpec(
        scenario="sinusoid",
        duration_s=4.0,
        seed=43,
        intrinsics="none",
        azimuth_resolution_deg=0.8,
        gyro_noise_density=10 * GYRO_NOISE_DENSITY,
        accel_noise_density=10 * ACCEL_NOISE_DENSITY,
    )
    sim = simulate(spec, tmp_path / "sim")
    run = calibrate(sim.bag_path, load_config(None))
    gyro, accel, _ = sensor_checks(run.fit.state, run.fit.inputs, run.noise)
    assert not any(p.material for p in gyro.patterns + accel.patterns)
    table = residual_table(run.fit.state, run.fit.inputs)
    readings = run.fit.inputs.imu.gyro
    np.testing.assert_allclose(table.angular_rate - table.gyro, readings, atol=1e-12)
    # the same residuals regressed on the readings: the noise as a pattern
    (on_readings,) = _patterns(
        table.gyro, [("angular rate", readings, False)], run.noise.gyro_sigma
    )
    assert on_readings.material
