"""Tests of licalib_cli.spline: knots, basis, R3/SO3 evaluation, Jacobians, fitting."""

from __future__ import annotations

import numpy as np
import pytest
from fd_check import STEP, assert_jacobian

from licalib_cli.geometry import so3
from licalib_cli.spline import (
    BASIS_MATRIX,
    CUMULATIVE_BASIS_MATRIX,
    R3Spline,
    SO3EvaluationCache,
    SO3Spline,
    UniformKnots,
    blending,
    cumulative_blending,
)
from licalib_cli.spline.so3_spline import _fit_residuals

FD_STEP = STEP  # central differences; the entry-wise criterion is that of fd_check


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def _scale(values: np.ndarray | None) -> float:
    """Magnitude of differentiated values (at least 1: rotation entries are of order 1)."""
    assert values is not None
    return max(float(np.abs(values).max()), 1.0)


# ---------------------------------------------------------------------------------------------
# Basis and knots
# ---------------------------------------------------------------------------------------------


def test_cumulative_basis_matches_paper_and_partition_of_unity() -> None:
    paper = np.array([[6, 5, 1, 0], [0, 3, 3, 0], [0, -3, 3, 0], [0, 1, -2, 1]]) / 6.0
    np.testing.assert_allclose(CUMULATIVE_BASIS_MATRIX, paper, atol=0)
    suffix = np.cumsum(BASIS_MATRIX[:, ::-1], axis=1)[:, ::-1]
    np.testing.assert_allclose(CUMULATIVE_BASIS_MATRIX, suffix, atol=1e-16)
    u = np.linspace(0, 1, 11)
    np.testing.assert_allclose(blending(u).sum(axis=1), 1.0, atol=1e-15)
    for k in (1, 2, 3):
        np.testing.assert_allclose(blending(u, k).sum(axis=1), 0.0, atol=1e-14)
    lam = cumulative_blending(u)
    np.testing.assert_allclose(lam[:, 0], 1.0)
    np.testing.assert_allclose(lam[0], [1, 5 / 6, 1 / 6, 0], atol=1e-16)
    np.testing.assert_allclose(lam[-1], [1, 1, 5 / 6, 1 / 6], atol=1e-15)
    # u-derivatives against finite differences
    h = FD_STEP
    for k in (1, 2):
        fd = (cumulative_blending(u + h, k - 1) - cumulative_blending(u - h, k - 1)) / (2 * h)
        assert_jacobian(cumulative_blending(u, k), fd, 1.0, what=f"d^{k}/du^{k}")


def test_knots_locate_and_range() -> None:
    kn = UniformKnots(t0_s=1.0, dt_s=0.1, num_control_points=7)  # 4 segments: [1.0, 1.4]
    assert kn.num_segments == 4
    assert kn.t_end_s == pytest.approx(1.4)
    idx, u = kn.locate(np.array([1.0, 1.05, 1.1, 1.399999, 1.4]))
    np.testing.assert_array_equal(idx, [0, 0, 1, 3, 3])
    np.testing.assert_allclose(u, [0.0, 0.5, 0.0, 0.99999, 1.0], atol=1e-9)
    assert idx.dtype == np.int64
    for bad in (0.999, 1.401, np.nan):
        with pytest.raises(ValueError, match="outside the spline range"):
            kn.locate(np.array([1.2, bad]))
    np.testing.assert_array_equal(kn.contains([0.9, 1.2, 1.5]), [False, True, False])
    np.testing.assert_allclose(kn.clamp([0.9, 1.2, 1.5]), [1.0, 1.2, 1.4])
    np.testing.assert_allclose(kn.control_point_times_s(), 1.0 + 0.1 * (np.arange(7) - 1))
    with pytest.raises(ValueError):
        UniformKnots(0.0, 0.0, 5)
    with pytest.raises(ValueError):
        UniformKnots(0.0, 0.1, 3)


def test_knots_for_interval() -> None:
    kn = UniformKnots.for_interval(2.0, 12.0, 0.05, padding_s=0.1)
    assert kn.t0_s == pytest.approx(1.9)
    assert kn.t_end_s >= 12.1 - 1e-12
    assert kn.t_end_s < 12.1 + 0.05
    assert kn.num_control_points == 204 + 3
    exact = UniformKnots.for_interval(0.0, 1.0, 0.1)
    assert exact.num_segments == 10  # no spurious extra segment from round-off
    kn.locate(np.array([1.9, 12.1]))
    with pytest.raises(ValueError):
        UniformKnots.for_interval(1.0, 0.0, 0.1)


