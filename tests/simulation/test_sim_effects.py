"""Effects by name (with default strengths) and the seeded random time offset; each named effect
shows in the simulated measurements with its recorded size and sign."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.errors import ConfigError
from licalib_cli.results import CalibrationResult
from licalib_cli.sections import ExtraTerms, RecordingSection
from licalib_cli.simulation import SimulationSpec, build_setup, generate_imu
from licalib_cli.simulation.effects import Effect
from licalib_cli.simulation.ground_truth import draw_extrinsic
from licalib_cli.simulation.simulate import build_truth
from licalib_cli.simulation.spec import (
    EFFECT_BIAS_WALK_SCALE,
    EFFECT_IMU_CLOCK_DRIFT_PPM,
    RANDOM_TIME_OFFSET_MAX_S,
    IntrinsicsMode,
)
from licalib_cli.truth import SimulatedImu


def _imu_truth(spec: SimulationSpec) -> SimulatedImu:
    setup = build_setup(spec)
    simulation = build_truth(spec, setup).simulation
    assert simulation is not None
    return simulation.imu


def test_effect_names_are_accepted_as_strings_and_by_their_earlier_names() -> None:
    spec = SimulationSpec(effects=("bias-random-walk", "imu-clock-drift", "g-sensitivity"))
    assert set(spec.effects) == {
        Effect.GYRO_BIAS_WALK,
        Effect.ACCEL_BIAS_WALK,
        Effect.IMU_CLOCK_DRIFT,
        Effect.G_SENSITIVITY,
    }
    every = SimulationSpec(effects=tuple(e.value for e in Effect))
    assert every.effects == tuple(Effect)
    with pytest.raises(ConfigError, match="gyro_scale, gyro_misalignment"):
        SimulationSpec(effects=("rain",))


def test_bias_random_walk_effect_default_strength_and_override() -> None:
    base = SimulationSpec(duration_s=4.0, intrinsics=IntrinsicsMode.NONE)
    strong = base.with_(effects=("bias-random-walk",))
    assert base.resolved_bias_walk_scale == 1.0
    assert strong.resolved_bias_walk_scale == EFFECT_BIAS_WALK_SCALE == 10.0
    # same noise stream: the walk is exactly 10x the MTi-100 walk
    _, t_base = generate_imu(base)
    _, t_strong = generate_imu(strong)
    walk_base = t_base.gyro_bias - t_base.gyro_bias[0]
    walk_strong = t_strong.gyro_bias - t_strong.gyro_bias[0]
    assert np.abs(walk_base).max() > 0
    np.testing.assert_allclose(walk_strong, EFFECT_BIAS_WALK_SCALE * walk_base, rtol=1e-9)
    # the numeric option sets the strength, with or without the effect
    custom = strong.with_(bias_walk_scale=3.0)
    _, t_custom = generate_imu(custom)
    np.testing.assert_allclose(
        t_custom.gyro_bias - t_custom.gyro_bias[0], 3.0 * walk_base, rtol=1e-9
    )
    info = _imu_truth(strong.with_(duration_s=0.2))
    assert info.effects == ("gyro_bias_walk", "accel_bias_walk")
    assert info.bias_walk_scale == 10.0
    assert _imu_truth(base.with_(duration_s=0.2)).effects == ()


def test_imu_clock_drift_effect_default_strength_and_override() -> None:
    spec = SimulationSpec(duration_s=2.0, noise_free=True, effects=("imu_clock_drift",))
    assert spec.resolved_imu_clock_drift_ppm == EFFECT_IMU_CLOCK_DRIFT_PPM == 50.0
    imu, truth = generate_imu(spec)
    rel = (imu.t_ns - spec.base_time_ns).astype(float) * 1e-9
    np.testing.assert_allclose(rel, truth.t_true_s * (1 + 50e-6), atol=1e-12)
    info = _imu_truth(spec.with_(duration_s=0.2))
    assert info.effects == ("imu_clock_drift",) and info.clock_drift_ppm == 50.0
    # the numeric option alone sets the drift and records the effect
    only_ppm = SimulationSpec(duration_s=0.2, imu_clock_drift_ppm=-20.0)
    assert only_ppm.resolved_imu_clock_drift_ppm == -20.0
    info = _imu_truth(only_ppm)
    assert info.effects == ("imu_clock_drift",) and info.clock_drift_ppm == -20.0


def test_g_sensitivity_recorded_with_its_strength() -> None:
    info = _imu_truth(SimulationSpec(duration_s=0.2, effects=("g-sensitivity",)))
    assert info.effects == ("g_sensitivity",) and info.g_sensitivity_dps_per_g == 0.1


def test_random_time_offset_is_seeded_and_bounded() -> None:
    offsets = {
        seed: draw_extrinsic(SimulationSpec(seed=seed, random_time_offset=True)).time_offset_s
        for seed in range(20)
    }
    values = np.array(list(offsets.values()))
    assert np.all(np.abs(values) <= RANDOM_TIME_OFFSET_MAX_S)
    assert len(set(values.tolist())) == 20 and values.std() > 0.01
    # deterministic per seed, and independent of whether the extrinsic is drawn too
    again = SimulationSpec(seed=7, random_time_offset=True)
    both = again.with_(random_extrinsic=True)
    assert draw_extrinsic(again).time_offset_s == offsets[7]
    assert draw_extrinsic(both).time_offset_s == offsets[7]
    # rounded to whole nanoseconds like a given offset
    assert round(offsets[7] * 1e9) / 1e9 == offsets[7]


def test_random_time_offset_leaves_the_other_draws_unchanged() -> None:
    spec = SimulationSpec(seed=5, duration_s=0.3, random_extrinsic=True)
    drawn = spec.with_(random_time_offset=True)
    a, b = build_setup(spec), build_setup(drawn)
    np.testing.assert_array_equal(a.extrinsic.rotation, b.extrinsic.rotation)
    np.testing.assert_array_equal(a.extrinsic.translation, b.extrinsic.translation)
    np.testing.assert_array_equal(a.imu_intrinsics.gyro_scale, b.imu_intrinsics.gyro_scale)
    imu_a, _ = generate_imu(spec, a)
    imu_b, _ = generate_imu(drawn, b)
    np.testing.assert_array_equal(imu_a.gyro, imu_b.gyro)
    assert a.extrinsic.time_offset_s == 0.0 and b.extrinsic.time_offset_s != 0.0
    simulation = build_truth(drawn, b).simulation
    assert simulation is not None
    assert simulation.clock.time_offset_drawn is True
    assert simulation.clock.time_offset_s == pytest.approx(b.extrinsic.time_offset_s, abs=1e-12)


def test_random_time_offset_conflicts_with_a_given_offset() -> None:
    with pytest.raises(ConfigError, match="--random-time-offset"):
        SimulationSpec(random_time_offset=True, time_offset_s=0.01)


def test_the_true_time_offset_of_a_drifting_clock_is_taken_where_the_result_refers() -> None:
    """``Truth.extrinsic_for`` gives the offset ``t_imu - t_lidar`` of the simulated stamps at
    the instant whose LiDAR time is the result's reference stamp (a drift the model estimated:
    ``t_imu = t_lidar + time_offset_s + k (t_lidar - reference)``) or its recording's middle."""
    spec = SimulationSpec(
        duration_s=10.0, noise_free=True, imu_clock_drift_ppm=400.0, time_offset_s=0.03
    )
    truth = build_truth(spec, build_setup(spec))
    imu, sampled = generate_imu(spec)

    def offset_at_lidar_stamp(stamp_ns: int) -> float:
        """IMU stamp minus LiDAR stamp of the instant the LiDAR stamped ``stamp_ns`` (the IMU
        stamps are linear in true time: interpolated between the simulated samples)."""
        lidar_rel_s = (stamp_ns - spec.base_time_ns) * 1e-9
        t_true = lidar_rel_s + spec.time_offset_s
        imu_rel_s = np.interp(t_true, sampled.t_true_s, (imu.t_ns - spec.base_time_ns) * 1e-9)
        return float(imu_rel_s - lidar_rel_s)

    start = int(imu.t_ns[0])
    reference = start + 7_500_000_000
    recording = RecordingSection("b", "/imu", "/points", len(imu), 100, 10.0, start, 0.0, 0.0)
    estimated = CalibrationResult(
        recording=recording, extra_terms=ExtraTerms(reference_ns=reference)
    )
    assert truth.extrinsic_for(estimated).time_offset_s == pytest.approx(
        offset_at_lidar_stamp(reference), abs=1e-9
    )
    # the instant the LiDAR stamps 7.5 s came 7.53 s after the first: the offset has grown by
    # the drift over 7.53 s, which differs from the growth over 7.5 s by more than the tolerance
    assert offset_at_lidar_stamp(reference) - spec.time_offset_s == pytest.approx(
        400e-6 * 7.53, rel=1e-6
    )
    # a constant offset fitted to the whole recording is compared at its middle
    constant = CalibrationResult(recording=recording)
    assert truth.extrinsic_for(constant).time_offset_s == pytest.approx(
        offset_at_lidar_stamp(start + 5_000_000_000), abs=1e-9
    )
    # without a drift nothing but the clock split changes
    steady = spec.with_(imu_clock_drift_ppm=0.0)
    steady_truth = build_truth(steady, build_setup(steady))
    assert steady_truth.extrinsic_for(estimated).time_offset_s == 0.03
