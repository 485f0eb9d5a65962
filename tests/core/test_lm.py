"""Levenberg-Marquardt, assembly, Schur + TSVD step, robust loss, fixed coordinates, stds.

The test model is a small curve fit with the structure of the calibration problem: a cubic
B-spline of R3 control points (trajectory group), observed directly ("imu-like", 3-vector
residuals), and through a sensor with an unknown rotation (so3), translation and scale
(calibration group): ``z = s R^T (p(t) - t)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
import pytest

from licalib_cli.errors import SolverError
from licalib_cli.geometry.so3 import exp as so3_exp
from licalib_cli.geometry.so3 import hat, matrix_to_quat, quat_to_matrix
from licalib_cli.solver import (
    DenseJacobian,
    HuberLoss,
    LMParams,
    ParameterBlock,
    Problem,
    ResidualEval,
    compute_step,
    local,
    solve,
)
from licalib_cli.solver.lm import SolverReport, widen_along_truncated


def _basis(u: np.ndarray) -> np.ndarray:
    """(n, 4) uniform cubic B-spline weights."""
    return np.stack(
        [
            (1 - u) ** 3 / 6,
            (3 * u**3 - 6 * u**2 + 4) / 6,
            (-3 * u**3 + 3 * u**2 + 3 * u + 1) / 6,
            u**3 / 6,
        ],
        axis=1,
    )


@dataclass
class Samples:
    seg: np.ndarray  # (n,) first control point
    w: np.ndarray  # (n, 4) weights
    meas: np.ndarray  # (n, 3)

    @property
    def elements(self) -> np.ndarray:
        return self.seg[:, None] + np.arange(4)


def _position(params: Mapping[str, np.ndarray], s: Samples) -> np.ndarray:
    ctrl = params["ctrl"]
    return np.einsum("nj,njk->nk", s.w, ctrl[s.elements])


class DirectResidual:
    """``r = (p(t) - y) / sigma``."""

    def __init__(self, samples: Samples, sigma: float) -> None:
        self.name = "direct"
        self.s, self.sigma = samples, sigma

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        r = (_position(params, self.s) - self.s.meas) / self.sigma
        jac = np.einsum("nj,ik->nijk", self.s.w, np.eye(3)) / self.sigma  # (n, 3, 4, 3)
        return ResidualEval(r, (DenseJacobian("ctrl", self.s.elements, jac),))


class SensorResidual:
    """``r = (s R^T (p(t) - t) - z) / sigma`` with R right-perturbed."""

    def __init__(self, samples: Samples, sigma: float, sparse: bool = False) -> None:
        self.name = "sensor"
        self.s, self.sigma, self.sparse = samples, sigma, sparse

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        rot = quat_to_matrix(params["rot"])
        trans, scale = params["trans"], float(params["scale"])
        v = (_position(params, self.s) - trans) @ rot  # R^T (p - t), (n, 3)
        r = (scale * v - self.s.meas) / self.sigma
        if not jacobians:
            return ResidualEval(r)
        n = r.shape[0]
        k = scale / self.sigma
        zero = np.zeros((n, 1), dtype=int)
        j_ctrl = k * np.einsum("nj,ki->nijk", self.s.w, rot)  # s R^T w_j
        j_rot = (k * hat(v))[:, :, None, :]
        j_trans = np.broadcast_to(-k * rot.T, (n, 3, 3))[:, :, None, :]
        j_scale = (v / self.sigma)[:, :, None, None]
        pieces = (
            DenseJacobian("ctrl", self.s.elements, j_ctrl),
            DenseJacobian("rot", zero, j_rot),
            DenseJacobian("trans", zero, np.ascontiguousarray(j_trans)),
            DenseJacobian("scale", zero, j_scale),
        )
        if self.sparse:
            pieces = tuple(p.to_coo() for p in pieces)
        return ResidualEval(r, pieces)


@dataclass
class Truth:
    ctrl: np.ndarray
    rot: np.ndarray
    trans: np.ndarray
    scale: float


def make_problem(
    rng: np.random.Generator,
    *,
    num_ctrl: int = 12,
    n_direct: int = 150,
    n_sensor: int = 150,
    sigma_direct: float = 0.01,
    sigma_sensor: float = 0.01,
    noise: bool = True,
    outliers: float = 0.0,
    perturb: bool = True,
    loss: HuberLoss | None = None,
    sparse: bool = False,
) -> tuple[Problem, Truth]:
    ctrl = rng.uniform(-3.0, 3.0, (num_ctrl, 3))
    truth = Truth(
        ctrl,
        matrix_to_quat(so3_exp(np.array([0.3, -0.5, 1.2]))),
        np.array([0.4, -0.2, 0.1]),
        1.02,
    )

    def samples(n: int, sigma: float) -> Samples:
        t = rng.uniform(0.0, num_ctrl - 3.0, n)
        seg = np.minimum(t.astype(int), num_ctrl - 4)
        return Samples(seg, _basis(t - seg), np.zeros((n, 3)))

    direct, sensor = samples(n_direct, sigma_direct), samples(n_sensor, sigma_sensor)
    tv = {"ctrl": ctrl, "rot": truth.rot, "trans": truth.trans, "scale": np.array(truth.scale)}
    direct.meas = _position(tv, direct) + noise * rng.normal(0, sigma_direct, (n_direct, 3))
    z = truth.scale * (_position(tv, sensor) - truth.trans) @ quat_to_matrix(truth.rot)
    sensor.meas = z + noise * rng.normal(0, sigma_sensor, (n_sensor, 3))
    if outliers:
        bad = rng.random(n_sensor) < outliers
        sensor.meas[bad] += rng.uniform(0.3, 1.0, (int(bad.sum()), 3))
    pr = Problem()
    d = 1.0 if perturb else 0.0
    pr.add_parameter_block(ParameterBlock("ctrl", ctrl + d * rng.normal(0, 0.1, ctrl.shape)))
    rot0 = matrix_to_quat(quat_to_matrix(truth.rot) @ so3_exp(d * np.array([0.05, -0.04, 0.06])))
    pr.add_parameter_block(
        ParameterBlock("rot", rot0, manifold="so3", group="calibration", scale=1e-2)
    )
    pr.add_parameter_block(
        ParameterBlock("trans", truth.trans + d * 0.1, group="calibration", scale=5e-2)
    )
    pr.add_parameter_block(
        ParameterBlock("scale", truth.scale + d * 0.05, group="calibration", scale=1e-2)
    )
    pr.add_residual_block(DirectResidual(direct, sigma_direct))
    pr.add_residual_block(SensorResidual(sensor, sigma_sensor, sparse), loss=loss)
    return pr, truth


def _errors(pr: Problem, truth: Truth) -> dict[str, float]:
    return {
        "rot": float(np.linalg.norm(local("so3", truth.rot[None], pr["rot"].value[None]))),
        "trans": float(np.linalg.norm(pr["trans"].value - truth.trans)),
        "scale": abs(float(pr["scale"].value) - truth.scale),
        "ctrl": float(np.abs(pr["ctrl"].value - truth.ctrl).max()),
    }


def _dense_jacobian(pr: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Whitened, IRLS-reweighted dense J and r built independently from COO triplets."""
    lay = pr.layout()
    vals = pr.values()
    blocks_j, blocks_r = [], []
    for res, loss in zip(pr.residual_blocks, pr._losses, strict=True):
        ev = res.evaluate(vals)
        n, m = ev.residuals.shape
        w = np.ones(n) if loss is None else loss(np.sum(ev.residuals**2, axis=1))[1]
        jd = np.zeros((n * m, lay.num_free))
        for piece in ev.jacobians:
            coo = piece.to_coo() if isinstance(piece, DenseJacobian) else piece
            cols = lay.index[piece.block][coo.cols]
            keep = cols >= 0
            np.add.at(jd, (coo.rows[keep], cols[keep]), coo.values[keep])
        sw = np.repeat(np.sqrt(w), m)
        blocks_j.append(jd * sw[:, None])
        blocks_r.append(ev.residuals.reshape(-1) * sw)
    return np.vstack(blocks_j), np.concatenate(blocks_r)


