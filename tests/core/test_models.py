"""Sensor models: forward values against the contract models, analytic Jacobians against central
finite differences entry by entry (relative error < 1e-6 above the floor of :mod:`fd_check`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from fd_check import STEP, assert_jacobian
from fd_check import central_difference as _fd
from scipy.spatial.transform import Rotation

from licalib_cli.geometry.so3 import exp as so3_exp
from licalib_cli.geometry.so3 import quat_exp, quat_multiply
from licalib_cli.models.imu import accel_model, gyro_model, imu_measure, specific_force
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.models.lidar import (
    BeamIntrinsic,
    PointToPlaneGeometry,
    intrinsics_from_array,
    intrinsics_to_array,
    lidar_point,
    lidar_point_terms,
    lidar_point_with_jacobian,
    nominal_intrinsics_array,
    nominal_point,
    point_to_plane,
)
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

ZERO3 = np.zeros(3)


def _fd_sample(f: Callable[[np.ndarray], np.ndarray], x_all: np.ndarray, i: int) -> np.ndarray:
    """(k, 3) central differences of ``f(x_all)[i]`` w.r.t. sample ``i`` of (n, 3) ``x_all``."""

    def one(x: np.ndarray) -> np.ndarray:
        xs = x_all.copy()
        xs[i] = x
        return f(xs)[i]

    return _fd(one, x_all[i])


def _check(analytic: np.ndarray, numeric: np.ndarray, values: np.ndarray, what: str) -> None:
    """Entry-wise check; the scale is that of the differentiated values (at least 1)."""
    assert_jacobian(analytic, numeric, max(float(np.abs(values).max()), 1.0), what=what)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def _random_imu_intrinsics(rng: np.random.Generator) -> ImuIntrinsics:
    return ImuIntrinsics(
        gyro_scale=1.0 + 0.05 * rng.standard_normal(3),
        gyro_misalignment=0.02 * rng.standard_normal(3),
        gyro_rotation=quat_exp(0.03 * rng.standard_normal(3)),
        accel_scale=1.0 + 0.05 * rng.standard_normal(3),
        accel_misalignment=0.02 * rng.standard_normal(3),
        gyro_g_sensitivity=1e-3 * rng.standard_normal((3, 3)),
        gyro_bias=0.01 * rng.standard_normal(3),
        accel_bias=0.1 * rng.standard_normal(3),
    )


def _written_imu_model(k: ImuIntrinsics, omega: np.ndarray, accel: np.ndarray) -> tuple:
    """method.md section 3 written out with matrices: ``S_w M_w R_wI w + A_w a + b_w`` and
    ``S_a M_a a + b_a`` (scipy for ``R_wI``)."""

    def m(x: np.ndarray) -> np.ndarray:
        return np.array([[1.0, x[0], x[1]], [0.0, 1.0, x[2]], [0.0, 0.0, 1.0]])

    r_wi = Rotation.from_quat(k.gyro_rotation).as_matrix()
    k_w = np.diag(k.gyro_scale) @ m(k.gyro_misalignment) @ r_wi
    k_a = np.diag(k.accel_scale) @ m(k.accel_misalignment)
    gyro = omega @ k_w.T + accel @ k.gyro_g_sensitivity.T + k.gyro_bias
    return gyro, accel @ k_a.T + k.accel_bias


def test_the_imu_model_is_the_written_model(rng: np.random.Generator) -> None:
    """gyro_model / accel_model (the solver's) and imu_measure (the simulator's, a thin use of
    them) agree with the model as written in method.md."""
    k = _random_imu_intrinsics(rng)
    omega = rng.standard_normal((20, 3))
    accel = rng.standard_normal((20, 3)) * 5.0
    g_ref, a_ref = _written_imu_model(k, omega, accel)
    g = gyro_model(
        omega,
        accel,
        k.gyro_scale,
        k.gyro_misalignment,
        k.gyro_rotation,
        k.gyro_bias,
        k.gyro_g_sensitivity.reshape(9),
    )
    a = accel_model(accel, k.accel_scale, k.accel_misalignment, k.accel_bias)
    np.testing.assert_allclose(g.value, g_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.value, a_ref, rtol=0, atol=1e-13)
    g_sim, a_sim = imu_measure(k, omega, accel)
    np.testing.assert_array_equal(g_sim, g.value)
    np.testing.assert_array_equal(a_sim, a.value)


def test_gyro_model_jacobians(rng: np.random.Generator) -> None:
    k = _random_imu_intrinsics(rng)
    omega = rng.standard_normal((6, 3))
    accel = rng.standard_normal((6, 3)) * 5.0
    gs = k.gyro_g_sensitivity.reshape(9)
    m = gyro_model(
        omega, accel, k.gyro_scale, k.gyro_misalignment, k.gyro_rotation, k.gyro_bias, gs
    )

    def pred(**kw: np.ndarray) -> np.ndarray:
        args = dict(
            omega=omega,
            accel=accel,
            scale=k.gyro_scale,
            misalignment=k.gyro_misalignment,
            rotation=k.gyro_rotation,
            bias=k.gyro_bias,
            g_sensitivity=gs,
        )
        args.update(kw)
        return gyro_model(**args, jacobians=False).value  # type: ignore[arg-type]

    v = m.value
    _check(m.d_scale, _fd(lambda x: pred(scale=x), k.gyro_scale), v, "scale")
    _check(m.d_misalignment, _fd(lambda x: pred(misalignment=x), k.gyro_misalignment), v, "mis")
    rot = _fd(lambda x: pred(rotation=quat_multiply(k.gyro_rotation, quat_exp(x))), np.zeros(3))
    _check(m.d_rotation, rot, v, "rotation")
    _check(m.d_g_sensitivity, _fd(lambda x: pred(g_sensitivity=x), gs), v, "g-sensitivity")
    # rate and specific-force derivatives (the same matrices for every sample)
    for i in range(6):
        d_om = _fd_sample(lambda x: pred(omega=x), omega, i)
        _check(m.d_omega, d_om, v, f"omega[{i}]")
        d_acc = _fd_sample(lambda x: pred(accel=x), accel, i)
        _check(m.d_accel, d_acc, v, f"accel[{i}]")


def test_accel_model_and_specific_force_jacobians(rng: np.random.Generator) -> None:
    k = _random_imu_intrinsics(rng)
    acc = rng.standard_normal((5, 3)) * 5.0
    m = accel_model(acc, k.accel_scale, k.accel_misalignment, k.accel_bias)
    f = lambda s: accel_model(acc, s, k.accel_misalignment, k.accel_bias).value  # noqa: E731
    _check(m.d_scale, _fd(f, k.accel_scale), m.value, "scale")
    f = lambda x: accel_model(acc, k.accel_scale, x, k.accel_bias).value  # noqa: E731
    _check(m.d_misalignment, _fd(f, k.accel_misalignment), m.value, "misalignment")
    f = lambda b: accel_model(acc, k.accel_scale, k.accel_misalignment, b).value  # noqa: E731
    _check(np.broadcast_to(np.eye(3), (5, 3, 3)), _fd(f, k.accel_bias), m.value, "bias")
    # d a_m / d a_I = S_a M_a (model level), per sample
    f = lambda x: accel_model(x, k.accel_scale, k.accel_misalignment, k.accel_bias).value  # noqa: E731
    for i in range(5):
        _check(m.d_accel, _fd_sample(f, acc, i), m.value, f"accel[{i}]")

    rot = so3_exp(rng.standard_normal((5, 3)))
    p_ddot = rng.standard_normal((5, 3))
    g = np.array([0.3, -0.2, -9.8])
    sf = specific_force(rot, p_ddot, g)
    np.testing.assert_allclose(
        sf.value, np.einsum("nji,nj->ni", rot, p_ddot - g), rtol=0, atol=1e-13
    )
    d_rot = _fd(lambda e: specific_force(rot @ so3_exp(e), p_ddot, g).value, np.zeros(3))
    _check(sf.d_rotation, d_rot, sf.value, "specific force rotation")
    d_g = _fd(lambda x: specific_force(rot, p_ddot, x).value, g)
    _check(-sf.d_acceleration, d_g, sf.value, "specific force gravity")
    for i in range(5):
        d_acc = _fd_sample(lambda x: specific_force(rot, x, g).value, p_ddot, i)
        _check(sf.d_acceleration[i], d_acc, sf.value, f"acceleration[{i}]")


def _random_lidar(rng: np.random.Generator, beams: int = 4) -> tuple[np.ndarray, np.ndarray]:
    phi = np.deg2rad(np.linspace(-15.0, 15.0, beams))
    values = np.column_stack(
        [
            1e-3 * rng.standard_normal(beams),
            1e-3 * rng.standard_normal(beams),
            0.01 * rng.standard_normal(beams),
            0.01 * rng.standard_normal(beams),
            1.0 + 1e-3 * rng.standard_normal(beams),
            0.02 * rng.standard_normal(beams),
        ]
    )
    return phi, values


def _written_lidar_model(
    phi: np.ndarray, values: np.ndarray, beam: np.ndarray, rho: np.ndarray, theta: np.ndarray
) -> np.ndarray:
    """method.md section 4 written out point by point, columns by name."""
    out = []
    for i, r, t in zip(beam, rho, theta, strict=True):
        d = dict(zip(("dphi", "dtheta", "V", "H", "s", "drho"), values[i], strict=True))
        r_bar, p_bar, t_bar = d["s"] * r + d["drho"], phi[i] + d["dphi"], t + d["dtheta"]
        out.append(
            [
                r_bar * np.cos(p_bar) * np.cos(t_bar) + d["H"] * np.sin(t_bar),
                r_bar * np.cos(p_bar) * np.sin(t_bar) - d["H"] * np.cos(t_bar),
                r_bar * np.sin(p_bar) + d["V"],
            ]
        )
    return np.asarray(out)


def test_lidar_point_is_the_written_model_and_its_jacobian(rng: np.random.Generator) -> None:
    """lidar_point_terms (the solver's), lidar_point (the map's) and nominal_point (the
    driver's) agree with the model as written in method.md."""
    phi, values = _random_lidar(rng)
    intr = intrinsics_from_array(phi, values)
    np.testing.assert_array_equal(intrinsics_to_array(intr), values)
    beam = rng.integers(0, 4, 40)
    rho = rng.uniform(1.0, 50.0, 40)
    theta = rng.uniform(-np.pi, np.pi, 40)
    p, jac = lidar_point_with_jacobian(phi, values, beam, rho, theta)
    np.testing.assert_allclose(
        p, _written_lidar_model(phi, values, beam, rho, theta), rtol=0, atol=1e-12
    )
    np.testing.assert_array_equal(lidar_point(intr, beam, rho, theta), p)
    nominal = lidar_point(LidarIntrinsics.nominal(phi), beam, rho, theta)
    np.testing.assert_allclose(nominal_point(rho, theta, phi[beam]), nominal, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(
        nominal_intrinsics_array(4), intrinsics_to_array(LidarIntrinsics.nominal(phi))
    )
    assert jac is not None
    for b in range(4):
        sel = beam == b

        def f(x: np.ndarray, b: int = b, sel: np.ndarray = sel) -> np.ndarray:
            v = values.copy()
            v[b] = x
            return lidar_point_with_jacobian(phi, v, beam[sel], rho[sel], theta[sel], False)[0]

        _check(jac[sel], _fd(f, values[b].copy()), p, f"beam {b}")
    # the vector-Jacobian product used by the residuals equals v^T J
    v = rng.standard_normal((40, 3))
    terms = lidar_point_terms(phi, values, beam, rho, theta, (np.cos(theta), np.sin(theta)))
    np.testing.assert_allclose(terms.point, p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        terms.vjp(v), np.einsum("ni,nij->nj", v, jac), rtol=1e-12, atol=1e-12
    )
    # the horizontal offset is perpendicular to the beam (method.md: minus sign on y)
    zero = nominal_intrinsics_array(1)
    zero[0, BeamIntrinsic.HORIZONTAL_OFFSET] = 0.1
    q, _ = lidar_point_with_jacobian(
        np.zeros(1), zero, np.zeros(1, int), np.array([10.0]), np.array([np.pi / 4]), False
    )
    ray = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0])
    assert abs((q[0] - 10.0 * ray) @ ray) < 1e-12


