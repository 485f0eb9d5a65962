"""Each named effect, hidden alone at 3 times its reference size, shows in the simulated
measurements with the size and sign ``truth.yaml`` records, and changes nothing else."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.models.imu import imu_measure
from licalib_cli.models.intrinsics import ImuIntrinsics
from licalib_cli.simulation import (
    EFFECT_SIZES,
    Effect,
    SimulationSpec,
    build_setup,
    build_truth,
    generate_imu,
    generate_scans,
)
from licalib_cli.simulation.spec import STANDARD_GRAVITY
from licalib_cli.truth import InjectedEffect, Truth

SCALE = 3.0


def _spec(effect: Effect, **kw: object) -> SimulationSpec:
    base: dict[str, object] = {
        "duration_s": 1.0,
        "seed": 3,
        "intrinsics": "none",
        "noise_free": True,
        "effects": (effect,),
        "effect_scale": SCALE,
        "azimuth_resolution_deg": 1.0,
    }
    base.update(kw)
    return SimulationSpec(**base)  # type: ignore[arg-type]


def _injected(spec: SimulationSpec) -> InjectedEffect:
    setup = build_setup(spec)
    truth = build_truth(spec, setup)
    assert truth.simulation is not None
    again = Truth.from_dict(truth.to_dict())  # the YAML round trip keeps the section
    assert again.simulation is not None and again.simulation.effects == truth.simulation.effects
    (injected,) = truth.simulation.effects
    assert injected.name == spec.effects[0].value and injected.scale == SCALE
    return injected


def _plausible_size(values: np.ndarray, size: float) -> None:
    """Values drawn as N(0, size): not all tiny, none beyond 4.5 sigma."""
    v = np.abs(np.asarray(values, dtype=float))
    assert v.max() > 0.2 * size and v.max() < 4.5 * size


def _regress(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``A`` (3, k) of ``y ~ A x`` by least squares; x (N, k), y (N, 3)."""
    return np.linalg.lstsq(x, y, rcond=None)[0].T


@pytest.mark.parametrize(
    "effect",
    [
        Effect.GYRO_SCALE,
        Effect.GYRO_MISALIGNMENT,
        Effect.GYRO_ROTATION,
        Effect.ACCEL_SCALE,
        Effect.ACCEL_MISALIGNMENT,
        Effect.G_SENSITIVITY,
    ],
)
def test_imu_intrinsic_effects_show_in_the_readings(effect: Effect) -> None:
    spec = _spec(effect, scenario="shake")
    injected = _injected(spec)
    size = SCALE * EFFECT_SIZES[effect].size
    assert injected.size == pytest.approx(size)
    imu, truth = generate_imu(spec)
    # the readings against the true rate / specific force: gyro = A omega + G a, accel = B a
    x = np.hstack([truth.omega, truth.specific_force])
    a_gyro = _regress(x, imu.gyro)
    a_acc = _regress(truth.specific_force, imu.accel)
    gyro_lin, acc_lin = a_gyro[:, :3] - np.eye(3), a_acc - np.eye(3)
    g_sens = a_gyro[:, 3:]
    v = np.asarray(injected.values)
    _plausible_size(v, size)
    if effect is Effect.GYRO_SCALE:
        np.testing.assert_allclose(np.diag(gyro_lin), v, atol=1e-9)
    elif effect is Effect.ACCEL_SCALE:
        np.testing.assert_allclose(np.diag(acc_lin), v, atol=1e-9)
    elif effect in (Effect.GYRO_MISALIGNMENT, Effect.ACCEL_MISALIGNMENT):
        lin = gyro_lin if effect is Effect.GYRO_MISALIGNMENT else acc_lin
        # M = [[1, m0, m1], [0, 1, m2], [0, 0, 1]]: the angles above the diagonal, signed
        upper = lin[np.triu_indices(3, 1)]
        np.testing.assert_allclose(upper, np.radians(v), rtol=1e-9, atol=1e-12)
        assert np.allclose(np.tril(lin), 0.0, atol=1e-12)
    elif effect is Effect.GYRO_ROTATION:
        # gyro = R_wI omega: the antisymmetric part is -hat(rotation vector) of R_wI
        w = 0.5 * np.array(
            [
                gyro_lin[2, 1] - gyro_lin[1, 2],
                gyro_lin[0, 2] - gyro_lin[2, 0],
                gyro_lin[1, 0] - gyro_lin[0, 1],
            ]
        )
        np.testing.assert_allclose(w, np.radians(v), rtol=2e-3, atol=1e-7)
    else:
        a_w = np.radians(v.reshape(3, 3)) / STANDARD_GRAVITY
        np.testing.assert_allclose(g_sens, a_w, rtol=1e-6, atol=1e-12)
    blocks = {"gyro": gyro_lin, "accel": acc_lin, "g": g_sens}
    changed = "g" if effect is Effect.G_SENSITIVITY else effect.value.split("_")[0]
    for name, block in blocks.items():
        if name != changed:  # nothing else moves
            assert np.abs(block).max() < 1e-9, name