def test_lm_converges_to_truth_noise_free() -> None:
    pr, truth = make_problem(np.random.default_rng(10), noise=False)
    report = solve(pr, LMParams(max_iterations=30, step_tolerance=1e-10))
    assert report.status == "converged", report.reason
    err = _errors(pr, truth)
    assert err["rot"] < 1e-8 and err["trans"] < 1e-8 and err["scale"] < 1e-8 and err["ctrl"] < 1e-8
    assert report.final_cost < 1e-12
    assert report.cost_history[0] > 1e3
    assert all(np.diff(report.cost_history) <= 0.0)
    assert report.truncated == ()
    assert np.all(report.observable) and np.all(np.isfinite(report.std))


def test_a_given_starting_evaluation_is_used_instead_of_evaluating_again() -> None:
    """``solve_with_linearization`` started from the caller's evaluation at the current values
    takes the same steps to the same estimate, with one evaluation fewer."""
    from licalib_cli.solver.lm import solve_with_linearization

    params = LMParams(max_iterations=30, step_tolerance=1e-10)
    plain, _ = make_problem(np.random.default_rng(11))
    given, _ = make_problem(np.random.default_rng(11))
    calls = {"plain": 0, "given": 0}

    def counted(problem: Problem, key: str) -> None:
        evaluate = problem.evaluate

        def counting(*args, **kwargs):  # type: ignore[no-untyped-def]
            calls[key] += 1
            return evaluate(*args, **kwargs)

        problem.evaluate = counting  # type: ignore[method-assign]

    start = given.evaluate(jacobians=True)
    counted(plain, "plain")
    counted(given, "given")
    first = solve_with_linearization(plain, params)
    second = solve_with_linearization(given, params, evaluation=start)
    assert calls["given"] == calls["plain"] - 1
    assert second.report.cost_history == first.report.cost_history
    for name in ("ctrl", "rot", "trans", "scale"):
        np.testing.assert_array_equal(given[name].value, plain[name].value)


