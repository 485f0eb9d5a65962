"""Residual blocks: every analytic Jacobian (every parameter block it touches) equals a central
finite difference through the block's retraction for random states, entry by entry (relative
error < 1e-6 above the floor of :mod:`fd_check`)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest
from fd_check import STEP as EPS
from fd_check import assert_jacobian

from licalib_cli.geometry.so3 import quat_exp
from licalib_cli.residuals import (
    ACCEL_BIAS,
    ACCEL_MISALIGNMENT,
    ACCEL_SCALE,
    EXT_ROTATION,
    EXT_TRANSLATION,
    GRAVITY,
    GYRO_BIAS,
    GYRO_G_SENSITIVITY,
    GYRO_MISALIGNMENT,
    GYRO_ROTATION,
    GYRO_SCALE,
    LIDAR_INTRINSICS,
    TIME_OFFSET,
    TRAJ_R3,
    TRAJ_SO3,
    AccelResidual,
    GaussianPrior,
    GyroResidual,
    PointToPlaneResidual,
)
from licalib_cli.solver import DenseJacobian, ResidualEval, dense_to_coo, retract
from licalib_cli.spline import UniformKnots

MANIFOLD = {TRAJ_SO3: "so3", EXT_ROTATION: "so3", GYRO_ROTATION: "so3", GRAVITY: "s2"}
TANGENT = {"so3": 3, "s2": 2}

KNOTS = UniformKnots(0.0, 0.1, 14)  # valid on [0, 1.1] s


def _random_params(rng: np.random.Generator, beams: int = 3) -> dict[str, np.ndarray]:
    n = KNOTS.num_control_points
    return {
        TRAJ_SO3: quat_exp(np.cumsum(0.25 * rng.standard_normal((n, 3)), axis=0)),
        TRAJ_R3: np.cumsum(0.3 * rng.standard_normal((n, 3)), axis=0),
        GYRO_BIAS: 0.01 * rng.standard_normal(3),
        ACCEL_BIAS: 0.1 * rng.standard_normal(3),
        GRAVITY: 9.81 * np.array([0.1, -0.2, -0.97]) / np.linalg.norm([0.1, -0.2, -0.97]),
        EXT_ROTATION: quat_exp(rng.standard_normal(3)),
        EXT_TRANSLATION: 0.2 * rng.standard_normal(3),
        TIME_OFFSET: np.array([0.004]),
        GYRO_SCALE: 1.0 + 0.05 * rng.standard_normal(3),
        GYRO_MISALIGNMENT: 0.02 * rng.standard_normal(3),
        GYRO_ROTATION: quat_exp(0.05 * rng.standard_normal(3)),
        ACCEL_SCALE: 1.0 + 0.05 * rng.standard_normal(3),
        ACCEL_MISALIGNMENT: 0.02 * rng.standard_normal(3),
        GYRO_G_SENSITIVITY: 1e-3 * rng.standard_normal(9),
        LIDAR_INTRINSICS: np.column_stack(
            [
                1e-3 * rng.standard_normal(beams),
                1e-3 * rng.standard_normal(beams),
                0.01 * rng.standard_normal(beams),
                0.01 * rng.standard_normal(beams),
                1.0 + 1e-3 * rng.standard_normal(beams),
                0.02 * rng.standard_normal(beams),
            ]
        ),
    }


def _analytic(ev: ResidualEval, block: str, size: int) -> np.ndarray:
    n, m = ev.residuals.shape
    out = np.zeros((n * m, size))
    for jac in ev.jacobians:
        if jac.block == block:
            assert isinstance(jac, DenseJacobian)
            rows, cols, vals = dense_to_coo(jac.values, jac.elements)
            np.add.at(out, (rows, cols), vals)
    return out


def _numeric(residual: object, params: Mapping[str, np.ndarray], block: str) -> np.ndarray:
    manifold = MANIFOLD.get(block, "euclidean")
    x = np.asarray(params[block], dtype=np.float64)
    amb = (
        4
        if manifold == "so3"
        else (3 if manifold == "s2" else (x.shape[-1] if x.ndim == 2 else x.size))
    )
    elements = x.reshape(-1, amb)
    tdim = TANGENT.get(manifold, amb)
    size = elements.shape[0] * tdim
    cols = []
    for j in range(size):
        delta = np.zeros(size)
        delta[j] = EPS
        r = []
        for sgn in (1.0, -1.0):
            xp = retract(manifold, elements, (sgn * delta).reshape(-1, tdim)).reshape(x.shape)
            p = dict(params)
            p[block] = xp
            r.append(residual.evaluate(p, jacobians=False).residuals.reshape(-1))  # type: ignore[attr-defined]
        cols.append((r[0] - r[1]) / (2 * EPS))
    return np.stack(cols, axis=1)


def _check_all(
    residual: object, params: Mapping[str, np.ndarray], blocks: list[str], term_scale: float
) -> None:
    """Entry-wise check of every block's Jacobian.

    ``term_scale``: magnitude of the whitened terms the residuals are computed from (prediction
    and reading over sigma), which sets the round-off of the differences.
    """
    ev = residual.evaluate(params, jacobians=True)  # type: ignore[attr-defined]
    ev0 = residual.evaluate(params, jacobians=False)  # type: ignore[attr-defined]
    np.testing.assert_array_equal(ev.residuals, ev0.residuals)
    assert ev0.jacobians == ()
    touched = {j.block for j in ev.jacobians}
    assert touched == set(blocks), touched ^ set(blocks)
    scale = max(float(np.abs(ev.residuals).max()), term_scale)
    for block in blocks:
        numeric = _numeric(residual, params, block)
        analytic = _analytic(ev, block, numeric.shape[1])
        assert_jacobian(analytic, numeric, scale, what=block)


@pytest.mark.parametrize("seed", [0, 1])
def test_gyro_residual_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    params = _random_params(rng)
    del params[GYRO_G_SENSITIVITY]
    t = rng.uniform(0.0, KNOTS.t_end_s, 25)
    res = GyroResidual(KNOTS, t, rng.standard_normal((25, 3)), np.array([0.5, 1.0, 2.0]))
    blocks = [TRAJ_SO3, GYRO_BIAS, GYRO_SCALE, GYRO_MISALIGNMENT, GYRO_ROTATION]
    _check_all(res, params, blocks, float(np.abs(res.gyro * res.inv_sigma).max()))


GYRO_G_BLOCKS = [
    TRAJ_SO3,
    TRAJ_R3,
    GRAVITY,
    GYRO_BIAS,
    GYRO_SCALE,
    GYRO_MISALIGNMENT,
    GYRO_ROTATION,
    GYRO_G_SENSITIVITY,
]
"""The blocks a gyro residual with g-sensitivity touches."""


def test_gyro_residual_with_g_sensitivity_jacobians() -> None:
    rng = np.random.default_rng(3)
    params = _random_params(rng)
    t = rng.uniform(0.0, KNOTS.t_end_s, 25)
    res = GyroResidual(KNOTS, t, rng.standard_normal((25, 3)), 0.7, g_sensitivity=True)
    _check_all(res, params, GYRO_G_BLOCKS, float(np.abs(res.gyro * res.inv_sigma).max()))


@pytest.mark.parametrize("seed", [0, 1])
def test_accel_residual_jacobians(seed: int) -> None:
    rng = np.random.default_rng(10 + seed)
    params = _random_params(rng)
    t = rng.uniform(0.0, KNOTS.t_end_s, 25)
    res = AccelResidual(KNOTS, t, rng.standard_normal((25, 3)) * 9.0, np.array([0.3, 0.5, 1.0]))
    _check_all(
        res,
        params,
        [TRAJ_SO3, TRAJ_R3, GRAVITY, ACCEL_BIAS, ACCEL_SCALE, ACCEL_MISALIGNMENT],
        float(np.abs(res.accel * res.inv_sigma).max()),
    )


def _points(rng: np.random.Generator, n: int, beams: int = 3) -> dict[str, np.ndarray]:
    normal = rng.standard_normal((n, 3))
    return {
        "t": rng.uniform(0.0, KNOTS.t_end_s - 0.01, n),
        "beam": rng.integers(0, beams, n),
        "rho": rng.uniform(2.0, 30.0, n),
        "theta": rng.uniform(-np.pi, np.pi, n),
        "normal": normal / np.linalg.norm(normal, axis=1, keepdims=True),
        "offset": rng.standard_normal(n) * 3.0,
        "sigma": rng.uniform(0.5, 2.0, n),
    }


@pytest.mark.parametrize("seed", [0, 1])
def test_point_to_plane_residual_jacobians(seed: int) -> None:
    rng = np.random.default_rng(20 + seed)
    params = _random_params(rng)
    pts = _points(rng, 30)
    res = PointToPlaneResidual(
        KNOTS,
        pts["t"],
        pts["beam"],
        pts["rho"],
        pts["theta"],
        pts["normal"],
        pts["offset"],
        pts["sigma"],
        np.deg2rad([-10.0, 0.0, 10.0]),
        intrinsics_at_predicted_range=False,
        motion_at_predicted_range=False,
        whitening_range_scale=params[LIDAR_INTRINSICS][:, 4] + 0.01,
    )
    # the distance is a difference of terms of the size of the range and the plane offset
    terms = (pts["rho"].max() + np.abs(pts["offset"]).max()) / pts["sigma"].min()
    _check_all(
        res,
        params,
        [TRAJ_SO3, TRAJ_R3, EXT_ROTATION, EXT_TRANSLATION, TIME_OFFSET, LIDAR_INTRINSICS],
        float(terms),
    )
    # distances are the unwhitened residuals; the whitening is in raw-range units, with the
    # block's range scales whatever the state's
    d = res.distances(params)
    scale = params[LIDAR_INTRINSICS][pts["beam"], 4] + 0.01
    np.testing.assert_allclose(
        d / (pts["sigma"] * scale), res.evaluate(params, False).residuals[:, 0]
    )
    other = dict(params)
    other[LIDAR_INTRINSICS] = params[LIDAR_INTRINSICS] * [1, 1, 1, 1, 1.1, 1]
    np.testing.assert_allclose(
        res.distances(other) / (pts["sigma"] * scale), res.evaluate(other, False).residuals[:, 0]
    )


def test_point_to_plane_residual_is_invariant_to_the_scale_of_the_world() -> None:
    """The range noise is the raw range's: when the world (trajectory, planes) and every length
    of the model (lever arm, range scales and offsets, beam offsets) scale together the raw
    measurements are unchanged, and so must the residuals be (in metres they would shrink with
    the world, and a fit with the map free would shrink it)."""
    rng = np.random.default_rng(31)
    params = _random_params(rng)
    pts = _points(rng, 40)

    def residuals(k: float) -> np.ndarray:
        scaled = dict(params)
        scaled[TRAJ_R3] = k * params[TRAJ_R3]
        scaled[EXT_TRANSLATION] = k * params[EXT_TRANSLATION]
        intr = params[LIDAR_INTRINSICS].copy()
        intr[:, 2:] *= k  # V, H, s, drho
        scaled[LIDAR_INTRINSICS] = intr
        res = PointToPlaneResidual(
            KNOTS,
            pts["t"],
            pts["beam"],
            pts["rho"],
            pts["theta"],
            pts["normal"],
            k * pts["offset"],
            pts["sigma"],
            np.deg2rad([-10.0, 0.0, 10.0]),
            whitening_range_scale=intr[:, 4],  # the block of a round that starts there
        )
        return res.evaluate(scaled, jacobians=False).residuals[:, 0]

    base = residuals(1.0)
    assert np.abs(base).max() > 1.0
    np.testing.assert_allclose(residuals(0.97), base, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(residuals(1.05), base, rtol=1e-9, atol=1e-9)


def _intrinsics_jacobian(res: PointToPlaneResidual, params: Mapping[str, np.ndarray]) -> np.ndarray:
    ev = res.evaluate(params, jacobians=True)
    return _analytic(ev, LIDAR_INTRINSICS, params[LIDAR_INTRINSICS].size)


def _noisy_block(
    pts: dict[str, np.ndarray], rho: np.ndarray, offset: np.ndarray, **flags: bool
) -> PointToPlaneResidual:
    """The block of ``pts`` with ranges ``rho`` and plane offsets ``offset`` (2 cm of noise,
    three beams), ``flags`` the ``*_at_predicted_range`` choices."""
    return PointToPlaneResidual(
        KNOTS,
        pts["t"],
        pts["beam"],
        rho,
        pts["theta"],
        pts["normal"],
        offset,
        0.02,
        np.deg2rad([-10.0, 0.0, 10.0]),
        **flags,
    )


def test_point_to_plane_intrinsics_derivatives_at_the_predicted_range() -> None:
    """With range noise, the intrinsics' derivatives are those of the noise-free point (where
    the ray meets its plane); on the plane they are the exact derivatives."""
    rng = np.random.default_rng(40)
    params = _random_params(rng)
    pts = _points(rng, 40)
    sigma = 0.02

    def block(rho: np.ndarray, offset: np.ndarray, at_predicted: bool) -> PointToPlaneResidual:
        return _noisy_block(pts, rho, offset, intrinsics_at_predicted_range=at_predicted)

    # planes through the noise-free points: zero residuals
    offset = pts["offset"] - block(pts["rho"], pts["offset"], False).distances(params)
    exact = block(pts["rho"], offset, False)
    np.testing.assert_allclose(exact.distances(params), 0.0, atol=1e-9)
    j_true = _intrinsics_jacobian(exact, params)
    np.testing.assert_allclose(
        _intrinsics_jacobian(block(pts["rho"], offset, True), params), j_true, atol=1e-9
    )
    # rays that meet their plane steeply, range noise of one sigma: the derivatives at the
    # predicted range are the noise-free ones; the exact derivatives at the measured range are not
    ray = _rays_in_world(exact, params)
    steep = np.abs(np.einsum("ij,ij->i", ray, pts["normal"])) > 0.3
    assert steep.sum() >= 10
    noisy = pts["rho"] + sigma * rng.choice([-1.0, 1.0], pts["rho"].shape[0])
    j_pred = _intrinsics_jacobian(block(noisy, offset, True), params)
    j_meas = _intrinsics_jacobian(block(noisy, offset, False), params)
    np.testing.assert_allclose(j_pred[steep], j_true[steep], atol=1e-9)
    assert np.abs(j_meas[steep] - j_true[steep]).max() > 1e-4
    # the shift is held to three sigmas: an outlier keeps (about) its measured range
    far = pts["rho"] + 50.0 * sigma
    j_far = _intrinsics_jacobian(block(far, offset, True), params)
    j_far_meas = _intrinsics_jacobian(block(far, offset, False), params)
    shifted = np.abs(j_far[steep] - j_far_meas[steep]).max()
    assert 0.0 < shifted < np.abs(j_far_meas[steep] - j_true[steep]).max()


def test_point_to_plane_motion_derivatives_at_the_predicted_range() -> None:
    """With range noise, the derivatives w.r.t. the trajectory's and the extrinsic's rotation and
    the time offset are those of the noise-free point, as the intrinsics' are: at the measured
    point their noise is the residual's, and the product biased the time offset by +0.15 ms
    under 3 cm of range noise. On the plane they are the exact derivatives."""
    rng = np.random.default_rng(41)
    params = _random_params(rng)
    pts = _points(rng, 40)
    sigma = 0.02
    blocks = {TRAJ_SO3: params[TRAJ_SO3].size, EXT_ROTATION: 3, TIME_OFFSET: 1}

    def block(rho: np.ndarray, offset: np.ndarray, at_predicted: bool) -> PointToPlaneResidual:
        return _noisy_block(pts, rho, offset, motion_at_predicted_range=at_predicted)

    def jacobian(res: PointToPlaneResidual) -> np.ndarray:
        ev = res.evaluate(params, jacobians=True)
        return np.hstack([_analytic(ev, name, size) for name, size in blocks.items()])

    offset = pts["offset"] - block(pts["rho"], pts["offset"], False).distances(params)
    exact = block(pts["rho"], offset, False)
    np.testing.assert_allclose(exact.distances(params), 0.0, atol=1e-9)
    j_true = jacobian(exact)
    np.testing.assert_allclose(jacobian(block(pts["rho"], offset, True)), j_true, atol=1e-9)
    ray = _rays_in_world(exact, params)
    steep = np.abs(np.einsum("ij,ij->i", ray, pts["normal"])) > 0.3
    assert steep.sum() >= 10
    noisy = pts["rho"] + sigma * rng.choice([-1.0, 1.0], pts["rho"].shape[0])
    j_pred = jacobian(block(noisy, offset, True))
    j_meas = jacobian(block(noisy, offset, False))
    np.testing.assert_allclose(j_pred[steep], j_true[steep], atol=1e-9)
    assert np.abs(j_meas[steep] - j_true[steep]).max() > 1e-4
    # the residuals themselves are the measured ones either way
    np.testing.assert_array_equal(
        block(noisy, offset, True).evaluate(params, jacobians=False).residuals,
        block(noisy, offset, False).evaluate(params, jacobians=False).residuals,
    )


def _rays_in_world(res: PointToPlaneResidual, params: Mapping[str, np.ndarray]) -> np.ndarray:
    """(N, 3) unit rays of the block's points in the world frame, by differencing the points
    along their ranges."""
    from licalib_cli.geometry.so3 import quat_to_matrix
    from licalib_cli.models.lidar import lidar_point_terms
    from licalib_cli.spline import SO3Spline

    terms = lidar_point_terms(
        res.nominal_elevation, params[LIDAR_INTRINSICS], res.beam, res.rho, res.theta
    )
    u = np.column_stack(
        [
            terms.cos_phi * terms.cos_theta,
            terms.cos_phi * terms.sin_theta,
            terms.sin_phi,
        ]
    )
    t = res.query_times(float(params[TIME_OFFSET][0]))
    rot = SO3Spline(KNOTS, params[TRAJ_SO3]).evaluate(t).rotation
    return np.einsum("nij,nj->ni", rot, u @ quat_to_matrix(params[EXT_ROTATION]).T)


def test_point_to_plane_outside_spline_is_infinite() -> None:
    rng = np.random.default_rng(5)
    params = _random_params(rng)
    pts = _points(rng, 10)
    pts["t"][0] = KNOTS.t_end_s - 1e-3
    res = PointToPlaneResidual(
        KNOTS,
        pts["t"],
        pts["beam"],
        pts["rho"],
        pts["theta"],
        pts["normal"],
        pts["offset"],
        1.0,
        np.deg2rad([-10.0, 0.0, 10.0]),
    )
    params[TIME_OFFSET] = np.array([0.01])  # pushes point 0 past the end
    r = res.evaluate(params, jacobians=False).residuals[:, 0]
    assert np.isinf(r[0]) and np.all(np.isfinite(r[1:]))


def test_priors_jacobians_and_values() -> None:
    rng = np.random.default_rng(30)
    params = _random_params(rng)
    mean = params[LIDAR_INTRINSICS] + 0.01 * rng.standard_normal(params[LIDAR_INTRINSICS].shape)
    sigma = np.array([1e-3, 1e-3, 0.01, 0.01, 1e-3, 0.02])
    prior = GaussianPrior(LIDAR_INTRINSICS, mean, sigma)
    _check_all(prior, params, [LIDAR_INTRINSICS], float(np.abs(mean / sigma).max()))
    r = prior.evaluate(params, False).residuals
    np.testing.assert_allclose(r[:, 2], (params[LIDAR_INTRINSICS][:, 2] - mean[:, 2]) / 0.01)
    rot_prior = GaussianPrior(EXT_ROTATION, quat_exp(rng.standard_normal(3)), 0.1, manifold="so3")
    _check_all(rot_prior, params, [EXT_ROTATION], 1.0 / 0.1)
    bias_prior = GaussianPrior(GYRO_BIAS, np.zeros(3), 0.02)
    _check_all(bias_prior, params, [GYRO_BIAS], 1.0)
    assert bias_prior.evaluate(params, False).residuals.shape == (1, 3)


def test_bias_drift_jacobians() -> None:
    """The candidate effects ``imu.gyro_bias_drift`` / ``imu.accel_bias_drift``: a bias that
    changes linearly with time about ``t_ref``."""
    from licalib_cli.residuals import ACCEL_BIAS_DRIFT, GYRO_BIAS_DRIFT

    rng = np.random.default_rng(40)
    params = _random_params(rng)
    del params[GYRO_G_SENSITIVITY]
    params[GYRO_BIAS_DRIFT] = 1e-3 * rng.standard_normal(3)
    params[ACCEL_BIAS_DRIFT] = 1e-2 * rng.standard_normal(3)
    t = rng.uniform(0.0, KNOTS.t_end_s, 25)
    gyro = GyroResidual(KNOTS, t, rng.standard_normal((25, 3)), 0.5, t_ref_s=0.4)
    _check_all(
        gyro,
        params,
        [TRAJ_SO3, GYRO_BIAS, GYRO_BIAS_DRIFT, GYRO_SCALE, GYRO_MISALIGNMENT, GYRO_ROTATION],
        float(np.abs(gyro.gyro * gyro.inv_sigma).max()),
    )
    accel = AccelResidual(KNOTS, t, rng.standard_normal((25, 3)) * 9.0, 0.5, t_ref_s=0.4)
    _check_all(
        accel,
        params,
        [TRAJ_SO3, TRAJ_R3, GRAVITY, ACCEL_BIAS, ACCEL_BIAS_DRIFT, ACCEL_SCALE, ACCEL_MISALIGNMENT],
        float(np.abs(accel.accel * accel.inv_sigma).max()),
    )
    # The drift adds d (t - t_ref) to the prediction.
    without = dict(params)
    del without[GYRO_BIAS_DRIFT]
    diff = gyro.evaluate(params, False).residuals - gyro.evaluate(without, False).residuals
    np.testing.assert_allclose(diff, (t - 0.4)[:, None] * params[GYRO_BIAS_DRIFT] * 2.0)


def test_piecewise_bias_drift_jacobians_and_values() -> None:
    """A bias walk in pieces (a ``(K, 3)`` drift block): Jacobians against finite differences,
    and the bias continuous, linear within each piece with its own slope, and unchanged at
    ``t_ref``."""
    from licalib_cli.models.imu import bias_drift_basis
    from licalib_cli.residuals import ACCEL_BIAS_DRIFT, GYRO_BIAS_DRIFT

    rng = np.random.default_rng(41)
    params = _random_params(rng)
    del params[GYRO_G_SENSITIVITY]
    t_ref = 0.5 * KNOTS.t_end_s
    params[GYRO_BIAS_DRIFT] = 1e-3 * rng.standard_normal((3, 3))
    params[ACCEL_BIAS_DRIFT] = 1e-2 * rng.standard_normal((4, 3))
    t = np.sort(rng.uniform(0.0, KNOTS.t_end_s, 40))
    gyro = GyroResidual(KNOTS, t, rng.standard_normal((40, 3)), 0.5, t_ref_s=t_ref)
    _check_all(
        gyro,
        params,
        [TRAJ_SO3, GYRO_BIAS, GYRO_BIAS_DRIFT, GYRO_SCALE, GYRO_MISALIGNMENT, GYRO_ROTATION],
        float(np.abs(gyro.gyro * gyro.inv_sigma).max()),
    )
    accel = AccelResidual(KNOTS, t, rng.standard_normal((40, 3)) * 9.0, 0.5, t_ref_s=t_ref)
    _check_all(
        accel,
        params,
        [TRAJ_SO3, TRAJ_R3, GRAVITY, ACCEL_BIAS, ACCEL_BIAS_DRIFT, ACCEL_SCALE, ACCEL_MISALIGNMENT],
        float(np.abs(accel.accel * accel.inv_sigma).max()),
    )
    # The bias's change: 0 at t_ref, continuous, slope d_k within piece k.
    d = params[GYRO_BIAS_DRIFT]
    edges = np.linspace(0.0, 2.0 * t_ref, 4)
    grid = np.linspace(0.0, 2.0 * t_ref, 301)
    change = bias_drift_basis(grid, t_ref, 3) @ d
    np.testing.assert_allclose(bias_drift_basis([t_ref], t_ref, 3), 0.0, atol=1e-15)
    for k in range(3):
        inside = (grid > edges[k] + 1e-9) & (grid < edges[k + 1] - 1e-9)
        slope = np.diff(change[inside], axis=0) / np.diff(grid[inside])[:, None]
        np.testing.assert_allclose(slope, np.broadcast_to(d[k], slope.shape), rtol=1e-9)
    assert np.max(np.abs(np.diff(change, axis=0))) < 2.0 * np.abs(d).max() * (grid[1] - grid[0])
    # one piece is the linear drift; equal drifts in every piece are the same bias
    np.testing.assert_allclose(bias_drift_basis(t, t_ref, 1)[:, 0], t - t_ref, atol=1e-15)
    np.testing.assert_allclose(bias_drift_basis(t, t_ref, 5).sum(axis=1), t - t_ref, atol=1e-12)
    without = dict(params)
    del without[GYRO_BIAS_DRIFT]
    diff = gyro.evaluate(params, False).residuals - gyro.evaluate(without, False).residuals
    np.testing.assert_allclose(diff, bias_drift_basis(t, t_ref, 3) @ d * 2.0, atol=1e-14)


def test_clock_drift_and_point_time_jacobians() -> None:
    """``ext.time_drift`` and ``lidar.point_time_scale`` move each point's query time by
    ``k_drift (tau - t_ref)`` and ``-k_point (tau - sweep start)``."""
    from licalib_cli.residuals import POINT_TIME_SCALE, TIME_DRIFT

    rng = np.random.default_rng(41)
    params = _random_params(rng)
    params[TIME_DRIFT] = np.array([2e-4])
    params[POINT_TIME_SCALE] = np.array([5e-3])
    pts = _points(rng, 30)
    start = pts["t"] - rng.uniform(0.0, 0.1, 30)
    res = PointToPlaneResidual(
        KNOTS,
        pts["t"],
        pts["beam"],
        pts["rho"],
        pts["theta"],
        pts["normal"],
        pts["offset"],
        pts["sigma"],
        np.deg2rad([-10.0, 0.0, 10.0]),
        t_ref_s=0.5,
        sweep_start_s=start,
        intrinsics_at_predicted_range=False,
        motion_at_predicted_range=False,
    )
    terms = (pts["rho"].max() + np.abs(pts["offset"]).max()) / pts["sigma"].min()
    _check_all(
        res,
        params,
        [
            TRAJ_SO3,
            TRAJ_R3,
            EXT_ROTATION,
            EXT_TRANSLATION,
            TIME_OFFSET,
            TIME_DRIFT,
            POINT_TIME_SCALE,
            LIDAR_INTRINSICS,
        ],
        float(terms),
    )
    expected = pts["t"] + 0.004 + 2e-4 * (pts["t"] - 0.5) - 5e-3 * (pts["t"] - start)
    np.testing.assert_allclose(res.query_times(0.004, 2e-4, 5e-3), expected)


def test_an_imu_clock_drift_scales_the_rates_the_imu_measures() -> None:
    """The splines run on the IMU's clock: an IMU clock ``1 + k`` fast sees the world move
    ``1 + k`` times slower, while the IMU measures rates per second of the world. The gyro's
    prediction is then that of a gyro scale ``1 + k`` times larger, the accelerometer's takes
    the acceleration ``(1 + k)^2`` times (gravity as it is), and the Jacobians hold with the
    drift among the blocks."""
    from licalib_cli.residuals import TIME_DRIFT

    k = 2e-4
    rng = np.random.default_rng(43)
    params = _random_params(rng)
    params[TIME_DRIFT] = np.array([k])
    t = rng.uniform(0.0, KNOTS.t_end_s, 25)
    gyro = GyroResidual(KNOTS, t, rng.standard_normal((25, 3)), np.array([0.5, 1.0, 2.0]))
    plain = {b: v for b, v in params.items() if b != GYRO_G_SENSITIVITY}
    _check_all(
        gyro,
        plain,
        [TRAJ_SO3, GYRO_BIAS, GYRO_SCALE, GYRO_MISALIGNMENT, GYRO_ROTATION, TIME_DRIFT],
        float(np.abs(gyro.gyro * gyro.inv_sigma).max()),
    )
    scaled = {b: v for b, v in plain.items() if b != TIME_DRIFT}
    scaled[GYRO_SCALE] = plain[GYRO_SCALE] * (1.0 + k)
    np.testing.assert_allclose(
        gyro.evaluate(plain, jacobians=False).residuals,
        gyro.evaluate(scaled, jacobians=False).residuals,
        rtol=1e-10,
        atol=1e-12,
    )
    sensitive = GyroResidual(KNOTS, t, rng.standard_normal((25, 3)), 0.7, g_sensitivity=True)
    _check_all(
        sensitive,
        params,
        [*GYRO_G_BLOCKS, TIME_DRIFT],
        float(np.abs(sensitive.gyro * sensitive.inv_sigma).max()),
    )
    accel = AccelResidual(KNOTS, t, rng.standard_normal((25, 3)) * 9.0, np.array([0.3, 0.5, 1.0]))
    _check_all(
        accel,
        params,
        [TRAJ_SO3, TRAJ_R3, GRAVITY, ACCEL_BIAS, ACCEL_SCALE, ACCEL_MISALIGNMENT, TIME_DRIFT],
        float(np.abs(accel.accel * accel.inv_sigma).max()),
    )
    # the acceleration is linear in the position's control points: scaling them all by
    # (1 + k)^2 scales the acceleration alone (gravity as it is), as the drift does
    stretched = {b: v for b, v in params.items() if b != TIME_DRIFT}
    stretched[TRAJ_R3] = params[TRAJ_R3] * (1.0 + k) ** 2
    np.testing.assert_allclose(
        accel.evaluate(params, jacobians=False).residuals,
        accel.evaluate(stretched, jacobians=False).residuals,
        rtol=1e-10,
        atol=1e-10,
    )
