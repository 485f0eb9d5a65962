"""Closed-form trajectories: derivatives, the paper's formulas, mountings, free space."""

from __future__ import annotations

import re

import numpy as np
import pytest

from licalib_cli.simulation import (
    Mounting,
    Scenario,
    Signal,
    SimulationSpec,
    build_setup,
    default_world,
    figure8,
    sinusoid,
)
from licalib_cli.simulation.scenarios import MOUNTING_VERTICAL
from licalib_cli.simulation.trajectories import euler_zyx_matrix, rot_x, rot_y, rot_z


def _vee_skew(m: np.ndarray) -> np.ndarray:
    return 0.5 * np.stack(
        [m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1
    )


def test_signal_derivatives_match_finite_differences() -> None:
    # Windowed and plain terms together; the window is [1, 3] s and t spans its edges.
    sig = Signal.sines([0.7, 0.3], [2.0, 9.0], [0.1, 1.0], offset=1.0, slope=0.2) + Signal.sines(
        [0.5], [7.0], [0.3], window=[1.0, 3.0]
    )
    t = np.linspace(0.0, 4.0, 401)
    h = 1e-5
    f, d1, d2 = sig.eval(t)
    fp, fm = sig.eval(t + h)[0], sig.eval(t - h)[0]
    assert np.max(np.abs((fp - fm) / (2 * h) - d1)) < 1e-6
    d1p, d1m = sig.eval(t + h)[1], sig.eval(t - h)[1]
    assert np.max(np.abs((d1p - d1m) / (2 * h) - d2)) < 1e-4
    # Outside the window only the plain terms remain.
    plain = Signal.sines([0.7, 0.3], [2.0, 9.0], [0.1, 1.0], offset=1.0, slope=0.2)
    outside = (t < 1.0) | (t > 3.0)
    assert np.allclose(f[outside], plain.eval(t[outside])[0], atol=1e-15)


def test_signal_value_is_evals_first_to_the_bit() -> None:
    """Poses are evaluated per point with the value alone: the bags it writes must be those
    of the value with its derivatives (windowed, plain, and windows the times miss)."""
    sig = Signal.sines([0.7, 0.3], [2.0, 9.0], [0.1, 1.0], offset=1.0, slope=0.2) + Signal.sines(
        [0.5, 0.2], [7.0, 3.0], [0.3, 0.0], window=[[1.0, 3.0], [5.0, 6.0]]
    )
    for t in (np.linspace(0.0, 4.0, 401), np.linspace(3.5, 4.5, 7), np.empty(0)):
        assert np.array_equal(sig.value(t), sig.eval(t)[0])
    only_windowed = Signal.sines([0.5], [7.0], [0.3], window=[1.0, 3.0])
    assert np.array_equal(only_windowed.value([4.0, 5.0]), [0.0, 0.0])


def test_sinusoid_is_the_papers_equation() -> None:
    t = np.linspace(0.0, 10.0, 57)
    st = sinusoid().state(t)
    w = np.pi / 5
    expected = np.stack(
        [2 * np.cos(w * t) + 5, 1.5 * np.sin(w * t) + 5, 0.8 * np.cos(4 * w * t) + 5], -1
    )
    assert np.allclose(st.position, expected, atol=1e-12)
    rot = rot_z(0.7 * t) @ rot_y(0.6 * np.sin(t)) @ rot_x(0.4 * np.cos(t))
    assert np.allclose(st.rotation, rot, atol=1e-12)
    assert np.allclose(euler_zyx_matrix(0.4 * np.cos(t), 0.6 * np.sin(t), 0.7 * t), rot, atol=1e-12)


@pytest.mark.parametrize("mounting", list(Mounting))
def test_figure8_vertical_in_imu_frame(mounting: Mounting) -> None:
    t = np.linspace(0.0, 10.0, 41)
    st = figure8(mounting).state(t)
    w = np.pi / 5
    assert np.allclose(st.position[:, 0], 2 * np.cos(w * t), atol=1e-12)
    assert np.allclose(st.position[:, 1], 1.5 * np.sin(w * t) * np.cos(w * t) + 5, atol=1e-12)
    assert np.allclose(st.position[:, 2], 2.0)
    v = MOUNTING_VERTICAL[mounting] / np.linalg.norm(MOUNTING_VERTICAL[mounting])
    up_in_imu = np.einsum("nji,j->ni", st.rotation, [0.0, 0.0, 1.0])
    assert np.allclose(up_in_imu, v, atol=1e-12)
    # Planar motion: the rotation axis is the vertical, so omega_I is parallel to v.
    assert np.allclose(np.cross(st.angular_velocity, v), 0.0, atol=1e-12)


@pytest.mark.parametrize("scenario", list(Scenario))
def test_angular_velocity_and_velocity_match_finite_differences(scenario: Scenario) -> None:
    setup = build_setup(SimulationSpec(scenario=scenario, seed=3, mounting=Mounting.C))
    traj = setup.trajectory
    t = np.linspace(0.5, min(20.0, setup.spec.resolved_duration_s - 0.5), 300)
    h = 1e-6
    st = traj.state(t)
    r_p, r_m = traj.rotation_at(t + h), traj.rotation_at(t - h)
    omega_fd = _vee_skew(np.einsum("nji,njk->nik", st.rotation, (r_p - r_m) / (2 * h)))
    assert np.max(np.abs(omega_fd - st.angular_velocity)) < 1e-6  # rad/s
    v_fd = (traj.position_at(t + h) - traj.position_at(t - h)) / (2 * h)
    assert np.max(np.abs(v_fd - st.velocity)) < 1e-6  # m/s
    a_fd = (traj.state(t + 1e-4).velocity - traj.state(t - 1e-4).velocity) / 2e-4
    assert np.max(np.abs(a_fd - st.acceleration)) < 1e-5  # m/s^2


@pytest.mark.parametrize("scenario", list(Scenario))
def test_sensors_stay_in_free_space(scenario: Scenario) -> None:
    """IMU and LiDAR keep at least 0.5 m from every surface (random extrinsic: |t| <= 0.5 m)."""
    world = default_world()
    for seed in range(3):
        spec = SimulationSpec(scenario=scenario, seed=seed, random_extrinsic=True)
        setup = build_setup(spec)
        t = np.arange(0.0, spec.resolved_duration_s, 0.02)
        _, p_l = setup.lidar_pose_at(t)
        assert world.clearance(setup.trajectory.position_at(t)).min() > 0.5
        assert world.clearance(p_l).min() > 0.5


def test_walk_has_bursts_of_shaking() -> None:
    setup = build_setup(SimulationSpec(scenario=Scenario.WALK, seed=5))
    bursts = setup.motion.bursts_s
    assert setup.spec.resolved_duration_s == 120.0
    assert bursts.shape[0] >= 3
    assert np.all(bursts[:, 1] - bursts[:, 0] >= 3.0) and np.all(bursts[:, 1] <= 119.0)
    t = np.arange(0.0, 120.0, 0.01)
    w = np.linalg.norm(setup.trajectory.state(t).angular_velocity, axis=1)
    in_burst = np.zeros_like(t, dtype=bool)
    for t0, t1 in bursts:
        in_burst |= (t > t0) & (t < t1)
    # Calm walking turns slowly; bursts shake at well over 1 rad/s.
    assert np.percentile(w[~in_burst], 99) < 0.5
    for t0, t1 in bursts:
        sel = (t > t0) & (t < t1)
        assert w[sel].max() > 1.0


def _gravity_direction_rms_deg(setup: object, duration_s: float) -> float:
    """RMS angle of gravity's direction in the IMU frame from its mean direction, deg."""
    t = np.linspace(0.0, duration_s, 2001)
    up = setup.trajectory.state(t).rotation[:, 2, :]  # type: ignore[attr-defined]
    mean = up.mean(axis=0) / np.linalg.norm(up.mean(axis=0))
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(up @ mean, -1.0, 1.0)) ** 2))))