def test_assembly_matches_dense_reference_with_fixed_coords_and_huber() -> None:
    rng = np.random.default_rng(11)
    pr, _ = make_problem(rng, outliers=0.2, loss=HuberLoss(2.0))
    pr["ctrl"].fix([0, 1, 2, 7])
    pr["trans"].fix(["trans.y"])
    ev = pr.evaluate()
    lin = pr.linearize(ev)
    j, r = _dense_jacobian(pr)
    assert j.shape[1] == 12 * 3 - 4 + 3 + 2 + 1
    np.testing.assert_allclose(lin.dense(), j.T @ j, rtol=1e-12, atol=1e-9 * np.abs(j.T @ j).max())
    np.testing.assert_allclose(lin.g, j.T @ r, rtol=1e-12, atol=1e-9 * np.abs(j.T @ r).max())
    # the COO (scipy.sparse) path gives the same normal equations
    pr_sparse, _ = make_problem(
        np.random.default_rng(11), outliers=0.2, loss=HuberLoss(2.0), sparse=True
    )
    pr_sparse["ctrl"].fix([0, 1, 2, 7])
    pr_sparse["trans"].fix(["trans.y"])
    lin_sparse = pr_sparse.linearize(pr_sparse.evaluate())
    np.testing.assert_allclose(lin_sparse.dense(), lin.dense(), atol=1e-9 * np.abs(j.T @ j).max())
    np.testing.assert_allclose(lin_sparse.g, lin.g, atol=1e-9 * np.abs(lin.g).max())
    # Huber cost: 0.5 sum rho(|r|^2)
    s = np.sum(pr.residual_blocks[1].evaluate(pr.values()).residuals ** 2, axis=1)
    huber = np.where(s <= 4.0, s, 4.0 * np.sqrt(s) - 4.0)
    direct = np.sum(pr.residual_blocks[0].evaluate(pr.values()).residuals ** 2)
    assert ev.cost == pytest.approx(0.5 * (direct + huber.sum()), rel=1e-12)


