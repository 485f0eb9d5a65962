"""Parameter blocks and retractions: round trips, norms, names, fixed masks, layout."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.geometry.so3 import exp as so3_exp
from licalib_cli.geometry.so3 import quat_to_matrix
from licalib_cli.solver import ParameterBlock, Problem, local, retract, s2_retraction_jacobian
from licalib_cli.solver.parameters import s2_basis


def _random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


@pytest.mark.parametrize("magnitude", [1e-9, 1e-3, 0.5, 3.0])
def test_so3_retraction_is_right_perturbation_and_round_trips(magnitude: float) -> None:
    rng = np.random.default_rng(1)
    q = _random_quats(rng, 50)
    d = rng.standard_normal((50, 3))
    d *= magnitude / np.linalg.norm(d, axis=1, keepdims=True)
    q1 = retract("so3", q, d)
    # R(q [+] d) == R(q) Exp(d), to 1e-12
    np.testing.assert_allclose(quat_to_matrix(q1), quat_to_matrix(q) @ so3_exp(d), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q1, axis=1), 1.0, atol=1e-14)
    # local(q, q [+] d) == d (|d| < pi)
    np.testing.assert_allclose(local("so3", q, q1), d, atol=1e-12)


def test_so3_local_then_retract_reaches_target() -> None:
    rng = np.random.default_rng(2)
    q0, q1 = _random_quats(rng, 40), _random_quats(rng, 40)
    back = retract("so3", q0, local("so3", q0, q1))
    np.testing.assert_allclose(quat_to_matrix(back), quat_to_matrix(q1), atol=1e-12)


def test_s2_keeps_norm_and_round_trips() -> None:
    rng = np.random.default_rng(3)
    v = rng.standard_normal((60, 3)) * 9.81
    v[0] = [0.0, 0.0, -9.81]  # axis-aligned cases use the other helper axis
    v[1] = [1e-3, 0.0, 9.81]
    d = rng.uniform(-1.0, 1.0, (60, 2))
    v1 = retract("s2", v, d)
    np.testing.assert_allclose(np.linalg.norm(v1, axis=1), np.linalg.norm(v, axis=1), rtol=1e-14)
    np.testing.assert_allclose(local("s2", v, v1), d, atol=1e-12)
    # rotation angle equals |d|
    cos = np.sum(v * v1, axis=1) / np.sum(v * v, axis=1)
    np.testing.assert_allclose(np.arccos(np.clip(cos, -1, 1)), np.linalg.norm(d, axis=1), atol=1e-7)


def test_s2_basis_and_jacobian() -> None:
    rng = np.random.default_rng(4)
    v = rng.standard_normal((20, 3)) * 3.0
    b = s2_basis(v)
    np.testing.assert_allclose(
        np.einsum("nki,nkj->nij", b, b), np.broadcast_to(np.eye(2), (20, 2, 2)), atol=1e-14
    )
    np.testing.assert_allclose(np.einsum("nk,nki->ni", v, b), 0.0, atol=1e-13)
    jac = s2_retraction_jacobian(v)
    h = 1e-6
    for k in range(2):
        e = np.zeros((20, 2))
        e[:, k] = h
        fd = (retract("s2", v, e) - retract("s2", v, -e)) / (2 * h)
        np.testing.assert_allclose(jac[..., k], fd, atol=1e-8)


def test_euclidean_round_trip() -> None:
    rng = np.random.default_rng(5)
    x, d = rng.standard_normal((7, 6)), rng.standard_normal((7, 6))
    np.testing.assert_allclose(local("euclidean", x, retract("euclidean", x, d)), d, atol=1e-15)


def test_block_shapes_names_and_scales() -> None:
    so3 = ParameterBlock("ext.rot", [0, 0, 0, 2.0], manifold="so3", group="calibration", scale=1e-3)
    assert so3.size == 3 and so3.coord_names == ("ext.rot.rx", "ext.rot.ry", "ext.rot.rz")
    np.testing.assert_allclose(so3.value, [0, 0, 0, 1])  # normalised
    assert so3.value.shape == (4,)
    dt = ParameterBlock("time_offset", 0.0, group="calibration", scale=1e-3)
    assert dt.size == 1 and dt.coord_names == ("time_offset",) and dt.value.shape == ()
    pts = ParameterBlock("r3", np.zeros((5, 3)))
    assert pts.size == 15 and pts.coord_names[4] == "r3[1].y"
    lidar = ParameterBlock("lidar", np.zeros((2, 6)), scale=[1e-3, 1e-3, 1e-2, 1e-2, 1e-3, 1e-2])
    np.testing.assert_allclose(lidar.scale[6:], [1e-3, 1e-3, 1e-2, 1e-2, 1e-3, 1e-2])
    g = ParameterBlock("gravity", [0, 0, -9.81], manifold="s2")
    assert g.size == 2
    with pytest.raises(ValueError, match="4 numbers"):
        ParameterBlock("bad", np.zeros(3), manifold="so3")
    with pytest.raises(ValueError, match="coordinate names"):
        ParameterBlock("bad", np.zeros(3), coord_names=["a"])


def test_block_retracted_and_local_on_blocks() -> None:
    g = ParameterBlock("gravity", [0.0, 0.0, -9.81], manifold="s2")
    new = g.retracted([0.1, -0.2])
    assert new.shape == (3,)
    assert np.linalg.norm(new) == pytest.approx(9.81, rel=1e-14)
    np.testing.assert_allclose(g.local(new), [0.1, -0.2], atol=1e-12)


def test_fix_free_by_name_and_layout_removes_fixed() -> None:
    pr = Problem()
    traj = pr.add_parameter_block(ParameterBlock("traj", np.zeros((3, 2))))
    cal = pr.add_parameter_block(
        ParameterBlock("cal", np.zeros(3), group="calibration", scale=0.01)
    )
    pre = pr.add_parameter_block(ParameterBlock("bias", np.zeros(2)))
    cal.fix(["cal.y"])
    traj.fix([0, 1])
    lay = pr.layout()
    assert lay.block_names == ("traj", "bias", "cal")  # trajectory group first
    assert lay.num_trajectory == 4 + 2 and lay.num_calibration == 2
    assert lay.calibration_names == ("cal.x", "cal.z")
    np.testing.assert_array_equal(lay.index["cal"], [6, -1, 7])
    np.testing.assert_array_equal(lay.index["traj"], [-1, -1, 0, 1, 2, 3])
    np.testing.assert_allclose(lay.calibration_scale, [0.01, 0.01])
    cal.free()
    pre.fix()
    lay2 = pr.layout()
    assert lay2.num_trajectory == 4 and lay2.num_calibration == 3
    # a step in reduced coordinates leaves fixed coordinates untouched
    dx = np.arange(1.0, 8.0)
    vals = pr.retracted_values(dx, lay2)
    np.testing.assert_allclose(vals["traj"], [[0, 0], [1, 2], [3, 4]])
    np.testing.assert_allclose(vals["bias"], [0, 0])
    np.testing.assert_allclose(vals["cal"], [5, 6, 7])
