"""Lever arm, gravity and accelerometer bias from odometry + IMU; gyro bias from odometry."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from licalib_cli.errors import ExcitationError
from licalib_cli.geometry import so3
from licalib_cli.initialization.translation import LeverArmConfig, estimate_lever_arm
from licalib_cli.spline import SO3Spline, UniformKnots

F64 = npt.NDArray[np.float64]
DURATION_S = 10.0
IMU_RATE = 400.0
GRAVITY_W = np.array([0.0, 0.0, -9.81])


def _rotvec(t: F64, axes: tuple[float, float, float]) -> F64:
    a = np.asarray(axes)
    return np.stack(
        [
            a[0] * 0.6 * np.sin(2 * np.pi * 1.3 * t),
            a[1] * 0.5 * np.sin(2 * np.pi * 0.9 * t + 1.0),
            a[2] * (0.8 * np.sin(2 * np.pi * 0.7 * t + 2.0) + 0.4 * t),
        ],
        axis=-1,
    )


def _position(t: F64) -> F64:
    return np.stack(
        [
            np.sin(2 * np.pi * 0.5 * t),
            0.5 * np.cos(2 * np.pi * 0.8 * t),
            0.3 * np.sin(2 * np.pi * 1.1 * t),
        ],
        axis=-1,
    )


def _figure8_rotvec(t: F64, axes: tuple[float, float, float]) -> F64:
    """The paper's figure-8: a yaw of 0.4 sin(t) rad about the vertical only."""
    zero = np.zeros_like(t)
    return np.stack([zero, zero, 0.4 * np.sin(t)], axis=-1)


def _figure8_position(t: F64) -> F64:
    w = np.pi / 5.0
    return np.stack([2.0 * np.cos(w * t), 0.75 * np.sin(2 * w * t), np.zeros_like(t)], axis=-1)


class Rig:
    """Analytic IMU motion ``R_W_I(t)``, ``p_W_I(t)`` and what the sensors see of it."""

    def __init__(
        self, axes: tuple[float, float, float] = (1.0, 1.0, 1.0), planar: bool = False
    ) -> None:
        self.axes = axes
        self.rotvec = _figure8_rotvec if planar else _rotvec
        self.position = _figure8_position if planar else _position
        self.t_imu = np.arange(0.0, DURATION_S, 1.0 / IMU_RATE)
        self.rot_w = so3.exp(self.rotvec(self.t_imu, axes))
        self.r0 = self.rot_w[0]

    def rotation(self, t: F64) -> F64:
        return so3.exp(self.rotvec(t, self.axes))

    def accel(self, bias: F64, noise: float, rng: np.random.Generator) -> F64:
        h = 1e-4
        t = self.t_imu
        acc_w = (self.position(t + h) - 2 * self.position(t) + self.position(t - h)) / h**2
        a_m = np.einsum("nji,nj->ni", self.rot_w, acc_w - GRAVITY_W) + bias
        return a_m + rng.normal(scale=noise, size=a_m.shape)

    def lidar_positions_G(self, t_pose: F64, lever: F64) -> F64:
        """LiDAR origin at the pose times in ``{G}`` (the IMU frame at t = 0)."""
        p_w = self.position(t_pose) + np.einsum("nij,j->ni", self.rotation(t_pose), lever)
        return (p_w - p_w[0]) @ self.r0

    def spline(self) -> tuple[UniformKnots, SO3Spline]:
        knots = UniformKnots.for_interval(0.0, float(self.t_imu[-1]), 0.02)
        rot_g = np.swapaxes(self.r0, 0, 1)[None] @ self.rot_w
        return knots, SO3Spline.from_rotations(knots, self.t_imu, rot_g)


def _solve(
    rig: Rig,
    lever: F64,
    *,
    pose_noise: float = 0.01,
    seed: int = 0,
    prior: F64 | None = None,
    outliers: int = 0,
    bias: F64 | None = None,
    cfg: LeverArmConfig | None = None,
) -> tuple[object, F64]:
    rng = np.random.default_rng(seed)
    knots, spline = rig.spline()
    bias = np.array([0.05, -0.03, 0.02]) if bias is None else bias
    a_m = rig.accel(bias, 0.01, rng)
    t_pose = np.arange(0.05, DURATION_S - 0.05, 0.1)
    p_gl = rig.lidar_positions_G(t_pose, lever) + rng.normal(
        scale=pose_noise, size=(t_pose.size, 3)
    )
    if outliers:
        idx = rng.choice(t_pose.size, outliers, replace=False)
        p_gl[idx] += rng.normal(scale=0.5, size=(outliers, 3))
    est = estimate_lever_arm(knots, spline, rig.t_imu, a_m, t_pose, p_gl, prior, cfg)
    g_true = rig.r0.T @ GRAVITY_W
    return est, g_true