def test_schur_tsvd_step_equals_full_lstsq_when_nothing_truncated() -> None:
    pr, _ = make_problem(np.random.default_rng(12))
    lin = pr.linearize(pr.evaluate())
    j, r = _dense_jacobian(pr)
    reference = np.linalg.lstsq(j, -r, rcond=None)[0]
    step = compute_step(lin, 0.0, LMParams(tsvd_threshold=1e-9))
    assert step.num_truncated == 0
    np.testing.assert_allclose(step.dx, reference, rtol=1e-7, atol=1e-9 * np.abs(reference).max())
    plain = compute_step(lin, 0.0, LMParams(use_tsvd=False))
    np.testing.assert_allclose(plain.dx, reference, rtol=1e-7, atol=1e-9 * np.abs(reference).max())
    # predicted reduction of the Gauss-Newton step is 0.5 |J dx|^2
    assert step.predicted_reduction == pytest.approx(0.5 * np.sum((j @ reference) ** 2), rel=1e-8)


def test_huber_downweights_outliers() -> None:
    errs = {}
    for name, loss in (("huber", HuberLoss(2.0)), ("plain", None)):
        pr, truth = make_problem(np.random.default_rng(13), outliers=0.15, loss=loss)
        report = solve(pr, LMParams(max_iterations=100))
        assert report.status == "converged", report.reason
        errs[name] = _errors(pr, truth)
    # 15 % one-sided outliers of 0.3-1 m: Huber stays within a few millimetres (2.8 mm here),
    # plain least squares is pulled off by decimetres (0.20 m here)
    assert errs["huber"]["trans"] < 1e-2, errs
    assert errs["plain"]["trans"] > 5.0 * errs["huber"]["trans"], errs
    assert errs["plain"]["trans"] > 5e-2, errs


def test_fixed_coordinates_do_not_move_and_can_be_freed() -> None:
    pr, truth = make_problem(np.random.default_rng(14), noise=False)
    scale0 = float(pr["scale"].value)
    trans0 = pr["trans"].value.copy()
    ctrl0 = pr["ctrl"].value.copy()
    pr["scale"].fix()
    pr["trans"].fix(["trans.x"])
    pr["ctrl"].fix([0, 1, 2])
    report = solve(pr, LMParams(max_iterations=30, step_tolerance=1e-10))
    assert report.status == "converged", report.reason
    assert float(pr["scale"].value) == scale0
    assert pr["trans"].value[0] == trans0[0]
    np.testing.assert_array_equal(pr["ctrl"].value[0], ctrl0[0])
    assert "scale" not in report.calibration_names and "trans.x" not in report.calibration_names
    assert report.final_cost > 1.0  # the wrong fixed values leave residuals
    pr["scale"].free()
    pr["trans"].free()
    pr["ctrl"].free()
    report = solve(pr, LMParams(max_iterations=50, step_tolerance=1e-10))
    assert report.status == "converged", report.reason
    err = _errors(pr, truth)
    assert err["scale"] < 1e-8 and err["trans"] < 1e-8 and err["rot"] < 1e-8
    assert len(report.calibration_names) == 7


def test_non_finite_initial_cost_raises() -> None:
    pr, _ = make_problem(np.random.default_rng(15))
    pr["trans"].set_value([np.nan, 0.0, 0.0])
    with pytest.raises(SolverError, match="not finite"):
        solve(pr)


# --------------------------------------------------------------------- rank-deficient problem
class OffsetResidual:
    """Chain values ``x_k`` seen through ``y = x_k + a + 2 b`` (a, b only as a + 2b) and a
    coordinate ``c`` seen only very weakly."""

    def __init__(self, k: np.ndarray, y: np.ndarray, sigma: float) -> None:
        self.name = "offset"
        self.k, self.y, self.sigma = k, y, sigma

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        a, b = params["offset"]
        r = (params["chain"][self.k, 0] + a + 2 * b - self.y) / self.sigma
        n = r.size
        jx = np.full((n, 1, 1, 1), 1.0 / self.sigma)
        jo = np.broadcast_to(np.array([1.0, 2.0]) / self.sigma, (n, 1, 1, 2))
        zero = np.zeros((n, 1), dtype=int)
        return ResidualEval(
            r,
            (
                DenseJacobian("chain", self.k[:, None], jx),
                DenseJacobian("offset", zero, np.ascontiguousarray(jo)),
            ),
        )


