"""The plane coordinates of the planes-free refinement: derivatives against finite differences."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from licalib_cli.estimation import Planes
from licalib_cli.pipeline.free_planes import plane_jacobian, stepped_planes


def _planes(rng: np.random.Generator, num: int) -> Planes:
    normal = rng.standard_normal((num, 3))
    normal[0] = [0.0, 0.05, 1.0]  # near the switch of the tangent basis
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return Planes(normal=normal, d=rng.uniform(0.5, 6.0, num), thickness=np.full(num, 0.01))


def _distances(points: np.ndarray, plane: np.ndarray, planes: Planes) -> np.ndarray:
    return np.einsum("ni,ni->n", planes.normal[plane], points) + planes.d[plane]


@pytest.mark.parametrize("seed", [0, 1])
def test_plane_jacobian_matches_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    planes = _planes(rng, 5)
    plane = np.repeat(np.arange(5), 40)
    points = rng.uniform(-8.0, 8.0, (plane.size, 3))
    jac, centroid = plane_jacobian(points, plane, planes.normal)
    for p in range(5):
        np.testing.assert_allclose(centroid[p], points[plane == p].mean(axis=0))
    base = _distances(points, plane, planes)
    eps = 1e-6
    for j in range(3):
        dp = np.zeros((5, 3))
        dp[:, j] = eps
        plus = _distances(points, plane, stepped_planes(planes, centroid, dp))
        minus = _distances(points, plane, stepped_planes(planes, centroid, -dp))
        np.testing.assert_allclose((plus - minus) / (2 * eps), jac[:, j], atol=1e-6)
    # a zero step keeps the planes; any step keeps unit normals
    same = stepped_planes(planes, centroid, np.zeros((5, 3)))
    np.testing.assert_allclose(_distances(points, plane, same), base, atol=1e-12)
    moved = stepped_planes(planes, centroid, 0.1 * rng.standard_normal((5, 3)))
    np.testing.assert_allclose(np.linalg.norm(moved.normal, axis=1), 1.0)
    assert moved.thickness is planes.thickness


def test_an_offset_step_moves_the_plane_along_its_normal_at_the_centroid() -> None:
    rng = np.random.default_rng(4)
    planes = _planes(rng, 3)
    plane = np.repeat(np.arange(3), 10)
    points = rng.uniform(-3.0, 3.0, (30, 3))
    _, centroid = plane_jacobian(points, plane, planes.normal)
    dp = np.zeros((3, 3))
    dp[:, 2] = 0.004
    moved = stepped_planes(planes, centroid, dp)
    np.testing.assert_allclose(moved.normal, planes.normal)
    np.testing.assert_allclose(moved.d - planes.d, 0.004)


class _Cost:
    """A stand-in for a problem: only its cost is read by planes_free_steps."""

    def __init__(self, cost: float) -> None:
        self.cost = cost

    def evaluate(self, jacobians: bool = False) -> _Cost:
        return self


def _exact_steps(cost: Callable[[int], float]):  # type: ignore[no-untyped-def]
    """A ``step_at`` for planes_free_steps whose estimate ``k`` costs ``cost(k)`` and whose step
    predicts its gain exactly, and the list of the estimates it linearised at."""
    from types import SimpleNamespace

    calls: list[int] = []

    def step_at(problem: _Cost, k: int):  # type: ignore[no-untyped-def]
        calls.append(k)
        step = SimpleNamespace(predicted_reduction=cost(k) - cost(k + 1), num_truncated=0)
        return cost(k), step, lambda fraction: (k + 1, _Cost(cost(k + 1)))

    return step_at, calls


def test_planes_free_steps_stop_when_the_next_step_is_expected_to_gain_too_little() -> None:
    """Linear convergence (each step gains a thousandth of the one before): after the second
    step the third is expected to gain 1e-4 of a cost of 1000, below the 1e-6 relative
    tolerance, so it is not linearised; the first step's own gain keeps the steps going."""
    from licalib_cli.pipeline.free_planes import planes_free_steps

    def cost(k: int) -> float:
        return 1000.0 + 100.0 * 0.001**k

    step_at, calls = _exact_steps(cost)
    final, problem, steps, start = planes_free_steps(_Cost(cost(0)), 0, step_at, "step")
    assert calls == [0, 1]
    assert (final, steps, start) == (2, 2, cost(0))
    assert problem.cost == cost(2)


def test_planes_free_steps_stop_once_a_step_is_worth_under_a_third_of_a_sigma() -> None:
    """Gains 30, 0.9, 0.027, ... of a cost of 1000: after the second step the third is expected
    to gain 0.027, above the relative tolerance (1e-3) but below MIN_GAIN (a move of under a
    third of a sigma), so it is not linearised."""
    from licalib_cli.pipeline.free_planes import MIN_GAIN, RELATIVE_DECREASE, planes_free_steps

    def cost(k: int) -> float:
        return 1000.0 + 1000.0 * 0.03 ** (k + 1) / 0.97

    third = (cost(2) - cost(3)) * 1.0001
    assert RELATIVE_DECREASE * cost(2) < third < MIN_GAIN
    step_at, calls = _exact_steps(cost)
    final, _, steps, _ = planes_free_steps(_Cost(cost(0)), 0, step_at, "step")
    assert calls == [0, 1]
    assert (final, steps) == (2, 2)