def test_nominal_intrinsics_round_trip() -> None:
    intr = LidarIntrinsics.nominal(np.deg2rad([-15.0, 0.0, 15.0]))
    arr = intrinsics_to_array(intr)
    np.testing.assert_array_equal(arr[:, BeamIntrinsic.RANGE_SCALE], 1.0)
    back = intrinsics_from_array(intr.nominal_elevation, arr)
    for name in ("elevation_correction", "range_scale", "range_offset", "horizontal_offset"):
        np.testing.assert_array_equal(getattr(back, name), getattr(intr, name))


def test_point_to_plane_jacobians(rng: np.random.Generator) -> None:
    knots = UniformKnots(0.0, 0.1, 12)
    so3 = SO3Spline(knots, quat_exp(np.cumsum(0.2 * rng.standard_normal((12, 3)), axis=0)))
    r3 = R3Spline(knots, np.cumsum(0.3 * rng.standard_normal((12, 3)), axis=0))
    n = 10
    t = rng.uniform(0.05, 0.85, n)
    R_il = so3_exp(rng.standard_normal(3))
    t_il = rng.standard_normal(3) * 0.2
    p_l = rng.standard_normal((n, 3)) * 5.0
    normal = rng.standard_normal((n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.standard_normal(n)

    def geo(
        tt: np.ndarray,
        rot_pert: np.ndarray = ZERO3,
        ext: np.ndarray = ZERO3,
        trans: np.ndarray = t_il,
        pl: np.ndarray = p_l,
        pos_shift: np.ndarray = ZERO3,
    ) -> PointToPlaneGeometry:
        rev = so3.evaluate(tt, order=1)
        pev = r3.evaluate(tt, order=1)
        return point_to_plane(
            rev.rotation @ so3_exp(rot_pert),
            pev.position + pos_shift,
            R_il @ so3_exp(ext),
            trans,
            pl,
            normal,
            offset,
            rev.angular_velocity,
            pev.velocity,
        )

    g = geo(t)
    expected = (
        np.einsum(
            "ni,ni->n",
            normal,
            np.einsum("nij,nj->ni", so3.rotation(t), p_l @ R_il.T + t_il) + r3.position(t),
        )
        + offset
    )
    np.testing.assert_allclose(g.distance, expected, rtol=0, atol=1e-12)
    d = lambda **kw: geo(t, **kw).distance  # noqa: E731
    pairs = [
        (g.d_rotation, _fd(lambda x: d(rot_pert=x), np.zeros(3))),
        (g.d_position, _fd(lambda x: d(pos_shift=x), np.zeros(3))),
        (g.d_ext_rotation, _fd(lambda x: d(ext=x), np.zeros(3))),
        (g.d_ext_translation, _fd(lambda x: d(trans=x), t_il.copy())),
    ]
    # rounding follows the terms of the distance: |R p_I|, |p|, |d| (a few metres)
    scale = float(np.abs(p_l).max() + np.abs(r3.position(t)).max() + np.abs(offset).max())
    names = ("rotation", "position", "ext rotation", "ext translation")
    for name, (analytic, numeric) in zip(names, pairs, strict=True):
        # a shared perturbation of all points: every row is the derivative of its own point
        assert_jacobian(analytic, numeric, scale, what=name)
    # the point in {L}: every point (each distance depends on its own point only)
    d_pl = _fd(lambda x: d(pl=p_l + x), np.zeros(3))
    assert_jacobian(g.d_point, d_pl, scale, what="point")
    d_t = (geo(t + STEP).distance - geo(t - STEP).distance) / (2 * STEP)
    assert g.d_time is not None
    assert_jacobian(g.d_time, d_t, scale, what="time")