def test_tilted_shake_turns_gravity_tens_of_degrees_and_keeps_the_shaking() -> None:
    plain = build_setup(SimulationSpec(scenario=Scenario.SHAKE, seed=11))
    tilted = build_setup(SimulationSpec(scenario=Scenario.SHAKE, seed=11, tilt_deg=30.0))
    t = np.linspace(0.0, 10.0, 1001)
    # The tilt is drawn after the shaking: position and yaw are those of the plain shake.
    assert np.array_equal(plain.trajectory.position_at(t), tilted.trajectory.position_at(t))
    assert np.array_equal(
        plain.trajectory.euler[2].eval(t)[0], tilted.trajectory.euler[2].eval(t)[0]
    )
    assert _gravity_direction_rms_deg(plain, 10.0) < 15.0
    assert _gravity_direction_rms_deg(tilted, 10.0) > 25.0
    assert tilted.spec.tilt_deg == 30.0
    # At the largest tilt the sensors still keep clear of the room (as the other scenarios).
    world = default_world()
    for seed in range(3):
        setup = build_setup(
            SimulationSpec(scenario=Scenario.SHAKE, seed=seed, random_extrinsic=True, tilt_deg=60)
        )
        assert world.clearance(setup.lidar_pose_at(t)[1]).min() > 0.5


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"scenario": Scenario.SINUSOID, "tilt_deg": 20.0}, "pass --scenario shake"),
        ({"scenario": Scenario.SHAKE, "tilt_deg": 75.0}, "must be in [0, 60]"),
        ({"scenario": Scenario.SHAKE, "tilt_deg": -5.0}, "must be in [0, 60]"),
        ({"scenario": Scenario.SHAKE, "tilt_deg": float("nan")}, "must be in [0, 60]"),
    ],
)
def test_tilt_is_refused_off_the_shake_and_out_of_range(kwargs: dict, words: str) -> None:
    from licalib_cli.errors import ConfigError

    with pytest.raises(ConfigError, match=re.escape(words)):
        SimulationSpec(**kwargs)