class ChainResidual:
    """Direct observations of the chain (sigma 0.01) and a very weak one of ``c`` (sigma 100)."""

    def __init__(self, y: np.ndarray, c_meas: float) -> None:
        self.name = "chain"
        self.y, self.c_meas = y, c_meas

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        x = params["chain"][:, 0]
        n = x.size
        r = np.concatenate([(x - self.y) / 0.01, [(float(params["weak"]) - self.c_meas) / 100.0]])
        jx = np.zeros((n + 1, 1, 1, 1))
        jx[:n] = 100.0
        jc = np.zeros((n + 1, 1, 1, 1))
        jc[n] = 0.01
        el = np.concatenate([np.arange(n), [0]])[:, None]
        return ResidualEval(
            r,
            (
                DenseJacobian("chain", el, jx),
                DenseJacobian("weak", np.zeros((n + 1, 1), dtype=int), jc),
            ),
        )


def make_rank_deficient(rng: np.random.Generator) -> Problem:
    n = 30
    x_true = rng.normal(0, 1, n)
    a_true, b_true, c_true = 0.1, 0.2, -0.3
    k = rng.integers(0, n, 200)
    pr = Problem()
    pr.add_parameter_block(ParameterBlock("chain", np.zeros((n, 1))))
    pr.add_parameter_block(
        ParameterBlock(
            "offset", [0.3, -0.2], group="calibration", coord_names=["offset.a", "offset.b"]
        )
    )
    pr.add_parameter_block(ParameterBlock("weak", 0.5, group="calibration"))
    y_off = x_true[k] + a_true + 2 * b_true + rng.normal(0, 0.01, k.size)
    pr.add_residual_block(OffsetResidual(k, y_off, 0.01))
    pr.add_residual_block(ChainResidual(x_true + rng.normal(0, 0.01, n), c_true))
    return pr


def test_tsvd_keeps_unobservable_directions_and_names_them() -> None:
    pr = make_rank_deficient(np.random.default_rng(16))
    report = solve(pr, LMParams(max_iterations=20, tsvd_threshold=1.0))
    assert report.status == "converged", report.reason
    a, b = pr["offset"].value
    # the observable combination is fitted, the null direction (2, -1)/sqrt(5) stays at 0.8
    assert a + 2 * b == pytest.approx(0.5, abs=5e-3)
    assert 2 * a - b == pytest.approx(2 * 0.3 + 0.2, abs=1e-9)
    assert float(pr["weak"].value) == pytest.approx(0.5, abs=1e-9)
    assert len(report.truncated) == 2
    weakest, second = report.truncated  # weakest first: the exact null direction
    np.testing.assert_allclose(weakest.vector, np.array([2.0, -1.0, 0.0]) / np.sqrt(5), atol=1e-6)
    np.testing.assert_allclose(second.vector, [0.0, 0.0, 1.0], atol=1e-6)
    assert (
        weakest.text
        == "offset along [0.89, -0.45]: unobservable, not estimated (stays near its initial value)"
    )
    assert second.text.startswith("weak along [1.00]")
    assert [c[0] for c in weakest.components] == ["offset.a", "offset.b"]
    assert not report.observable.any()
    assert np.all(np.isinf(report.std))
    assert report.singular_values[-1] < 1e-9 and report.singular_values[-2] == pytest.approx(
        1e-4, rel=1e-6
    )