@pytest.mark.parametrize("effect", [Effect.GYRO_BIAS_WALK, Effect.ACCEL_BIAS_WALK])
def test_each_bias_walk_drives_only_its_own_sensor(effect: Effect) -> None:
    spec = _spec(effect, duration_s=10.0, noise_free=False)
    plain = spec.with_(effects=())
    imu, truth = generate_imu(spec)
    imu0, _ = generate_imu(plain)  # same white noise, MTi-100 walk
    gyro = effect is Effect.GYRO_BIAS_WALK
    own, other = (imu.gyro, imu.accel) if gyro else (imu.accel, imu.gyro)
    own0, other0 = (imu0.gyro, imu0.accel) if gyro else (imu0.accel, imu0.gyro)
    np.testing.assert_array_equal(other, other0)
    # the walk is 10 x effect_scale times the MTi-100 walk of the same stream
    walk = own - own0
    multiplier = SCALE * EFFECT_SIZES[effect].size
    density = spec.gyro_bias_walk_density if gyro else spec.accel_bias_walk_density
    step = np.diff(walk, axis=0) * (multiplier / (multiplier - 1.0))
    assert np.std(step) == pytest.approx(multiplier * density / np.sqrt(400.0), rel=0.03)
    # the recorded slope is the least-squares slope of the bias actually added
    injected = _injected(spec)
    bias = truth.gyro_bias if gyro else truth.accel_bias
    t = truth.t_true_s - truth.t_true_s.mean()
    slope = t @ (bias - bias.mean(axis=0)) / (t @ t)
    np.testing.assert_allclose(injected.values, slope, rtol=1e-6)
    # the readings minus the ideal ones drift the same way, within the white noise's slope
    setup = build_setup(spec)
    ideal = imu_measure(setup.imu_intrinsics, truth.omega, truth.specific_force)[0 if gyro else 1]
    error = own - ideal
    measured = t @ (error - error.mean(axis=0)) / (t @ t)
    sigma = truth.gyro_noise_sigma if gyro else truth.accel_noise_sigma
    assert np.all(np.abs(measured - slope) < 4.0 * sigma / np.sqrt(t @ t))


def test_clock_drift_by_name_and_scale() -> None:
    spec = _spec(Effect.IMU_CLOCK_DRIFT, duration_s=2.0)
    injected = _injected(spec)
    assert injected.values == (SCALE * 50.0,)
    imu, truth = generate_imu(spec)
    rel = (imu.t_ns - spec.base_time_ns).astype(float) * 1e-9
    np.testing.assert_allclose(rel, truth.t_true_s * (1 + SCALE * 50e-6), atol=1e-12)


_LIDAR = [
    Effect.LIDAR_RANGE_OFFSET,
    Effect.LIDAR_RANGE_SCALE,
    Effect.LIDAR_ELEVATION,
    Effect.LIDAR_AZIMUTH,
    Effect.LIDAR_VERTICAL_OFFSET,
    Effect.LIDAR_HORIZONTAL_OFFSET,
]


