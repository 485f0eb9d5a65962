"""Coarse time offset and whole-bag clock shift from angular-speed cross-correlation.

Convention under test: ``t_imu = t_lidar + time_offset_s``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial.transform import Rotation
from stages_motion import T0_NS, RotationMotion

from licalib_cli.errors import ExcitationError
from licalib_cli.initialization.time_offset import (
    TimeOffsetConfig,
    angular_speed_from_gyro,
    correlate_angular_speed,
    estimate_clock_shift,
    estimate_time_offset,
    estimate_time_offset_aligned,
    estimate_time_offset_joint,
)
from licalib_cli.measurements import ImuSamples
from licalib_cli.odometry import PoseSeries
from licalib_cli.simulation.scenarios import sinusoid


def _speed(t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """A smooth, non-periodic angular-speed profile, rad/s."""
    return (
        1.0
        + 0.5 * np.sin(2.1 * t_s)
        + 0.3 * np.sin(5.3 * t_s + 1.0)
        + 0.4 * np.exp(-((t_s - 6.0) ** 2) / 0.3)
        + 0.2 * np.sin(0.7 * t_s + 0.2)
    )


@pytest.mark.parametrize("offset_s", [0.02, -0.037])
def test_signal_offset_and_sign(offset_s: float) -> None:
    # LiDAR-clock signal at 10 Hz; the IMU sees the same profile offset_s later on its clock.
    tau = T0_NS + np.arange(0, 15_000_000_000, 100_000_000, dtype=np.int64)
    t_imu = T0_NS + np.arange(0, 15_000_000_000, 5_000_000, dtype=np.int64)
    a = _speed((tau - T0_NS) * 1e-9)
    b = _speed((t_imu - T0_NS) * 1e-9 - offset_s)
    est = correlate_angular_speed(tau, a, t_imu, b)
    # Tolerance 2 ms, same sign.
    assert est.time_offset_s == pytest.approx(offset_s, abs=0.002)
    assert np.sign(est.time_offset_s) == np.sign(offset_s)
    assert est.ok and est.peak_correlation > 0.99
    # Swapping the roles flips the sign.
    swapped = correlate_angular_speed(t_imu, b, tau, a)
    assert swapped.time_offset_s == pytest.approx(-offset_s, abs=0.002)


@pytest.mark.parametrize("offset_s", [0.02, -0.037])
def test_offset_from_gyro_and_poses(offset_s: float) -> None:
    motion = RotationMotion.random(11)
    imu = motion.imu(20.0, rate_hz=200.0)
    gen = np.random.default_rng(0)
    imu = ImuSamples(imu.t_ns, imu.gyro + 0.01 * gen.normal(size=imu.gyro.shape), imu.accel)
    poses = motion.lidar_poses(
        Rotation.from_euler("xyz", [90, 0, 180], degrees=True),
        time_offset_s=offset_s,
        duration_s=19.0,
        noise_deg=0.03,
        start_ns=T0_NS + 500_000_000,
    )
    est = estimate_time_offset(imu, poses)
    # Tolerance 2 ms, same sign.
    assert est.time_offset_s == pytest.approx(offset_s, abs=0.002), est.time_offset_s
    assert est.ok and est.peak_correlation > 0.9


def test_large_offset_needs_the_option() -> None:
    motion = RotationMotion.random(4)
    imu = motion.imu(30.0)
    poses = motion.lidar_poses(Rotation.identity(), 1.3, 25.0, start_ns=T0_NS + 2 * 10**9)
    narrow = estimate_time_offset(imu, poses)
    assert not narrow.ok
    wide = estimate_time_offset(imu, poses, TimeOffsetConfig(max_lag_s=3.0))
    assert wide.ok
    assert wide.time_offset_s == pytest.approx(1.3, abs=0.002)


def test_flat_angular_speed_is_refused() -> None:
    t = T0_NS + np.arange(0, 10_000_000_000, 5_000_000, dtype=np.int64)
    spin = np.tile([0.0, 0.0, 0.8], (t.size, 1))  # constant rate: |w| flat
    imu = ImuSamples(t, spin, np.zeros_like(spin))
    tau = T0_NS + np.arange(0, 9_000_000_000, 100_000_000, dtype=np.int64)
    with pytest.raises(ExcitationError, match="angular rate hardly varies"):
        correlate_angular_speed(tau, np.full(tau.size, 0.8), t, np.full(t.size, 0.8))
    w = angular_speed_from_gyro(imu, tau, 0.1)
    np.testing.assert_allclose(w[1:-1], 0.8, rtol=1e-9)


def _on_clock(poses: PoseSeries, t_ns: npt.NDArray[np.int64]) -> PoseSeries:
    return PoseSeries(
        t_ns=t_ns,
        T_map_lidar=poses.T_map_lidar,
        n_points=poses.n_points,
        n_keypoints=poses.n_keypoints,
        threshold_m=poses.threshold_m,
        deviation_m=poses.deviation_m,
        deviation_deg=poses.deviation_deg,
    )


def test_clock_shift_unix_vs_boot_time() -> None:
    motion = RotationMotion.random(9)
    boot_ns = 1_234_567_890_123  # IMU clock: ~20 min after boot
    lidar_ahead_ns = 730_000_000  # LiDAR clock (UNIX time) reads 0.73 s more than true time
    imu = motion.imu(40.0)  # stamps on the true timeline T
    imu_boot = ImuSamples(imu.t_ns - T0_NS + boot_ns, imu.gyro, imu.accel)
    poses = motion.lidar_poses(Rotation.identity(), 0.0, 35.0, start_ns=T0_NS + 2 * 10**9)
    poses_unix = _on_clock(poses, poses.t_ns + lidar_ahead_ns)
    expected = boot_ns - T0_NS - lidar_ahead_ns  # t_imu = t_lidar + shift

    shift = estimate_clock_shift(imu_boot, poses_unix)
    assert shift.method == "correlation"
    assert shift.overlap_fraction == 0.0
    # Tolerance 1 ms (the shift is rounded to whole milliseconds).
    assert abs(shift.shift_ns - expected) <= 1_000_000, (shift.shift_ns - expected) * 1e-9

    # After applying the shift, the fine estimate is ~0 and the clock shift is "none".
    aligned = _on_clock(poses_unix, poses_unix.t_ns + shift.shift_ns)
    assert estimate_clock_shift(imu_boot, aligned).method == "none"
    fine = estimate_time_offset(imu_boot, aligned)
    assert fine.time_offset_s == pytest.approx((expected - shift.shift_ns) * 1e-9, abs=0.002)


def _sinusoid_rig(offset_s: float, r_imu_lidar: Rotation) -> tuple[ImuSamples, PoseSeries]:
    """The paper's sinusoidal motion (steady yaw rate with rocking): a 400 Hz gyro with white
    noise and 10 Hz LiDAR poses ``R_map_lidar(tau) = R_W_I(tau + offset) R_imu_lidar``."""
    traj = sinusoid()
    t_imu = np.arange(0.0, 10.0, 1.0 / 400.0)
    gyro = traj.state(t_imu).angular_velocity
    gyro = gyro + 3.5e-3 * np.random.default_rng(3).normal(size=gyro.shape)
    imu = ImuSamples(T0_NS + np.rint(t_imu * 1e9).astype(np.int64), gyro, np.zeros_like(gyro))
    tau = np.arange(0.3, 9.7, 0.1)
    r_wl = traj.rotation_at(tau + offset_s) @ r_imu_lidar.as_matrix()
    r_wl = np.einsum("ij,njk->nik", r_wl[0].T, r_wl)
    k = tau.size
    poses = PoseSeries(
        T0_NS + np.rint(tau * 1e9).astype(np.int64),
        np.tile(np.eye(4), (k, 1, 1)),
        np.full(k, 1000),
        np.full(k, 500),
        np.full(k, 0.1),
        np.zeros(k),
        np.zeros(k),
    )
    poses.T_map_lidar[:, :3, :3] = r_wl
    return imu, poses


@pytest.mark.parametrize("offset_s", [0.03, -0.045])
def test_joint_offset_and_rotation_on_steady_yaw(offset_s: float) -> None:
    """With a steady yaw rate a rotation of the extrinsic mimics a time shift: correlating with
    the rotation that hand-eye finds at a zero offset lands near zero; the joint search does
    not."""
    r_true = Rotation.from_euler("xyz", [1.0, 2.0, 5.0], degrees=True)
    imu, poses = _sinusoid_rig(offset_s, r_true)
    est, rot = estimate_time_offset_joint(imu, poses)
    assert est.ok, est.reason
    assert est.time_offset_s == pytest.approx(offset_s, abs=0.003)
    assert (Rotation.from_matrix(rot).inv() * r_true).magnitude() < np.radians(0.3)
    # The rotation that best explains the rates at a zero offset is off by about a degree and
    # then explains the offset away.
    _, rot_at_zero = estimate_time_offset_joint(imu, poses, TimeOffsetConfig(max_lag_s=0.0005))
    assert (Rotation.from_matrix(rot_at_zero).inv() * r_true).magnitude() > np.radians(0.5)
    biased = estimate_time_offset_aligned(imu, poses, rot_at_zero)
    assert abs(biased.time_offset_s - offset_s) > 0.5 * abs(offset_s)