def test_plain_step_moves_unobservable_direction() -> None:
    pr = make_rank_deficient(np.random.default_rng(16))
    lin = pr.linearize(pr.evaluate())
    nt = lin.layout.num_trajectory
    plain = compute_step(lin, 1e-9, LMParams(use_tsvd=False))
    tsvd = compute_step(lin, 1e-9, LMParams(use_tsvd=True, tsvd_threshold=1.0))
    null = np.array([2.0, -1.0]) / np.sqrt(5)
    assert abs(plain.dx[nt : nt + 2] @ null) > 1e-3
    assert abs(plain.dx[nt + 2]) > 1e-3
    assert abs(tsvd.dx[nt : nt + 2] @ null) < 1e-10
    assert abs(tsvd.dx[nt + 2]) < 1e-12
    assert tsvd.num_truncated == 2


class WeakResidual:
    """The chain seen directly (sigma 0.01) and ``weak`` seen once with ``sigma``."""

    def __init__(self, y: np.ndarray, c_meas: float, sigma: float) -> None:
        self.name = "chain"
        self.y, self.c_meas, self.sigma = y, c_meas, sigma

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        x = params["chain"][:, 0]
        n = x.size
        w = float(params["weak"])
        r = np.concatenate([(x - self.y) / 0.01, [(w - self.c_meas) / self.sigma]])
        jx = np.zeros((n + 1, 1, 1, 1))
        jx[:n] = 100.0
        jc = np.zeros((n + 1, 1, 1, 1))
        jc[n] = 1.0 / self.sigma
        el = np.concatenate([np.arange(n), [0]])[:, None]
        return ResidualEval(
            r,
            (
                DenseJacobian("chain", el, jx),
                DenseJacobian("weak", np.zeros((n + 1, 1), dtype=int), jc),
            ),
        )


def _weak_problem(pull_sigmas: float, sigma: float = np.sqrt(2.0)) -> Problem:
    """``weak`` (scale 1) with information 1 / sigma^2 (0.5: below the threshold of 1, above
    its weak floor), its measurement ``pull_sigmas`` standard deviations from the start."""
    n = 5
    pr = Problem()
    pr.add_parameter_block(ParameterBlock("chain", np.zeros((n, 1))))
    pr.add_parameter_block(ParameterBlock("weak", 0.5, group="calibration"))
    pr.add_residual_block(WeakResidual(np.arange(n, dtype=float), 0.5 + pull_sigmas * sigma, sigma))
    return pr


def test_a_weak_direction_is_estimated_and_its_sigma_reported() -> None:
    """Below the threshold but above its weak floor, made of the extrinsic-like (unbounded)
    block: estimated where the data put it, its standard deviation reported and the direction
    named as weak; held and not observable with ``weak_floor=0``, under the floor, or made of a
    bounded block (an intrinsic)."""
    params = LMParams(max_iterations=20, tsvd_threshold=1.0)
    for pull in (20.0, 3.0):
        weak = _weak_problem(pull)
        report = solve(weak, params)
        assert float(weak["weak"].value) == pytest.approx(0.5 + pull * np.sqrt(2.0), abs=0.05)
        assert report.truncated == () and bool(report.observable[0])
        assert report.std[0] == pytest.approx(np.sqrt(2.0), rel=1e-3)
        (named,) = report.weak
        assert "weakly determined" in named.text and "singular value 0.50" in named.text
        assert report.weak_floor == params.weak_floor == 0.1  # as applied, for the result
    for problem, held in (
        (_weak_problem(20.0), replace(params, weak_floor=0.0)),
        (_weak_problem(20.0, sigma=10.0), params),  # information 0.01, under the floor of 0.1
        (_weak_problem(20.0), replace(params, bounded_blocks=("weak",))),
    ):
        report = solve(problem, held)
        assert float(problem["weak"].value) == 0.5
        assert len(report.truncated) == 1 and report.weak == ()
    assert not solve(_weak_problem(20.0), replace(params, weak_floor=0.0)).observable[0]
    assert solve(_weak_problem(20.0), replace(params, use_tsvd=False)).weak_floor == 0.0