@pytest.mark.parametrize("lidar", ["vlp16", "os1-64"])
@pytest.mark.parametrize("effect", _LIDAR)
def test_lidar_intrinsic_effects_show_in_the_points(effect: Effect, lidar: str) -> None:
    spec = _spec(effect, duration_s=0.2, lidar=lidar, azimuth_resolution_deg=2.0)
    setup = build_setup(spec)
    injected = _injected(spec)
    v = np.asarray(injected.values)
    _plausible_size(v[1:], SCALE * EFFECT_SIZES[effect].size)
    scan = next(generate_scans(spec, setup, [1]))
    tr = scan.truth
    pts = scan.points.reshape(-1)
    ok = tr.valid
    published = np.stack([pts["x"], pts["y"], pts["z"]], -1).astype(np.float64)[ok]
    beam, theta, rho, rho_bar = tr.beam[ok], tr.theta[ok], tr.rho[ok], tr.rho_bar[ok]
    r_wl, p_wl = setup.lidar_pose_at(tr.t_true_s[ok])
    true_l = np.einsum("nji,nj->ni", r_wl, tr.hit_world[ok] - p_wl)  # hit in {L}
    if effect is Effect.LIDAR_RANGE_OFFSET:
        per_point = rho_bar - rho
    elif effect is Effect.LIDAR_RANGE_SCALE:
        per_point = rho_bar / rho - 1.0
    elif effect is Effect.LIDAR_ELEVATION:
        phi_true = np.arcsin(true_l[:, 2] / np.linalg.norm(true_l, axis=1))
        phi_pub = np.arcsin(published[:, 2] / np.linalg.norm(published, axis=1))
        per_point = np.degrees(phi_true - phi_pub)
    elif effect is Effect.LIDAR_AZIMUTH:
        d = np.arctan2(true_l[:, 1], true_l[:, 0]) - np.arctan2(published[:, 1], published[:, 0])
        per_point = np.degrees((d + np.pi) % (2 * np.pi) - np.pi)
    elif effect is Effect.LIDAR_VERTICAL_OFFSET:
        per_point = true_l[:, 2] - published[:, 2]
    else:
        side = np.stack([np.sin(theta), -np.cos(theta)], -1)
        per_point = np.einsum("ni,ni->n", true_l[:, :2] - published[:, :2], side)
    for b in np.unique(beam):
        got = per_point[beam == b]
        # float32 points: ~1e-6 relative; the angles are exact up to that
        assert np.median(got) == pytest.approx(v[b], abs=2e-5 + 1e-3 * abs(v[b]))
    assert injected.values[0] == 0.0 or effect in (
        Effect.LIDAR_RANGE_OFFSET,
        Effect.LIDAR_RANGE_SCALE,
    )


@pytest.mark.parametrize("lidar", ["vlp16", "os1-64"])
def test_point_time_error_stretches_the_published_times(lidar: str) -> None:
    spec = _spec(Effect.LIDAR_POINT_TIME, duration_s=0.3, lidar=lidar, azimuth_resolution_deg=2.0)
    injected = _injected(spec)
    k = SCALE * 0.01
    assert injected.values == (pytest.approx(k),)
    setup = build_setup(spec)
    scan = next(generate_scans(spec, setup, [2]))
    pts = scan.points.reshape(-1)
    rel = pts["time"].astype(np.float64) if lidar == "vlp16" else pts["t"] * 1e-9
    ok = scan.truth.valid  # aligned with the cloud's points (organised: all of them)
    t_pub = ((scan.stamp_ns - spec.base_time_ns) * 1e-9 + rel)[ok]
    t_true = scan.truth.t_true_s[ok]
    first = scan.truth.t_true_s.min()
    # a point published at tau was measured at tau - k (tau - sweep start)
    np.testing.assert_allclose(t_pub - k * (t_pub - first), t_true, atol=2e-8)
    np.testing.assert_allclose(scan.truth.t_published_s[ok], t_pub, atol=2e-8)
    # the header stamp stays the true first firing
    assert (scan.stamp_ns - spec.base_time_ns) * 1e-9 == pytest.approx(first, abs=1e-9)


def test_naming_one_effect_changes_no_other_draw() -> None:
    plain = SimulationSpec(duration_s=0.2, seed=9)
    named = plain.with_(effects=("gyro_scale", "lidar_elevation"), effect_scale=2.0)
    a, b = build_setup(plain), build_setup(named)
    for name in ("gyro_misalignment", "accel_scale", "gyro_rotation", "gyro_bias"):
        np.testing.assert_array_equal(
            getattr(a.imu_intrinsics, name), getattr(b.imu_intrinsics, name)
        )
    np.testing.assert_array_equal(a.lidar_intrinsics.range_offset, b.lidar_intrinsics.range_offset)
    assert not np.array_equal(a.imu_intrinsics.gyro_scale, b.imu_intrinsics.gyro_scale)
    np.testing.assert_array_equal(a.extrinsic.rotation, b.extrinsic.rotation)
    assert isinstance(b.imu_intrinsics, ImuIntrinsics)


def test_together_every_effect_is_recorded_once() -> None:
    spec = SimulationSpec(
        duration_s=0.3, intrinsics="none", effects=tuple(Effect), effect_scale=2.0
    )
    truth = build_truth(spec, build_setup(spec))
    assert truth.simulation is not None
    assert [e.name for e in truth.simulation.effects] == [e.value for e in Effect]
    assert all(e.scale == 2.0 for e in truth.simulation.effects)
