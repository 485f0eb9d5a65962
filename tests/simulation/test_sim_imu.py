"""IMU readings: exact kinematics, integration back to the trajectory, noise, drift."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.models.imu import imu_measure
from licalib_cli.simulation import (
    Effect,
    IntrinsicsMode,
    Scenario,
    SimulationSpec,
    build_setup,
    generate_imu,
)


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def _integrate_rk4(
    r0: np.ndarray,
    v0: np.ndarray,
    p0: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    g_w: np.ndarray,
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """RK4 over pairs of samples (step 2 dt, the middle sample as the midpoint)."""

    def deriv(r: np.ndarray, v: np.ndarray, w: np.ndarray, a: np.ndarray):
        return r @ _hat(w), r @ a + g_w, v

    r, v, p = r0.copy(), v0.copy(), p0.copy()
    h = 2 * dt
    positions, rotations = [p.copy()], [r.copy()]
    for k in range(0, gyro.shape[0] - 2, 2):
        w0, w1, w2 = gyro[k], gyro[k + 1], gyro[k + 2]
        a0, a1, a2 = accel[k], accel[k + 1], accel[k + 2]
        k1 = deriv(r, v, w0, a0)
        k2 = deriv(r + h / 2 * k1[0], v + h / 2 * k1[1], w1, a1)
        k3 = deriv(r + h / 2 * k2[0], v + h / 2 * k2[1], w1, a1)
        k4 = deriv(r + h * k3[0], v + h * k3[1], w2, a2)
        p = p + h / 6 * (v + 2 * (v + h / 2 * k1[1]) + 2 * (v + h / 2 * k2[1]) + (v + h * k3[1]))
        r = r + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        v = v + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        u, _, vt = np.linalg.svd(r)
        r = u @ vt
        positions.append(p.copy())
        rotations.append(r.copy())
    return np.array(positions), np.array(rotations)


@pytest.mark.parametrize("scenario", [Scenario.SINUSOID, Scenario.SHAKE, Scenario.WALK])
def test_integrating_ideal_imu_follows_the_trajectory(scenario: Scenario) -> None:
    """Noise-free, intrinsics-free readings integrate to the true pose (< 1 mm, < 0.01 deg, 2 s)."""
    spec = SimulationSpec(
        scenario=scenario,
        duration_s=12.0 if scenario is Scenario.WALK else 2.0,
        seed=2,
        noise_free=True,
        intrinsics=IntrinsicsMode.NONE,
    )
    setup = build_setup(spec)
    imu, truth = generate_imu(spec, setup)
    # Start at the walk's first burst when there is one (the hardest part).
    t0 = setup.motion.bursts_s[0, 0] if setup.motion.bursts_s.size else 0.0
    i0 = int(np.searchsorted(truth.t_true_s, t0))
    sel = slice(i0, i0 + 801)  # 2 s at 400 Hz
    t = truth.t_true_s[sel]
    st0 = setup.trajectory.state(t[:1])
    pos, rot = _integrate_rk4(
        st0.rotation[0],
        st0.velocity[0],
        st0.position[0],
        imu.gyro[sel],
        imu.accel[sel],
        spec.gravity_w,
        1.0 / spec.imu_rate_hz,
    )
    ref = setup.trajectory.state(t[::2])
    assert np.max(np.linalg.norm(pos - ref.position, axis=1)) < 1e-3
    d_rot = np.einsum("nji,njk->nik", rot, ref.rotation)
    angle = np.arccos(np.clip((np.trace(d_rot, axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert np.degrees(angle.max()) < 0.01


def test_ideal_readings_are_the_kinematics() -> None:
    spec = SimulationSpec(duration_s=1.0, noise_free=True, intrinsics=IntrinsicsMode.NONE)
    setup = build_setup(spec)
    imu, truth = generate_imu(spec, setup)
    st = setup.trajectory.state(truth.t_true_s)
    assert np.array_equal(imu.gyro, st.angular_velocity)
    expected = np.einsum("nji,nj->ni", st.rotation, st.acceleration - [0.0, 0.0, -9.81])
    assert np.allclose(imu.accel, expected, atol=1e-12)
    assert imu.t_ns[0] == spec.base_time_ns and np.all(np.diff(imu.t_ns) == 2_500_000)


def test_intrinsics_and_g_sensitivity_follow_the_model() -> None:
    spec = SimulationSpec(duration_s=1.0, noise_free=True, effects=(Effect.G_SENSITIVITY,))
    setup = build_setup(spec)
    k = setup.imu_intrinsics
    assert np.abs(k.gyro_g_sensitivity).max() > 0
    assert not np.allclose(k.gyro_scale, 1.0) and not np.allclose(k.accel_bias, 0.0)
    imu, truth = generate_imu(spec, setup)
    g, a = imu_measure(k, truth.omega, truth.specific_force)
    assert np.allclose(imu.gyro, g, atol=1e-15) and np.allclose(imu.accel, a, atol=1e-15)


def test_noise_has_the_datasheet_sigma() -> None:
    """White noise sigma = density sqrt(rate) within 3 % (24k samples per axis)."""
    spec = SimulationSpec(duration_s=20.0, bias_walk_scale=0.0, intrinsics=IntrinsicsMode.NONE)
    imu, truth = generate_imu(spec)
    ideal, _ = generate_imu(spec.with_(noise_free=True))
    sg = np.std(imu.gyro - ideal.gyro)
    sa = np.std(imu.accel - ideal.accel)
    assert sg == pytest.approx(spec.gyro_noise_density * np.sqrt(400.0), rel=0.03)
    assert sa == pytest.approx(spec.accel_noise_density * np.sqrt(400.0), rel=0.03)
    assert truth.gyro_noise_sigma == pytest.approx(np.radians(0.01) * 20.0)


def test_bias_random_walk_grows_like_sqrt_time() -> None:
    spec = SimulationSpec(duration_s=100.0, bias_walk_scale=100.0, intrinsics=IntrinsicsMode.NONE)
    _, truth = generate_imu(spec)
    # 100x the MTi-100 walk: after 100 s the gyro bias std is 100 x 10 deg/h.
    drift = truth.gyro_bias[-1] - truth.gyro_bias[0]
    expected = 100 * spec.gyro_bias_walk_density * 10.0
    assert np.all(np.abs(drift) < 5 * expected)
    assert np.abs(drift).max() > 0.05 * expected


def test_clock_drift_scales_stamps() -> None:
    spec = SimulationSpec(duration_s=2.0, imu_clock_drift_ppm=100.0, noise_free=True)
    imu, truth = generate_imu(spec)
    rel = (imu.t_ns - spec.base_time_ns).astype(float) * 1e-9
    assert np.allclose(rel, truth.t_true_s * (1 + 100e-6), atol=1e-12)
    assert np.all(np.diff(imu.t_ns) == 2_500_000)
    assert truth.record_ns[-1] - spec.base_time_ns == pytest.approx(2.0e9 / (1 + 1e-4), abs=1)


def test_a_noise_seed_draws_new_noise_for_the_same_truth() -> None:
    """``noise_seed`` changes the IMU's and the LiDAR's noise and nothing else: the motion,
    the mounting, the time offset and the intrinsics stay those of ``seed``; by default the
    noise is ``seed``'s (bags made before the option are unchanged)."""
    from licalib_cli.simulation import generate_scans

    spec = SimulationSpec(duration_s=2.0, seed=3, random_time_offset=True, dropout=0.0)
    same = spec.with_(noise_seed=3)
    other = spec.with_(noise_seed=4)
    assert spec.resolved_noise_seed == 3 and other.resolved_noise_seed == 4
    base, other_setup = build_setup(spec), build_setup(other)
    np.testing.assert_array_equal(base.extrinsic.rotation, other_setup.extrinsic.rotation)
    np.testing.assert_array_equal(base.extrinsic.translation, other_setup.extrinsic.translation)
    assert base.extrinsic.time_offset_s == other_setup.extrinsic.time_offset_s
    np.testing.assert_array_equal(
        base.lidar_intrinsics.range_offset, other_setup.lidar_intrinsics.range_offset
    )
    imu, truth = generate_imu(spec)
    imu_same, _ = generate_imu(same)
    imu_other, truth_other = generate_imu(other)
    np.testing.assert_array_equal(imu.gyro, imu_same.gyro)
    np.testing.assert_array_equal(truth.omega, truth_other.omega)  # the same motion
    assert not np.array_equal(imu.gyro, imu_other.gyro)
    noise = imu.accel - imu_other.accel  # the difference of two draws: sqrt(2) sigma
    assert np.std(noise) == pytest.approx(np.sqrt(2) * truth.accel_noise_sigma, rel=0.1)
    scan = next(generate_scans(spec, indices=[1]))
    scan_other = next(generate_scans(other, indices=[1]))
    np.testing.assert_array_equal(scan.truth.rho_bar, scan_other.truth.rho_bar)
    assert not np.array_equal(scan.truth.rho, scan_other.truth.rho)