# --------------------------------------------------------------------------- Monte Carlo stds
@pytest.mark.slow
def test_reported_std_matches_monte_carlo_spread() -> None:
    """200 noisy realisations solved by LM; sample spread vs reported std within 20 %
    (measured ratios 0.93-1.05)."""
    rng = np.random.default_rng(17)
    kw = dict(num_ctrl=6, n_direct=40, n_sensor=30, sigma_direct=0.02, sigma_sensor=0.02)
    base, truth = make_problem(np.random.default_rng(18), noise=False, perturb=False, **kw)
    params = LMParams(max_iterations=10, function_tolerance=1e-10, tsvd_threshold=1e-6)
    report = solve(base, params)
    names = report.calibration_names
    estimates = []
    for _ in range(200):
        pr, _ = make_problem(np.random.default_rng(18), noise=False, perturb=False, **kw)
        # same geometry, fresh noise
        direct, sensor = pr.residual_blocks
        direct.s.meas = direct.s.meas + rng.normal(0, 0.02, direct.s.meas.shape)
        sensor.s.meas = sensor.s.meas + rng.normal(0, 0.02, sensor.s.meas.shape)
        solve(pr, params)
        estimates.append(
            np.concatenate(
                [
                    local("so3", truth.rot[None], pr["rot"].value[None])[0],
                    pr["trans"].value - truth.trans,
                    [float(pr["scale"].value) - truth.scale],
                ]
            )
        )
    spread = np.std(np.asarray(estimates), axis=0, ddof=1)
    assert names == ("rot.rx", "rot.ry", "rot.rz", "trans.x", "trans.y", "trans.z", "scale")
    np.testing.assert_allclose(spread, report.std, rtol=0.2)


# ------------------------------------------- a calibration direction the trajectory absorbs
class ShiftedResidual:
    """``y = x_k + a``: the sensor sees the chain shifted by the calibration offset ``a``."""

    def __init__(self, k: np.ndarray, y: np.ndarray, sigma: float) -> None:
        self.name = "shifted"
        self.k, self.y, self.sigma = k, y, sigma

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        r = (params["chain"][self.k, 0] + float(params["a"]) - self.y) / self.sigma
        n = r.size
        ones = np.full((n, 1, 1, 1), 1.0 / self.sigma)
        return ResidualEval(
            r,
            (
                DenseJacobian("chain", self.k[:, None], ones),
                DenseJacobian("a", np.zeros((n, 1), dtype=int), ones.copy()),
            ),
        )


class DifferenceResidual:
    """``d_k = x_{k+1} - x_k``: only the shape of the chain, not its level (like an IMU)."""

    def __init__(self, d: np.ndarray, sigma: float) -> None:
        self.name = "difference"
        self.d, self.sigma = d, sigma

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        x = params["chain"][:, 0]
        r = (np.diff(x) - self.d) / self.sigma
        n = r.size
        jac = np.zeros((n, 1, 2, 1))
        jac[:, 0, 0, 0], jac[:, 0, 1, 0] = -1.0 / self.sigma, 1.0 / self.sigma
        el = np.stack([np.arange(n), np.arange(1, n + 1)], axis=1)
        return ResidualEval(r, (DenseJacobian("chain", el, jac),))


def make_absorbed(rng: np.random.Generator) -> tuple[Problem, np.ndarray]:
    """The offset ``a`` and a common shift of the chain are one and the same: ``S_aa = 0`` although
    ``H_tt`` is regular (the sensor fixes the chain's level once ``a`` is given)."""
    n, sigma = 40, 1e-3
    x_true = np.cumsum(rng.normal(0, 1, n))
    k = rng.integers(0, n, 400)
    pr = Problem()
    pr.add_parameter_block(ParameterBlock("chain", x_true[:, None] + rng.normal(0, 0.1, (n, 1))))
    pr.add_parameter_block(ParameterBlock("a", 0.25, group="calibration", scale=0.1))
    pr.add_residual_block(ShiftedResidual(k, x_true[k] + 0.1 + rng.normal(0, sigma, k.size), sigma))
    pr.add_residual_block(DifferenceResidual(np.diff(x_true) + rng.normal(0, sigma, n - 1), sigma))
    return pr, x_true