# ---------------------------------------------------------------------------------------------
# R3 spline
# ---------------------------------------------------------------------------------------------


def _random_r3(rng: np.random.Generator, n: int = 12, dt: float = 0.05) -> R3Spline:
    return R3Spline(UniformKnots(0.3, dt, n), rng.normal(size=(n, 3)))


def test_r3_jacobians_match_finite_differences(rng: np.random.Generator) -> None:
    spline = _random_r3(rng)
    t = rng.uniform(spline.knots.t0_s, spline.knots.t_end_s, 40)
    ev = spline.evaluate(t, order=3)
    n = spline.knots.num_control_points
    h = FD_STEP
    for name, weights in (
        ("position", ev.weights),
        ("velocity", ev.velocity_weights),
        ("acceleration", ev.acceleration_weights),
    ):
        assert weights is not None
        for k in range(4):
            for c in range(3):
                fd = np.empty((t.size, 3))
                for m in range(t.size):  # each query perturbs its own control point
                    cp = np.array(spline.control_points)
                    cp[ev.index[m] + k, c] += h
                    plus = getattr(spline.with_control_points(cp).evaluate(t[m : m + 1]), name)
                    cp[ev.index[m] + k, c] -= 2 * h
                    minus = getattr(spline.with_control_points(cp).evaluate(t[m : m + 1]), name)
                    fd[m] = (plus - minus)[0] / (2 * h)
                expected = np.zeros((t.size, 3))
                expected[:, c] = weights[:, k]
                scale = _scale(getattr(ev, name))
                assert_jacobian(expected, fd, scale, what=f"{name} {k} {c}")
    # weights reproduce the values and sum to 1 (0 for derivatives)
    cps = spline.control_points[ev.index[:, None] + np.arange(4)]
    np.testing.assert_allclose(np.einsum("mj,mjk->mk", ev.weights, cps), ev.position, atol=1e-14)
    np.testing.assert_allclose(ev.weights.sum(axis=1), 1.0, atol=1e-15)
    assert n == spline.control_points.shape[0]


def test_r3_time_derivatives_match_finite_differences(rng: np.random.Generator) -> None:
    spline = _random_r3(rng)
    dt = spline.knots.dt_s
    # keep queries away from knots, where the jerk is discontinuous
    seg = rng.integers(0, spline.knots.num_segments, 30)
    t = spline.knots.t0_s + (seg + rng.uniform(0.05, 0.95, 30)) * dt
    h = FD_STEP
    ev = spline.evaluate(t, order=3)
    plus, minus = spline.evaluate(t + h, order=3), spline.evaluate(t - h, order=3)
    for value, deriv in (
        ("position", "velocity"),
        ("velocity", "acceleration"),
        ("acceleration", "jerk"),
    ):
        fd = (getattr(plus, value) - getattr(minus, value)) / (2 * h)
        assert_jacobian(getattr(ev, deriv), fd, _scale(getattr(ev, value)), what=value)


@pytest.mark.parametrize("derivative", [0, 1, 2])
def test_r3_design_matrix_is_the_control_point_jacobian(
    rng: np.random.Generator, derivative: int
) -> None:
    """``B[m, n] = d p^(k)(t_m) / d c_n`` (the same for each coordinate), by central differences."""
    spline = _random_r3(rng)
    t = rng.uniform(spline.knots.t0_s, spline.knots.t_end_s, 25)
    name = ("position", "velocity", "acceleration")[derivative]
    B = spline.design_matrix(t, derivative=derivative).toarray()  # (M, N)
    values = getattr(spline.evaluate(t, order=derivative), name)
    np.testing.assert_allclose(B @ spline.control_points, values, rtol=1e-13, atol=1e-12)
    h = FD_STEP
    n = spline.knots.num_control_points
    for c in range(3):
        fd = np.empty((t.size, n))
        for k in range(n):  # one control-point coordinate at a time, all queries at once
            cp = np.array(spline.control_points)
            cp[k, c] += h
            plus = getattr(spline.with_control_points(cp).evaluate(t, order=derivative), name)
            cp[k, c] -= 2 * h
            minus = getattr(spline.with_control_points(cp).evaluate(t, order=derivative), name)
            fd[:, k] = (plus - minus)[:, c] / (2 * h)
        assert_jacobian(B, fd, _scale(values), what=f"d^{derivative} coordinate {c}")