def test_planes_free_steps_take_none_worth_under_a_third_of_a_sigma() -> None:
    """A first step predicted to gain 0.04 of a cost of 10: above the relative tolerance, below
    MIN_GAIN: not taken."""
    from types import SimpleNamespace

    from licalib_cli.pipeline.free_planes import planes_free_steps

    def step_at(problem: _Cost, k: int):  # type: ignore[no-untyped-def]
        step = SimpleNamespace(predicted_reduction=0.04, num_truncated=0)
        return 10.0, step, lambda fraction: (k + 1, _Cost(9.96))

    final, _, steps, start = planes_free_steps(_Cost(10.0), 0, step_at, "step")
    assert (final, steps, start) == (0, 0, 10.0)


def test_a_step_past_the_spline_s_padding_is_rejected_and_a_shorter_one_tried() -> None:
    """A whole step that moves the time offset past the spline's padding cannot be built into a
    problem (the point times leave the spline); it is a rejected trial like one that raises the
    cost, and half the step is tried (it was an internal error, on a bag read with a wrong
    accelerometer unit)."""
    from types import SimpleNamespace

    from licalib_cli.estimation import SplineCoverageError
    from licalib_cli.pipeline.free_planes import planes_free_steps

    tried: list[float] = []

    def step_at(problem: _Cost, k: int):  # type: ignore[no-untyped-def]
        def trial(fraction: float):  # type: ignore[no-untyped-def]
            tried.append(fraction)
            if fraction == 1.0:
                raise SplineCoverageError("89 point times fall outside the trajectory spline")
            return k + 1, _Cost(5.0)

        step = SimpleNamespace(predicted_reduction=5.0 if k == 0 else 0.0, num_truncated=0)
        return (10.0 if k == 0 else 5.0), step, trial

    final, problem, steps, start = planes_free_steps(_Cost(10.0), 0, step_at, "step")
    assert tried == [1.0, 0.5]
    assert (final, steps, start, problem.cost) == (1, 1, 10.0, 5.0)


def test_noise_corrected_plane_steps_remove_the_range_noise_tilt() -> None:
    """A patch seen obliquely from one point, its range noise along the rays: a Gauss-Newton
    step of the plane from its true normal tilts the normal away from the rays on average; with
    the noise's expected part removed (``noise_corrected``) the mean tilt is zero."""
    import scipy.sparse as sp

    from licalib_cli.pipeline.free_planes import noise_corrected, noise_corrected_gradient
    from licalib_cli.solver import s2_basis
    from licalib_cli.solver.nuisance import NuisanceTerms

    rng = np.random.default_rng(7)
    normal = np.array([[-1.0, 0.0, 0.0]])  # the wall x = 1.5, facing the sensor at the origin
    sigma, n = 0.05, 400
    plain, corrected = [], []
    for _ in range(200):
        wall = np.column_stack(
            [np.full(n, 1.5), rng.uniform(1.0, 2.0, n), rng.uniform(-0.5, 0.5, n)]
        )
        rays = wall / np.linalg.norm(wall, axis=1, keepdims=True)
        points = wall + rays * (sigma * rng.standard_normal(n))[:, None]
        plane = np.zeros(n, dtype=np.intp)
        jac, _ = plane_jacobian(points, plane, normal)
        r = points @ normal[0] + 1.5
        r -= r.mean()  # the offset at the centroid, solved with the normal
        jac = jac / sigma  # whitened
        terms = NuisanceTerms(
            sp.csr_matrix((0, 3)),
            (jac.T @ jac)[None],
            (jac.T @ (r / sigma))[None],
        )
        fixed = noise_corrected(terms, plane, normal, rays, np.ones(n))
        # the gradient alone (the chord steps' path) is the terms' gradient
        np.testing.assert_array_equal(
            noise_corrected_gradient(terms.g_p, plane, normal, rays, np.ones(n)), fixed.g_p
        )
        for out, t in ((plain, terms), (corrected, fixed)):
            step = -np.linalg.solve(t.H_pp[0], t.g_p[0])
            out.append(s2_basis(normal)[0] @ step[:2])  # the normal's change
    tilt_plain, tilt_corrected = np.array(plain)[:, 1], np.array(corrected)[:, 1]
    se = tilt_plain.std() / np.sqrt(tilt_plain.size)
    assert tilt_plain.mean() > 8 * se  # the bias: the normal turns away from the rays (+y)
    assert abs(tilt_corrected.mean()) < 3 * se