def test_direction_absorbed_by_trajectory_is_truncated_under_damping() -> None:
    """The truncation is decided on the undamped Schur complement: damping ``H_tt`` charges the
    chain for the shift and makes ``a`` look determined (here ``S_d`` ~ 1e3 at lambda 1e-4)."""
    pr, x_true = make_absorbed(np.random.default_rng(18))
    lin = pr.linearize(pr.evaluate())
    nt = lin.layout.num_trajectory
    step = compute_step(lin, 1e-4, LMParams(tsvd_threshold=1.0))
    assert step.num_truncated == 1
    assert abs(step.dx[nt]) < 1e-12
    # what the damped Schur complement alone would have said
    from licalib_cli.solver.schur import schur_complement

    damped = schur_complement(lin, 1e-4 * lin.H_tt.diagonal()).S
    assert float(damped[0, 0]) * 0.1**2 > 100.0

    report = solve(pr, LMParams(max_iterations=30))
    assert float(pr["a"].value) == 0.25
    assert report.truncated and report.truncated[0].text.startswith("a along [1.00]")
    assert not report.observable[0] and np.isinf(report.std[0])
    assert report.singular_values[0] < 1e-6
    # the chain takes up the whole shift: x_true + 0.1 - 0.25
    np.testing.assert_allclose(pr["chain"].value[:, 0], x_true - 0.15, atol=2e-3)


def _bounded_report() -> tuple[Problem, SolverReport]:
    """The rank-deficient problem with both calibration blocks bounded a priori: its two truncated
    directions add one characteristic scale each instead of leaving the coordinates unknown."""
    pr = make_rank_deficient(np.random.default_rng(16))
    report = solve(pr, LMParams(max_iterations=20, bounded_blocks=("offset", "weak")))
    assert len(report.truncated) == 2 and report.observable.all()
    return pr, report


def test_a_move_along_a_truncated_direction_is_added_to_its_variance() -> None:
    _, report = _bounded_report()
    null = report.truncated[0].vector  # (2, -1, 0)/sqrt(5), scale 1
    widened = widen_along_truncated(report, 3.0 * null)
    grown = widened.covariance - report.covariance
    np.testing.assert_allclose(grown, 9.0 * np.outer(null, null), atol=1e-12)
    np.testing.assert_allclose(widened.std, np.sqrt(np.diag(widened.covariance)))
    assert widened.truncated[0].text.endswith(
        "the fit moved the estimate 3.0 characteristic scales along it from its initial value, "
        "which the sigmas include"
    )
    assert widened.truncated[1] == report.truncated[1]  # not moved along: unchanged


def test_an_uncertain_initial_value_widens_and_a_move_the_data_determine_does_not() -> None:
    _, report = _bounded_report()
    # the observable combination (1, 2)/sqrt(5) and a move within one scale: same report
    assert widen_along_truncated(report, np.array([1.0, 2.0, 0.0]) / np.sqrt(5)) is report
    small = widen_along_truncated(report, 0.5 * report.truncated[0].vector)
    assert small.truncated == report.truncated  # within one scale: still near its initial value
    # the weak coordinate's initial value known to 3 scales instead of 1: 9 - 1 more variance
    wider = widen_along_truncated(report, np.zeros(3), initial_sd=np.array([1.0, 1.0, 3.0]))
    assert wider.covariance[2, 2] - report.covariance[2, 2] == pytest.approx(8.0)
    assert wider.std[2] == pytest.approx(np.sqrt(report.covariance[2, 2] + 8.0))
    assert wider.std[0] == pytest.approx(report.std[0])


def test_a_coordinate_the_data_do_not_determine_stays_unknown() -> None:
    pr = make_rank_deficient(np.random.default_rng(16))
    report = solve(pr, LMParams(max_iterations=20))  # nothing bounded: all three unknown
    widened = widen_along_truncated(report, np.array([2.0, -1.0, 4.0]))
    assert np.all(np.isinf(widened.std))