def test_r3_linear_control_points_give_constant_velocity() -> None:
    kn = UniformKnots(0.0, 0.1, 10)
    cp = np.outer(np.arange(10.0), [1.0, -2.0, 0.5])  # c_k = k v
    ev = R3Spline(kn, cp).evaluate(np.linspace(0, kn.t_end_s, 25), order=2)
    np.testing.assert_allclose(
        ev.velocity, np.broadcast_to([10.0, -20.0, 5.0], (25, 3)), atol=1e-12
    )
    np.testing.assert_allclose(ev.acceleration, 0.0, atol=1e-10)


# ---------------------------------------------------------------------------------------------
# SO3 spline
# ---------------------------------------------------------------------------------------------


def _random_so3(rng: np.random.Generator, scale: float, n: int = 10, dt: float = 0.05) -> SO3Spline:
    """Control points whose successive relative rotations have magnitude ~scale rad."""
    steps = rng.normal(size=(n, 3)) * scale
    R = np.empty((n, 3, 3))
    R[0] = so3.exp(rng.normal(size=3))
    for k in range(1, n):
        R[k] = R[k - 1] @ so3.exp(steps[k])
    return SO3Spline.from_matrices(UniformKnots(-0.2, dt, n), R)


def _fd_control_jacobians(
    spline: SO3Spline, t: np.ndarray, index: np.ndarray, k: int, c: int, ev_rotation: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Central differences of (eps, w, alpha) w.r.t. delta_{index+k}[c] for each query."""
    h = FD_STEP
    n = spline.knots.num_control_points
    out = np.empty((3, t.size, 3))
    for m in range(t.size):
        res = []
        for sign in (1.0, -1.0):
            delta = np.zeros((n, 3))
            delta[index[m] + k, c] = sign * h
            ev = spline.retract(delta).evaluate(t[m : m + 1], order=2)
            eps = so3.log(ev_rotation[m].T @ ev.rotation[0])
            res.append((eps, ev.angular_velocity[0], ev.angular_acceleration[0]))
        for q in range(3):
            out[q, m] = (res[0][q] - res[1][q]) / (2 * h)
    return out[0], out[1], out[2]


@pytest.mark.parametrize("scale", [1e-9, 0.05, 0.8])
def test_so3_jacobians_match_finite_differences(rng: np.random.Generator, scale: float) -> None:
    spline = _random_so3(rng, scale)
    t = rng.uniform(spline.knots.t0_s, spline.knots.t_end_s, 12)
    t[:2] = [spline.knots.t0_s, spline.knots.t_end_s]  # u = 0 and u = 1 ends
    ev = spline.evaluate(t, order=2, jacobians=True)
    assert ev.jac_rotation is not None
    assert ev.jac_angular_velocity is not None
    assert ev.jac_angular_acceleration is not None
    # w and alpha come from rotation entries (rounded at order 1) divided by dt and dt^2
    dt = spline.knots.dt_s
    w_scale = max(_scale(ev.angular_velocity), 1.0 / dt)
    a_scale = max(_scale(ev.angular_acceleration), 1.0 / dt**2)
    for k in range(4):
        for c in range(3):
            fd_rot, fd_w, fd_a = _fd_control_jacobians(spline, t, ev.index, k, c, ev.rotation)
            # the rotation's differences round like its matrix entries (of order 1)
            assert_jacobian(ev.jac_rotation[:, k, :, c], fd_rot, 1.0, what=f"rot {k} {c}")
            assert_jacobian(ev.jac_angular_velocity[:, k, :, c], fd_w, w_scale, what=f"w {k} {c}")
            assert_jacobian(
                ev.jac_angular_acceleration[:, k, :, c], fd_a, a_scale, what=f"alpha {k} {c}"
            )
    # lower orders return the same Jacobians
    ev0 = spline.evaluate(t, order=0, jacobians=True)
    ev1 = spline.evaluate(t, order=1, jacobians=True)
    np.testing.assert_allclose(ev0.jac_rotation, ev.jac_rotation, atol=1e-14)
    np.testing.assert_allclose(ev1.jac_angular_velocity, ev.jac_angular_velocity, atol=1e-12)
    assert ev0.angular_velocity is None and ev1.jac_angular_acceleration is None


@pytest.mark.parametrize("scale", [1e-9, 0.05, 0.8])
def test_so3_time_derivatives_match_finite_differences(
    rng: np.random.Generator, scale: float
) -> None:
    spline = _random_so3(rng, scale)
    kn = spline.knots
    t = rng.uniform(kn.t0_s + 1e-3, kn.t_end_s - 1e-3, 50)
    h = FD_STEP
    ev = spline.evaluate(t, order=2)
    plus, minus = spline.evaluate(t + h, order=2), spline.evaluate(t - h, order=2)
    # d eps / dt = w with eps the right perturbation of R(t)
    fd_w = so3.log(np.swapaxes(minus.rotation, -1, -2) @ plus.rotation) / (2 * h)
    assert_jacobian(ev.angular_velocity, fd_w, 1.0, what="w")
    fd_a = (plus.angular_velocity - minus.angular_velocity) / (2 * h)
    w_scale = max(_scale(ev.angular_velocity), 1.0 / kn.dt_s)  # rotation entries over dt
    assert_jacobian(ev.angular_acceleration, fd_a, w_scale, what="alpha")


def test_so3_value_matches_cumulative_formula(rng: np.random.Generator) -> None:
    """R(t) = R_i prod_j Exp(lambda_j Log(R_{i+j-1}^T R_{i+j})), evaluated naively."""
    spline = _random_so3(rng, 0.7)
    t = rng.uniform(spline.knots.t0_s, spline.knots.t_end_s, 20)
    idx, u = spline.knots.locate(t)
    lam = cumulative_blending(u)
    R = spline.control_rotations
    expected = R[idx].copy()
    for j in (1, 2, 3):
        d = so3.log(np.swapaxes(R[idx + j - 1], -1, -2) @ R[idx + j])
        expected = expected @ so3.exp(lam[:, j : j + 1] * d)
    np.testing.assert_allclose(spline.rotation(t), expected, atol=1e-14)
    q = spline.quaternion(t)
    np.testing.assert_allclose(so3.quat_to_matrix(q), expected, atol=1e-14)
    # constant control points: constant rotation, zero rates
    const = SO3Spline(spline.knots, np.tile(spline.control_quats[3], (10, 1)))
    ev = const.evaluate(t, order=2)
    np.testing.assert_allclose(ev.rotation, np.broadcast_to(R[3], ev.rotation.shape), atol=1e-15)
    np.testing.assert_allclose(ev.angular_velocity, 0.0, atol=1e-15)
    np.testing.assert_allclose(ev.angular_acceleration, 0.0, atol=1e-15)


def test_so3_constant_rate_rotation() -> None:
    """Control points R_k = Exp(k w dt): the spline rotates at exactly w."""
    w = np.array([0.3, -1.2, 2.0])
    kn = UniformKnots(0.0, 0.05, 12)
    spline = SO3Spline.from_matrices(kn, so3.exp(np.outer(np.arange(12) - 1.0, w * 0.05)))
    t = np.linspace(0, kn.t_end_s, 30)
    ev = spline.evaluate(t, order=2)
    np.testing.assert_allclose(ev.rotation, so3.exp(np.outer(t, w)), atol=1e-14)
    np.testing.assert_allclose(ev.angular_velocity, np.broadcast_to(w, (30, 3)), atol=1e-12)
    np.testing.assert_allclose(ev.angular_acceleration, 0.0, atol=1e-10)


def test_so3_blocked_evaluation_matches_single_queries(rng: np.random.Generator) -> None:
    """More queries than one internal block: results equal query-by-query evaluation."""
    spline = _random_so3(rng, 0.3, n=30)
    t = rng.uniform(spline.knots.t0_s, spline.knots.t_end_s, 9000)
    ev = spline.evaluate(t, order=2, jacobians=True)
    pick = np.array([0, 1, 4095, 4096, 4097, 8191, 8192, 8999])
    for m in pick:
        single = spline.evaluate(t[m : m + 1], order=2, jacobians=True)
        np.testing.assert_allclose(ev.rotation[m], single.rotation[0], atol=1e-15)
        np.testing.assert_allclose(ev.angular_velocity[m], single.angular_velocity[0], atol=1e-13)
        np.testing.assert_allclose(
            ev.jac_angular_velocity[m], single.jac_angular_velocity[0], atol=1e-13
        )
        np.testing.assert_allclose(
            ev.jac_angular_acceleration[m], single.jac_angular_acceleration[0], atol=1e-11
        )
    np.testing.assert_array_equal(ev.index, spline.knots.locate(t)[0])


def test_so3_retract_and_errors(rng: np.random.Generator) -> None:
    spline = _random_so3(rng, 0.2)
    n = spline.knots.num_control_points
    delta = 0.01 * rng.normal(size=(n, 3))
    moved = spline.retract(delta)
    np.testing.assert_allclose(
        moved.control_rotations, spline.control_rotations @ so3.exp(delta), atol=1e-15
    )
    with pytest.raises(ValueError, match="outside the spline range"):
        spline.evaluate([spline.knots.t_end_s + 1.0])
    with pytest.raises(ValueError):
        spline.evaluate([0.0], order=3)
    with pytest.raises(ValueError):
        SO3Spline(spline.knots, np.zeros((n, 4)))
    with pytest.raises(ValueError):
        SO3Spline(spline.knots, np.ones((n + 1, 4)))


def test_so3_jacobian_order_and_rotation_vjp(rng: np.random.Generator) -> None:
    """Jacobians of lower derivatives only, and row-vector products with the rotation Jacobian,
    agree with the full evaluation (also across internal blocks)."""
    spline = _random_so3(rng, 0.6, n=30)
    t = rng.uniform(spline.knots.t0_s, spline.knots.t_end_s, 9000)
    full = spline.evaluate(t, order=2, jacobians=True)
    part = spline.evaluate(t, order=2, jacobians=True, jacobian_order=0)
    assert part.jac_angular_velocity is None and part.jac_angular_acceleration is None
    np.testing.assert_array_equal(part.jac_rotation, full.jac_rotation)
    np.testing.assert_array_equal(part.angular_acceleration, full.angular_acceleration)
    one = spline.evaluate(t, order=2, jacobians=True, jacobian_order=1)
    np.testing.assert_array_equal(one.jac_angular_velocity, full.jac_angular_velocity)
    assert one.jac_angular_acceleration is None
    with pytest.raises(ValueError, match="jacobian_order"):
        spline.evaluate(t, order=1, jacobians=True, jacobian_order=2)
    v = rng.normal(size=(9000, 3))
    expected = np.einsum("mi,mkil->mkl", v, full.jac_rotation)
    for ev in (
        spline.evaluate(t, order=0, rotation_vjp=True),
        spline.evaluate(t, order=1, jacobians=True, rotation_vjp=True),
    ):
        assert ev.rotation_vjp is not None
        np.testing.assert_allclose(ev.rotation_vjp(v), expected, rtol=0, atol=1e-13)
        np.testing.assert_array_equal(ev.rotation, full.rotation)
    assert spline.evaluate(t, order=0).rotation_vjp is None
    with pytest.raises(ValueError, match="shape"):
        spline.evaluate(t[:5], rotation_vjp=True).rotation_vjp(v)  # type: ignore[misc]


def test_so3_evaluation_cache_shares_and_refreshes(rng: np.random.Generator) -> None:
    spline = _random_so3(rng, 0.4)
    knots, quats = spline.knots, spline.control_quats
    t = rng.uniform(knots.t0_s, knots.t_end_s, 50)
    cache = SO3EvaluationCache()
    first = cache.evaluate(knots, quats, t, 1, True)
    assert cache.evaluate(knots, quats.copy(), t.copy(), 0, True) is first  # equal values: shared
    assert cache.evaluate(knots, quats, t, 1, False) is first  # a superset is fine
    higher = cache.evaluate(knots, quats, t, 2, False)  # more than stored: evaluated again
    assert higher is not first and higher.angular_acceleration is not None
    np.testing.assert_array_equal(higher.jac_angular_velocity, first.jac_angular_velocity)
    moved = spline.retract(0.01 * rng.normal(size=(knots.num_control_points, 3)))
    new = cache.evaluate(knots, moved.control_quats, t, 0, True)
    # (the cache builds its spline from the quaternions again: equal up to round-off)
    reference = SO3Spline(knots, moved.control_quats).evaluate(t, order=2, jacobians=True)
    assert new.angular_acceleration is not None  # the highest order asked at these times
    np.testing.assert_array_equal(new.rotation, reference.rotation)
    np.testing.assert_array_equal(new.jac_angular_velocity, reference.jac_angular_velocity)
    other_t = cache.evaluate(knots, moved.control_quats, t[:10], 0, False)
    np.testing.assert_array_equal(other_t.rotation, reference.rotation[:10])


# ---------------------------------------------------------------------------------------------
# Fitting an analytic trajectory (paper eq. simu_traj1, sinusoidal, t in [0, 10] s)
# ---------------------------------------------------------------------------------------------

_W = np.pi / 5


def _sinusoid(t: np.ndarray) -> dict[str, np.ndarray]:
    """Position/velocity/acceleration in G and R_G_I with body rate; Euler angles are
    roll = 0.4 cos t, pitch = 0.6 sin t, yaw = 0.7 t with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    c1, s1, c4, s4 = np.cos(_W * t), np.sin(_W * t), np.cos(4 * _W * t), np.sin(4 * _W * t)
    p = np.column_stack([2 * c1 + 5, 1.5 * s1 + 5, 0.8 * c4 + 5])
    v = np.column_stack([-2 * _W * s1, 1.5 * _W * c1, -3.2 * _W * s4])
    a = np.column_stack([-2 * _W**2 * c1, -1.5 * _W**2 * s1, -12.8 * _W**2 * c4])
    roll, pitch, yaw = 0.4 * np.cos(t), 0.6 * np.sin(t), 0.7 * t
    droll, dpitch, dyaw = -0.4 * np.sin(t), 0.6 * np.cos(t), np.full_like(t, 0.7)
    R = so3.rpy_to_matrix(np.column_stack([roll, pitch, yaw]))
    # body rates of the ZYX Euler sequence
    w = np.column_stack(
        [
            droll - dyaw * np.sin(pitch),
            dpitch * np.cos(roll) + dyaw * np.sin(roll) * np.cos(pitch),
            -dpitch * np.sin(roll) + dyaw * np.cos(roll) * np.cos(pitch),
        ]
    )
    return {"p": p, "v": v, "a": a, "R": R, "w": w}


def test_analytic_body_rate_reference_is_right() -> None:
    t = np.linspace(0.3, 9.7, 15)
    h = 1e-6
    ref = _sinusoid(t)
    fd = so3.log(np.swapaxes(_sinusoid(t - h)["R"], -1, -2) @ _sinusoid(t + h)["R"]) / (2 * h)
    np.testing.assert_allclose(fd, ref["w"], atol=1e-8)


# (dt, position m, velocity m/s, acceleration m/s^2, rotation rad, rate rad/s,
#  angular acceleration rad/s^2): about 3x the errors observed over the whole 10 s
# with noiseless 400 Hz samples.
FIT_TOLERANCES = [
    (0.02, 3e-8, 1e-5, 5e-3, 5e-8, 1.5e-5, 1e-2),
    (0.05, 1e-6, 1.5e-4, 3e-2, 6e-7, 1e-4, 5e-2),
]


@pytest.mark.parametrize(
    ("dt", "tol_p", "tol_v", "tol_a", "tol_r", "tol_w", "tol_al"), FIT_TOLERANCES
)
def test_fit_sinusoidal_trajectory(
    dt: float, tol_p: float, tol_v: float, tol_a: float, tol_r: float, tol_w: float, tol_al: float
) -> None:
    t = np.arange(0.0, 10.0 + 1e-9, 1.0 / 400.0)
    ref = _sinusoid(t)
    knots = UniformKnots.for_interval(0.0, 10.0, dt)

    pos = R3Spline.fit(knots, t, ref["p"])
    ev = pos.evaluate(t, order=2)
    assert np.linalg.norm(ev.position - ref["p"], axis=1).max() < tol_p
    assert np.linalg.norm(ev.velocity - ref["v"], axis=1).max() < tol_v
    assert np.linalg.norm(ev.acceleration - ref["a"], axis=1).max() < tol_a

    rot = SO3Spline.from_rotations(knots, t, ref["R"])
    er = rot.evaluate(t, order=2)
    rot_err = np.linalg.norm(so3.log(np.swapaxes(ref["R"], -1, -2) @ er.rotation), axis=1)
    assert rot_err.max() < tol_r
    assert np.linalg.norm(er.angular_velocity - ref["w"], axis=1).max() < tol_w
    # angular acceleration reference: central difference of the analytic rate (error ~1e-9)
    h = 1e-5
    tin = t[(t > 0.01) & (t < 9.99)]
    alpha_ref = (_sinusoid(tin + h)["w"] - _sinusoid(tin - h)["w"]) / (2 * h)
    alpha = rot.angular_acceleration(tin)
    assert np.linalg.norm(alpha - alpha_ref, axis=1).max() < tol_al


def test_fit_weights_smoothing_and_errors(rng: np.random.Generator) -> None:
    knots = UniformKnots.for_interval(0.0, 2.0, 0.1)
    t = np.linspace(0.0, 2.0, 200)
    truth = np.column_stack([np.sin(t), t**2, np.ones_like(t)])
    noisy = truth + 0.05 * rng.normal(size=truth.shape)
    rough = R3Spline.fit(knots, t, noisy)
    smooth = R3Spline.fit(knots, t, noisy, smoothing=1e-2)
    acc_rough = np.abs(np.diff(rough.acceleration(t), axis=0)).sum()
    acc_smooth = np.abs(np.diff(smooth.acceleration(t), axis=0)).sum()
    assert acc_smooth < 0.5 * acc_rough
    # zero-weight outliers are ignored
    bad = noisy.copy()
    bad[::10] += 100.0
    w = np.ones_like(t)
    w[::10] = 0.0
    np.testing.assert_allclose(
        R3Spline.fit(knots, t, bad, weights=w).position(t),
        R3Spline.fit(knots, t[w > 0], noisy[w > 0]).position(t),
        atol=1e-8,
    )
    with pytest.raises(ValueError):
        R3Spline.fit(knots, t, noisy[:, :2])
    with pytest.raises(ValueError):
        R3Spline.fit(knots, np.array([1.0, 1.0]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="outside the spline range"):
        R3Spline.fit(knots, t + 5.0, noisy)


def test_so3_from_rotations_with_sparse_samples(rng: np.random.Generator) -> None:
    """Control points far from any sample stay finite and the fit still passes the samples."""
    knots = UniformKnots.for_interval(0.0, 1.0, 0.05)
    t = np.sort(rng.uniform(0.2, 0.8, 40))
    R = so3.exp(np.outer(t, [0.5, 0.2, -0.4]))
    spline = SO3Spline.from_rotations(knots, t, R)
    err = np.linalg.norm(so3.log(np.swapaxes(R, -1, -2) @ spline.rotation(t)), axis=1)
    assert err.max() < 1e-6
    assert np.all(np.isfinite(spline.control_quats))
    single = SO3Spline.from_rotations(knots, [0.5], R[:1], iterations=1)
    np.testing.assert_allclose(single.rotation([0.5])[0], R[0], atol=1e-6)


@pytest.mark.parametrize("scale", [0.05, 0.8])
def test_so3_fit_residual_jacobian_matches_finite_differences(
    rng: np.random.Generator, scale: float
) -> None:
    """The Gauss-Newton Jacobian of :meth:`SO3Spline.from_rotations`,
    ``d Log(R_m^T R(t_m)) / d delta = Jr_inv(r) d eps / d delta``, by central differences."""
    spline = _random_so3(rng, scale)
    t = rng.uniform(spline.knots.t0_s, spline.knots.t_end_s, 12)
    samples = spline.rotation(t) @ so3.exp(0.3 * rng.normal(size=(12, 3)))  # r of ~0.5 rad
    r0, jac, index = _fit_residuals(spline, t, samples)
    n = spline.knots.num_control_points
    h = FD_STEP
    for k in range(4):
        for c in range(3):
            fd = np.empty((t.size, 3))
            for m in range(t.size):
                delta = np.zeros((n, 3))
                delta[index[m] + k, c] = h
                plus = _fit_residuals(spline.retract(delta), t[m : m + 1], samples[m : m + 1])[0]
                minus = _fit_residuals(spline.retract(-delta), t[m : m + 1], samples[m : m + 1])[0]
                fd[m] = (plus - minus)[0] / (2 * h)
            assert_jacobian(jac[:, k, :, c], fd, _scale(r0), what=f"slot {k} coordinate {c}")
