"""Tests of licalib_cli.geometry.so3: group axioms, maps, Jacobians, conventions, accuracy."""

from __future__ import annotations

import numpy as np
import pytest
from fd_check import assert_jacobian, central_difference
from scipy.spatial.transform import Rotation

from licalib_cli.geometry import so3

# Angles (rad) that exercise the Taylor branches, the switch at 0.1 and the region near pi.
ANGLES = [
    0.0,
    1e-12,
    1e-8,
    1e-4,
    0.05,
    0.1 - 1e-12,
    0.1,
    0.1 + 1e-12,
    0.5,
    1.0,
    2.5,
    3.0,
    np.pi - 1e-6,
    np.pi - 1e-9,
]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20220705)


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _random_rotvecs(rng: np.random.Generator, n: int) -> np.ndarray:
    return _unit(rng, n) * rng.uniform(0.0, np.pi, size=(n, 1))


def test_hat_vee(rng: np.random.Generator) -> None:
    v, w = rng.normal(size=(2, 50, 3))
    H = so3.hat(v)
    np.testing.assert_allclose(H, -np.swapaxes(H, -1, -2), atol=0.0)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", H, w), np.cross(v, w), atol=1e-14)
    np.testing.assert_array_equal(so3.vee(H), v)
    assert so3.hat(np.zeros((2, 4, 3))).shape == (2, 4, 3, 3)


def test_exp_matches_scipy_and_is_a_rotation(rng: np.random.Generator) -> None:
    phi = _random_rotvecs(rng, 500)
    R = so3.exp(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=2e-15)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=2e-15
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=2e-15)
    # group axioms: inverse, identity, composition about one axis adds angles
    np.testing.assert_allclose(
        so3.exp(phi) @ so3.exp(-phi), np.broadcast_to(np.eye(3), R.shape), atol=2e-15
    )
    np.testing.assert_array_equal(so3.exp(np.zeros(3)), np.eye(3))
    np.testing.assert_allclose(so3.exp(0.3 * phi) @ so3.exp(0.7 * phi), R, atol=3e-15)


def test_exp_near_identity_is_exact_to_machine_precision(rng: np.random.Generator) -> None:
    # For |phi| = 1e-8 the series I + hat + hat^2/2 is exact to ~1e-24.
    phi = 1e-8 * _unit(rng, 20)
    H = so3.hat(phi)
    expected = np.eye(3) + H + 0.5 * H @ H
    np.testing.assert_allclose(so3.exp(phi), expected, rtol=0, atol=1e-22)
    # off-diagonal entries carry the information: relative accuracy 1e-15
    off = np.array([[0, 1, 1], [1, 0, 1], [1, 1, 0]], dtype=bool)
    rel = np.abs(so3.exp(phi)[:, off] - expected[:, off]) / np.abs(expected[:, off])
    assert rel.max() < 1e-15


@pytest.mark.parametrize("angle", ANGLES)
def test_log_exp_round_trip(rng: np.random.Generator, angle: float) -> None:
    phi = angle * _unit(rng, 30)
    back = so3.log(so3.exp(phi))
    err = np.linalg.norm(back - phi, axis=1)
    # relative 1e-14 (absolute 1e-15 for the zero vector)
    assert np.all(err <= 1e-14 * max(angle, 0.1)), err.max()


def test_log_at_exactly_pi_and_exp_log_round_trip(rng: np.random.Generator) -> None:
    n = _unit(rng, 30)
    R = so3.exp(np.pi * n)
    phi = so3.log(R)
    np.testing.assert_allclose(np.linalg.norm(phi, axis=1), np.pi, rtol=1e-15)
    # direction is +-n
    np.testing.assert_allclose(np.abs(np.sum(phi * n, axis=1)), np.pi, rtol=1e-14)
    np.testing.assert_allclose(so3.exp(phi), R, atol=3e-15)
    # random matrices: exp(log(R)) = R and |log| <= pi
    R = Rotation.random(200, random_state=1).as_matrix()
    phi = so3.log(R)
    assert np.all(np.linalg.norm(phi, axis=1) <= np.pi + 1e-15)
    np.testing.assert_allclose(so3.exp(phi), R, atol=3e-15)


