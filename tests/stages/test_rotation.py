"""Gyro integration and hand-eye rotation initialisation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from stages_motion import T0_NS, RotationMotion

from licalib_cli.errors import ExcitationError, TimestampError
from licalib_cli.initialization.rotation import (
    GyroIntegrator,
    HandEyeConfig,
    constant_velocity_error_deg,
    estimate_rotation_extrinsic,
    lidar_rotation_at,
    relative_rotations,
    solve_hand_eye_rotation,
)
from licalib_cli.measurements import ImuSamples

MOUNTINGS = {
    "identity": Rotation.identity(),
    "x90": Rotation.from_euler("x", 90, degrees=True),
    "z180": Rotation.from_euler("z", 180, degrees=True),
    "xy180": Rotation.from_rotvec(np.pi * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)),
    "y-90z90": Rotation.from_euler("yz", [-90, 90], degrees=True),
    "random1": Rotation.random(random_state=1),
    "random2": Rotation.random(random_state=2),
}


def _angle_deg(a: Rotation, b: Rotation) -> float:
    return float(np.degrees((a.inv() * b).magnitude()))


def test_gyro_integration_matches_analytic_orientation() -> None:
    motion = RotationMotion.random(5)
    imu = motion.imu(6.0, rate_hz=400.0)
    gyro = GyroIntegrator.from_imu(imu)
    tq = T0_NS + np.linspace(0.0, 5.99, 57) * 1e9
    tq = tq.astype(np.int64)
    truth = motion.rotation(imu.t_ns[:1]).inv() * motion.rotation(tq)
    err = np.degrees((truth.inv() * gyro(tq)).magnitude())
    # Trapezoidal integration at 400 Hz of up to ~2 rad/s: drift below 0.05 deg over 6 s.
    assert err.max() < 0.05, err.max()
    rel = relative_rotations(gyro, tq[:-1], tq[1:])
    rel_true = motion.rotation(tq[:-1]).inv() * motion.rotation(tq[1:])
    assert np.degrees((rel_true.inv() * rel).magnitude()).max() < 0.01
    with pytest.raises(TimestampError, match="outside the IMU data"):
        gyro(np.array([imu.t_ns[-1] + 1]))


@pytest.mark.parametrize("name", sorted(MOUNTINGS))
def test_hand_eye_recovers_any_mounting(name: str) -> None:
    r_x = MOUNTINGS[name]
    gen = np.random.default_rng(sorted(MOUNTINGS).index(name))
    m = 300
    axes = gen.normal(size=(m, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rel_i = Rotation.from_rotvec(axes * np.radians(gen.uniform(2.0, 15.0, m))[:, None])
    # 0.02 deg per axis of relative-rotation noise (odometry between neighbouring scans).
    noise = Rotation.from_rotvec(np.radians(0.02) * gen.normal(size=(m, 3)))
    rel_l = r_x.inv() * rel_i * r_x * noise
    # 5% gross outliers (e.g. odometry slips of a few degrees).
    bad = gen.choice(m, 15, replace=False)
    kick = Rotation.from_rotvec(np.radians(3.0) * gen.normal(size=(15, 3)))
    quats = rel_l.as_quat()
    quats[bad] = (rel_l[bad] * kick).as_quat()
    rel_l = Rotation.from_quat(quats)

    res = solve_hand_eye_rotation(rel_i, rel_l)
    # Tolerance 0.1 deg from no initial guess.
    err = _angle_deg(Rotation.from_matrix(res.R_imu_lidar), r_x)
    print(f"{name}: error {err:.4f} deg, std {res.std_deg:.4f} deg, cond {res.conditioning:.4f}")
    assert err < 0.1
    assert res.q_imu_lidar[3] >= 0.0
    assert res.conditioning < 0.1
    assert res.std_deg < 0.1
    assert err < 5.0 * res.std_deg
    assert res.axis_excitation_deg[2] > 1.0
    assert res.n_pairs >= m - 20


def test_hand_eye_single_axis_is_refused() -> None:
    gen = np.random.default_rng(0)
    m = 200
    r_x = MOUNTINGS["random1"]
    axis = np.array([0.3, -0.2, 0.93])
    axis /= np.linalg.norm(axis)
    rel_i = Rotation.from_rotvec(np.outer(gen.uniform(-8.0, 8.0, m), np.radians(axis)))
    for noise_deg in (0.0, 0.05):
        noise = Rotation.from_rotvec(np.radians(noise_deg) * gen.normal(size=(m, 3)))
        rel_l = r_x.inv() * rel_i * r_x * noise
        with pytest.raises(ExcitationError, match="rotate the rig about at least two axes"):
            solve_hand_eye_rotation(rel_i * noise, rel_l)
    # Barely moving: refused for lack of rotating intervals.
    tiny = Rotation.from_rotvec(np.radians(0.1) * gen.normal(size=(m, 3)))
    with pytest.raises(ExcitationError, match="too weak"):
        solve_hand_eye_rotation(tiny, r_x.inv() * tiny * r_x)


def test_hand_eye_weak_second_axis_flagged_by_conditioning() -> None:
    """Wobble about a second axis at the noise level: ill-conditioned, not a confident answer."""
    gen = np.random.default_rng(1)
    m = 200
    r_x = MOUNTINGS["x90"]
    rv = np.zeros((m, 3))
    rv[:, 2] = np.radians(gen.uniform(2.0, 8.0, m))
    rv[:, 0] = np.radians(0.6) * gen.normal(size=m)  # axis ratio ~0.12, above min_axis_ratio
    rel_i = Rotation.from_rotvec(rv)
    noise = Rotation.from_rotvec(np.radians(0.3) * gen.normal(size=(m, 3)))
    rel_l = r_x.inv() * rel_i * r_x * noise
    with pytest.raises(ExcitationError, match="ill-conditioned"):
        solve_hand_eye_rotation(rel_i, rel_l)


def test_rotation_extrinsic_from_gyro_and_poses() -> None:
    motion = RotationMotion.random(7)
    r_x = MOUNTINGS["y-90z90"]
    imu = motion.imu(12.0, rate_hz=200.0)
    poses = motion.lidar_poses(r_x, time_offset_s=0.0, duration_s=11.9, noise_deg=0.03)
    res = estimate_rotation_extrinsic(imu, poses, cfg=HandEyeConfig(pair_stride=2))
    assert _angle_deg(Rotation.from_matrix(res.R_imu_lidar), r_x) < 0.1
    assert res.n_pairs_total == len(poses) - 2
    # With a time offset, the IMU interval is shifted by it (t_imu = t_lidar + t_c).
    shifted = motion.lidar_poses(r_x, time_offset_s=0.05, duration_s=11.0, noise_deg=0.03)
    res_c = estimate_rotation_extrinsic(GyroIntegrator.from_imu(imu), shifted, time_offset_s=0.05)
    assert _angle_deg(Rotation.from_matrix(res_c.R_imu_lidar), r_x) < 0.1
    # The LiDAR orientation built from the gyro matches the poses.
    rot_at = lidar_rotation_at(GyroIntegrator.from_imu(imu), res_c.R_imu_lidar, 0.05)
    r_l = rot_at(shifted.t_ns)
    rel = (r_l[0].inv() * r_l).inv() * shifted.rotations
    assert np.degrees(rel.magnitude()).max() < 0.3
    late = motion.lidar_poses(r_x, 0.0, 5.0, start_ns=T0_NS + 20 * 10**9)
    with pytest.raises(TimestampError, match="do not overlap"):
        estimate_rotation_extrinsic(imu, late)


def test_constant_velocity_error_is_what_the_previous_interval_mispredicts() -> None:
    """Zero for a constant rate; for a rate switching between two values, the angle between the
    two intervals' rotations, the same whatever frame the rate is read in."""
    t = T0_NS + np.arange(0, 4000) * 2_500_000  # 400 Hz, 10 s
    scans = T0_NS + np.arange(1, 99) * 100_000_000  # 10 Hz interval ends
    steady = GyroIntegrator.from_imu(
        ImuSamples(t, np.tile([0.3, -0.2, 1.0], (t.size, 1)), np.zeros((t.size, 3)))
    )
    assert constant_velocity_error_deg(steady, scans).max() < 1e-6
    # Rate alternating every 0.1 s between two vectors: each interval rotates by one of them.
    w_a, w_b = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    even = ((t - T0_NS) // 100_000_000) % 2 == 0
    rate = np.where(even[:, None], w_a, w_b)
    expected = np.degrees(
        (Rotation.from_rotvec(0.1 * w_a).inv() * Rotation.from_rotvec(0.1 * w_b)).magnitude()
    )
    for r_x in (Rotation.identity(), Rotation.random(random_state=3)):
        gyro = GyroIntegrator.from_imu(ImuSamples(t, r_x.apply(rate), np.zeros((t.size, 3))))
        err = constant_velocity_error_deg(gyro, scans)
        assert err.shape == (scans.size - 2,)
        # The rate is linear between samples, so the switch smears over one 2.5 ms sample.
        assert np.median(np.abs(err - expected)) < 0.05 * expected, (np.median(err), expected)
    # Fewer than three times inside the IMU data: nothing to compare.
    assert constant_velocity_error_deg(steady, scans[:2]).size == 0


def test_a_still_rig_is_refused_and_a_slow_turn_is_not() -> None:
    """The still-rig check before the rotation search: an IMU that stays within 1 deg of its
    first attitude is refused with the angle it turned; a turn of 3 deg over 10 s (0.03 deg a
    sweep, far below what hand-eye pairs need) is left to the search."""
    from licalib_cli.pipeline.initialise import STILL_SPAN_DEG, _refuse_a_still_rig

    t = T0_NS + np.arange(0, 4000) * 2_500_000  # 400 Hz, 10 s
    sweeps = T0_NS + np.arange(0, 100) * 100_000_000
    phase = 2 * np.pi * (t - T0_NS) / 2e9  # a 2 s wobble
    amplitude = np.radians(0.3)  # attitude within +-0.3 deg about x and y
    wobble = np.stack(
        [amplitude * np.pi * np.cos(phase), amplitude * np.pi * np.sin(phase), 0 * phase], axis=1
    )
    still = GyroIntegrator.from_imu(ImuSamples(t, wobble, np.zeros((t.size, 3))))
    with pytest.raises(ExcitationError, match=r"the IMU turned at most 0\.[0-9]+ deg") as info:
        _refuse_a_still_rig(still, sweeps)
    assert f"(under {STILL_SPAN_DEG:g})" in str(info.value)
    assert "initialization.rotation_rpy_deg" in str(info.value)
    slow = np.tile(np.radians([0.3, 0.0, 0.0]), (t.size, 1))  # 3 deg over the 10 s
    _refuse_a_still_rig(GyroIntegrator.from_imu(ImuSamples(t, slow, np.zeros((t.size, 3)))), sweeps)