@pytest.mark.parametrize("lever", [(0.3, 0.15, 0.05), (0.8, -1.0, -0.2), (-1.5, 1.2, 0.6)])
def test_known_lever_arm_is_recovered(lever: tuple[float, float, float]) -> None:
    rig = Rig()
    est, g_true = _solve(rig, np.asarray(lever))
    err = est.t_imu_lidar - np.asarray(lever)
    assert np.linalg.norm(err) < 0.01
    assert np.all(np.isfinite(est.std_m))
    assert np.all(np.abs(err) < 4 * est.std_m + 1e-3)
    cos = est.gravity_G @ g_true / (np.linalg.norm(est.gravity_G) * np.linalg.norm(g_true))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 0.5
    assert abs(np.linalg.norm(est.gravity_G) - 9.81) < 1e-9
    assert est.undetermined.shape == (0, 3)


def test_odometry_outliers_are_down_weighted() -> None:
    rig = Rig()
    lever = np.array([0.8, -1.0, -0.2])
    est, _ = _solve(rig, lever, outliers=5)
    assert np.linalg.norm(est.t_imu_lidar - lever) < 0.02


def test_single_axis_rotation_leaves_the_axis_component_at_the_prior() -> None:
    """Rotation about z only: the lever arm along z is absorbed by the position spline."""
    rig = Rig(axes=(0.0, 0.0, 1.0))
    lever = np.array([0.4, -0.3, 0.7])
    prior = np.array([0.0, 0.0, 0.25])
    est, _ = _solve(rig, lever, prior=prior)
    assert est.undetermined.shape[0] == 1
    assert abs(abs(est.undetermined[0] @ np.array([0.0, 0.0, 1.0])) - 1.0) < 1e-3
    assert est.t_imu_lidar[2] == pytest.approx(0.25, abs=1e-3)
    assert np.linalg.norm(est.t_imu_lidar[:2] - lever[:2]) < 0.01
    assert np.isinf(est.std_m[2])
    assert np.all(np.isfinite(est.std_m[:2]))


def test_larger_position_noise_gives_larger_reported_std() -> None:
    rig = Rig()
    lever = np.array([0.3, 0.15, 0.05])
    quiet, _ = _solve(rig, lever, pose_noise=0.005)
    cfg_loud = LeverArmConfig(position_sigma_m=0.05)
    rng = np.random.default_rng(1)
    knots, spline = rig.spline()
    a_m = rig.accel(np.zeros(3), 0.01, rng)
    t_pose = np.arange(0.05, DURATION_S - 0.05, 0.1)
    p_gl = rig.lidar_positions_G(t_pose, lever) + rng.normal(scale=0.05, size=(t_pose.size, 3))
    loud = estimate_lever_arm(knots, spline, rig.t_imu, a_m, t_pose, p_gl, cfg=cfg_loud)
    assert np.all(loud.std_m > quiet.std_m)
    assert np.linalg.norm(loud.t_imu_lidar - lever) < 6 * np.linalg.norm(loud.std_m)


def _angle_deg(a: F64, b: F64) -> float:
    cos = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_planar_motion_keeps_the_lever_arm_near_its_prior_not_its_mirror_image() -> None:
    """The figure-8's yaw is one sinusoid, so the horizontal lever arm and the horizontal
    accelerometer bias predict the same accelerations (b = -omega^2 t): without a prior on the
    bias the least squares lands on the lever arm's mirror image; with it, near the prior."""
    rig = Rig(axes=(0.0, 0.0, 1.0), planar=True)
    lever = np.array([0.3, 0.15, 0.05])
    est, g_true = _solve(rig, lever, pose_noise=0.005, bias=np.zeros(3))
    assert np.linalg.norm(est.t_imu_lidar[:2]) < 0.05
    assert np.linalg.norm(est.accel_bias) < 0.5
    assert _angle_deg(est.gravity_G, g_true) < 3.0
    free, _ = _solve(
        rig, lever, pose_noise=0.005, bias=np.zeros(3), cfg=LeverArmConfig(accel_bias_sigma=1e6)
    )
    assert np.linalg.norm(free.t_imu_lidar[:2] + lever[:2]) < 0.05  # the mirror image
    assert _angle_deg(free.gravity_G, g_true) > _angle_deg(est.gravity_G, g_true)


def test_a_bias_far_beyond_its_prior_means_the_sensors_disagree() -> None:
    """An accelerometer that reads 8 m/s^2 more than gravity along the vertical: no lever arm,
    gravity or bias is returned (the caller keeps its prior)."""
    with pytest.raises(ExcitationError, match="odometry and the accelerometer disagree"):
        _solve(Rig(axes=(0.0, 0.0, 1.0), planar=True), np.zeros(3), bias=np.array([0, 0, 8.0]))
    # the same bias within the prior's reach is estimated
    est, _ = _solve(Rig(), np.zeros(3), bias=np.array([0.0, 0.0, 2.0]))
    assert est.accel_bias[2] == pytest.approx(2.0, abs=0.05)