def test_quaternion_conventions_and_round_trips(rng: np.random.Generator) -> None:
    R = Rotation.random(300, random_state=2)
    q_ref = R.as_quat()  # scipy uses [x, y, z, w]
    q_ref = np.where(q_ref[:, 3:] < 0, -q_ref, q_ref)
    q = so3.matrix_to_quat(R.as_matrix())
    np.testing.assert_allclose(q, q_ref, atol=2e-15)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(so3.quat_to_matrix(q), R.as_matrix(), atol=2e-15)
    # 90 deg about z: [0, 0, sin45, cos45]
    qz = so3.matrix_to_quat(so3.exp([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(qz, [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-16)
    # near and at pi (w ~ 0): round trip up to sign
    for angle in (np.pi - 1e-9, np.pi):
        phi = angle * _unit(rng, 20)
        q = so3.quat_exp(phi)
        back = so3.matrix_to_quat(so3.quat_to_matrix(q))
        sign = np.sign(np.sum(back * q, axis=1, keepdims=True))
        np.testing.assert_allclose(back * sign, q, atol=2e-15)


def test_quaternion_algebra(rng: np.random.Generator) -> None:
    q1, q2, q3 = (so3.quat_exp(_random_rotvecs(rng, 50)) for _ in range(3))
    m = so3.quat_to_matrix
    np.testing.assert_allclose(m(so3.quat_multiply(q1, q2)), m(q1) @ m(q2), atol=3e-15)
    np.testing.assert_allclose(
        so3.quat_multiply(so3.quat_multiply(q1, q2), q3),
        so3.quat_multiply(q1, so3.quat_multiply(q2, q3)),
        atol=3e-15,
    )
    ident = so3.quat_multiply(q1, so3.quat_conjugate(q1))
    np.testing.assert_allclose(ident, np.broadcast_to([0, 0, 0, 1.0], ident.shape), atol=3e-16)
    v = rng.normal(size=(50, 3))
    np.testing.assert_allclose(
        so3.quat_rotate(q1, v), np.einsum("nij,nj->ni", m(q1), v), atol=3e-15
    )
    qn = so3.quat_normalize(-3.0 * q1)
    np.testing.assert_allclose(qn, np.where(q1[:, 3:] < 0, -q1, q1), atol=3e-16)


@pytest.mark.parametrize("angle", ANGLES)
def test_quat_exp_log(rng: np.random.Generator, angle: float) -> None:
    phi = angle * _unit(rng, 20)
    q = so3.quat_exp(phi)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=2e-16)
    np.testing.assert_allclose(so3.quat_to_matrix(q), so3.exp(phi), atol=2e-15)
    err = np.linalg.norm(so3.quat_log(q) - phi, axis=1)
    assert np.all(err <= 1e-14 * max(angle, 0.1))


@pytest.mark.parametrize("angle", [*ANGLES[:-2], 3.1])
def test_jacobian_identities(rng: np.random.Generator, angle: float) -> None:
    phi = angle * _unit(rng, 20)
    eye = np.broadcast_to(np.eye(3), (20, 3, 3))
    np.testing.assert_allclose(so3.Jr(phi) @ so3.Jr_inv(phi), eye, atol=1e-14)
    np.testing.assert_allclose(so3.Jl(phi) @ so3.Jl_inv(phi), eye, atol=1e-14)
    np.testing.assert_allclose(so3.Jl(phi), so3.exp(phi) @ so3.Jr(phi), atol=1e-15)
    np.testing.assert_allclose(so3.Jl(phi), so3.Jr(-phi), atol=0)


def test_jacobians_near_identity_series(rng: np.random.Generator) -> None:
    phi = 1e-8 * _unit(rng, 10)
    H = so3.hat(phi)
    eye = np.eye(3)
    # truncation of the series after hat^2 is ~1e-24
    np.testing.assert_allclose(so3.Jr(phi), eye - H / 2 + H @ H / 6, atol=1e-22, rtol=0)
    np.testing.assert_allclose(so3.Jr_inv(phi), eye + H / 2 + H @ H / 12, atol=1e-22, rtol=0)


def test_jacobians_continuous_at_series_switch(rng: np.random.Generator) -> None:
    n = _unit(rng, 5)
    for f in (so3.exp, so3.Jr, so3.Jr_inv, so3.quat_exp):
        # series just below, closed form at and above: a jump would break the linear midpoint
        lo, mid, hi = f((0.1 - 1e-9) * n), f(0.1 * n), f((0.1 + 1e-9) * n)
        assert np.abs(lo + hi - 2.0 * mid).max() < 2e-15, f.__name__


@pytest.mark.parametrize("angle", [1e-8, 0.05, 0.3, 1.5, 3.0])
def test_jacobians_are_derivatives(rng: np.random.Generator, angle: float) -> None:
    """Every Jacobian as the derivative it stands for, by central differences per entry::

    Exp(phi + d) ~= Exp(phi) Exp(Jr d)       Log(Exp(phi) Exp(d)) ~= phi + Jr_inv d
    Exp(phi + d) ~= Exp(Jl d) Exp(phi)       Log(Exp(d) Exp(phi)) ~= phi + Jl_inv d
    """
    phi = angle * _unit(rng, 10)
    rot = so3.exp(phi)
    rot_t = np.swapaxes(rot, -1, -2)
    scale = max(1.0, angle)  # rotation entries and the angle
    cases = {
        "Jr": (so3.Jr(phi), lambda d: so3.log(rot_t @ so3.exp(phi + d))),
        "Jr_inv": (so3.Jr_inv(phi), lambda d: so3.log(rot @ so3.exp(d))),
        "Jl": (so3.Jl(phi), lambda d: so3.log(so3.exp(phi + d) @ rot_t)),
        "Jl_inv": (so3.Jl_inv(phi), lambda d: so3.log(so3.exp(d) @ rot)),
    }
    for name, (analytic, f) in cases.items():
        assert_jacobian(analytic, central_difference(f, np.zeros(3)), scale, what=name)


def test_rpy_convention_against_explicit_product(rng: np.random.Generator) -> None:
    def rx(a: float) -> np.ndarray:
        c, s = np.cos(a), np.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a: float) -> np.ndarray:
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def rz(a: float) -> np.ndarray:
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    rpy = np.column_stack(
        [
            rng.uniform(-np.pi, np.pi, 50),
            rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, 50),
            rng.uniform(-np.pi, np.pi, 50),
        ]
    )
    expected = np.stack([rz(y) @ ry(p) @ rx(r) for r, p, y in rpy])
    np.testing.assert_allclose(so3.rpy_to_matrix(rpy), expected, atol=1e-15)
    np.testing.assert_allclose(so3.matrix_to_rpy(expected), rpy, atol=1e-12)
    # yaw 90 deg maps x to y; pitch 90 deg maps x to -z
    np.testing.assert_allclose(
        so3.rpy_to_matrix([0, 0, np.pi / 2]) @ [1, 0, 0], [0, 1, 0], atol=1e-16
    )
    np.testing.assert_allclose(
        so3.rpy_to_matrix([0, np.pi / 2, 0]) @ [1, 0, 0], [0, 0, -1], atol=1e-16
    )
    # gimbal lock: the returned angles still reproduce the rotation
    locked = so3.rpy_to_matrix([0.3, np.pi / 2, -0.4])
    np.testing.assert_allclose(so3.rpy_to_matrix(so3.matrix_to_rpy(locked)), locked, atol=1e-12)


def test_se3_helpers(rng: np.random.Generator) -> None:
    R_ab = so3.exp(_random_rotvecs(rng, 1))[0]
    t_ab = rng.normal(size=3)
    R_bc = so3.exp(_random_rotvecs(rng, 1))[0]
    t_bc = rng.normal(size=3)
    p_c = rng.normal(size=(100, 3))
    p_b = so3.transform_points(R_bc, t_bc, p_c)
    np.testing.assert_allclose(p_b, p_c @ R_bc.T + t_bc, atol=1e-15)
    R_ac, t_ac = so3.se3_compose(R_ab, t_ab, R_bc, t_bc)
    np.testing.assert_allclose(
        so3.transform_points(R_ac, t_ac, p_c), so3.transform_points(R_ab, t_ab, p_b), atol=1e-14
    )
    R_ca, t_ca = so3.se3_inverse(R_ac, t_ac)
    np.testing.assert_allclose(
        so3.transform_points(R_ca, t_ca, so3.transform_points(R_ac, t_ac, p_c)), p_c, atol=1e-14
    )
    T = so3.se3_to_matrix(R_ac, t_ac)
    np.testing.assert_allclose(T @ so3.se3_to_matrix(R_ca, t_ca), np.eye(4), atol=1e-15)
    R2, t2 = so3.se3_from_matrix(T)
    np.testing.assert_array_equal(R2, R_ac)
    np.testing.assert_array_equal(t2, t_ac)


def test_project_to_so3(rng: np.random.Generator) -> None:
    R = so3.exp(_random_rotvecs(rng, 20))
    np.testing.assert_allclose(so3.project_to_so3(R), R, atol=1e-14)
    noisy = R + 1e-3 * rng.normal(size=R.shape)
    P = so3.project_to_so3(noisy)
    np.testing.assert_allclose(
        P @ np.swapaxes(P, -1, -2), np.broadcast_to(np.eye(3), P.shape), atol=1e-14
    )
    np.testing.assert_allclose(np.linalg.det(P), 1.0, atol=1e-14)
    assert np.abs(P - R).max() < 5e-3


def test_quaternion_matrices_match_scipy_composition() -> None:
    a, b = Rotation.random(5, random_state=3), Rotation.random(5, random_state=4)
    qa, qb = a.as_quat(), b.as_quat()
    expected = (a * b).as_quat()
    for got in (
        so3.quat_multiply(qa, qb),
        np.einsum("nij,nj->ni", so3.quat_left_matrix(qa), qb),
        np.einsum("nij,nj->ni", so3.quat_right_matrix(qb), qa),
    ):
        np.testing.assert_allclose(np.abs(np.sum(got * expected, axis=1)), 1.0, atol=1e-12)
