"""Eliminating nuisance coordinates (the map planes) that enter the residuals of one block.

The reference is the dense computation: the full normal matrix over trajectory, calibration and
nuisance coordinates, the held trajectory coordinates removed, inverted; its calibration block's
inverse is the information ``marginal_schur`` must return.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
from test_assembly import RandomBlock, dense_reference, make_problem

from licalib_cli.parallel import threads as thr
from licalib_cli.solver import HuberLoss, ParameterBlock, ResidualEval
from licalib_cli.solver.lm import LMParams
from licalib_cli.solver.nuisance import (
    GRAM_SPLIT,
    NuisanceSegment,
    NuisanceTerms,
    _reduced_by,
    eliminate_nuisance,
    gram,
    marginal_schur,
    marginal_system,
    nuisance_gradient,
    nuisance_step,
    nuisance_terms,
    segmented_nuisance_step,
    whole_trajectory,
)
from licalib_cli.solver.observability import Truncation, undamped_schur
from licalib_cli.solver.problem import Evaluation, Layout, Linearization, Problem

NUM_GROUPS = 9
K = 3


def _nuisance(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    group = rng.integers(0, NUM_GROUPS, n)
    group[:NUM_GROUPS] = np.arange(NUM_GROUPS)  # every group is seen
    return rng.normal(size=(n, K)), group


def _dense_marginal(h_full: np.ndarray, nt: int, nc: int, hold: np.ndarray) -> np.ndarray:
    keep = np.setdiff1d(np.arange(h_full.shape[0]), hold)
    cov = np.linalg.inv(h_full[np.ix_(keep, keep)])
    pos = np.searchsorted(keep, np.arange(nt, nt + nc))
    return np.linalg.inv(cov[np.ix_(pos, pos)])


@pytest.mark.parametrize("huber", [False, True])
def test_marginal_schur_matches_the_dense_elimination(huber: bool) -> None:
    loss = HuberLoss(1.5) if huber else None
    pr, block = make_problem(3, 900, 1, False, loss)
    rng = np.random.default_rng(11)
    jac_p, group = _nuisance(rng, 900)
    evaluation = pr.evaluate()
    layout = pr.layout()
    lin = pr.linearize(evaluation, layout)
    terms = nuisance_terms(pr, evaluation, layout, 0, jac_p, group, NUM_GROUPS)

    # dense reference of the same weighted Jacobian, with the nuisance columns beside it
    h, _ = dense_reference(pr, block, loss)
    w = np.ones(900) if loss is None else loss(block.r[:, 0] ** 2)[1]
    jp = np.zeros((900, NUM_GROUPS * K))
    jp[np.arange(900)[:, None], group[:, None] * K + np.arange(K)] = jac_p
    jp *= np.sqrt(w)[:, None]
    jx = pr.jacobian_matrix(evaluation, 0, layout).toarray()
    np.testing.assert_allclose(jx.T @ jx, h, atol=1e-10 * np.abs(h).max())
    np.testing.assert_allclose(terms.H_xp.toarray(), jx.T @ jp, atol=1e-10 * np.abs(h).max())
    np.testing.assert_allclose(
        terms.H_pp,
        np.stack(
            [jp[:, g * K : g * K + K].T @ jp[:, g * K : g * K + K] for g in range(NUM_GROUPS)]
        ),
    )

    nt, nc = layout.num_trajectory, layout.num_calibration
    full = np.block([[h, jx.T @ jp], [jp.T @ jx, jp.T @ jp]])
    hold = np.array([0, 1, 2])
    expected = _dense_marginal(full, nt, nc, hold)
    got = marginal_schur(lin, terms, hold)
    np.testing.assert_allclose(got, expected, rtol=1e-7, atol=1e-9 * np.abs(expected).max())


def _plain_case(problem_seed: int, n: int, seed: int) -> tuple[Linearization, NuisanceTerms]:
    """A problem of ``n`` measurements (no loss) linearised, and random nuisance terms."""
    pr, _ = make_problem(problem_seed, n, 1, False, None)
    jac_p, group = _nuisance(np.random.default_rng(seed), n)
    evaluation = pr.evaluate()
    layout = pr.layout()
    terms = nuisance_terms(pr, evaluation, layout, 0, jac_p, group, NUM_GROUPS)
    return pr.linearize(evaluation, layout), terms


def test_eliminating_nuisance_never_adds_information() -> None:
    lin, terms = _plain_case(5, 900, 2)
    plain = undamped_schur(lin)
    marg = marginal_schur(lin, terms)
    # plain - marg is positive semi-definite: the calibration is never known better
    eig = np.linalg.eigvalsh(plain - marg)
    assert eig.min() > -1e-9 * np.abs(plain).max()
    assert eig.max() > 1e-3 * np.abs(plain).max()  # and here it is known measurably worse


def test_no_nuisance_gives_the_plain_schur_complement() -> None:
    pr, _ = make_problem(8, 600, 1, False, None)
    evaluation = pr.evaluate()
    layout = pr.layout()
    lin = pr.linearize(evaluation, layout)
    empty = NuisanceTerms(sp.csr_matrix((layout.num_free, 0)), np.zeros((0, K, K)))
    np.testing.assert_allclose(marginal_schur(lin, empty), undamped_schur(lin), rtol=1e-10)


def test_a_group_the_data_do_not_determine_is_left_alone() -> None:
    """A plane whose points give no information about one of its coordinates (all derivatives
    zero along it) must not break the elimination."""
    pr, _ = make_problem(4, 900, 1, False, None)
    rng = np.random.default_rng(5)
    jac_p, group = _nuisance(rng, 900)
    jac_p[group == 0, 1] = 0.0
    evaluation = pr.evaluate()
    layout = pr.layout()
    lin = pr.linearize(evaluation, layout)
    terms = nuisance_terms(pr, evaluation, layout, 0, jac_p, group, NUM_GROUPS)
    got = marginal_schur(lin, terms)
    assert np.all(np.isfinite(got))
    assert np.linalg.eigvalsh(got).min() > 0.0


def test_reduction_by_a_psd_matrix_matches_the_pseudo_inverse() -> None:
    rng = np.random.default_rng(4)
    m = rng.normal(size=(40, 30))
    b = rng.normal(size=(5, 30))
    full = m.T @ m + 0.1 * np.eye(30)  # well conditioned: the Cholesky path
    np.testing.assert_allclose(_reduced_by(full, b), b @ np.linalg.inv(full) @ b.T, rtol=1e-8)
    # rank 20 of 30 (the eigen path): for rows in its range, b a^+ b^T = c a c^T whatever
    # generalised inverse (scaled or not) is used
    low_rank = m[:20].T @ m[:20]
    c = rng.normal(size=(5, 30))
    in_range = c @ low_rank
    np.testing.assert_allclose(_reduced_by(low_rank, in_range), c @ low_rank @ c.T, rtol=1e-6)


@pytest.mark.parametrize("huber", [False, True])
def test_dense_jacobian_matrix_matches_its_coo_form(huber: bool) -> None:
    """Dense pieces laid out straight into CSR equal the COO assembly: two residuals per
    measurement, repeated blocks, partly fixed blocks."""
    loss = HuberLoss(1.5) if huber else None
    pr, _ = make_problem(5, 300, 2, True, loss)
    for name, mask in [("ctrl", np.arange(42) < 6), ("wide", np.arange(30) % 4 == 0)]:
        next(b for b in pr.parameter_blocks if b.name == name).set_fixed(mask)
    evaluation = pr.evaluate()
    layout = pr.layout()
    got = pr.jacobian_matrix(evaluation, 0, layout).toarray()
    ev = evaluation.evals[0]
    coo = ResidualEval(ev.residuals, tuple(j.to_coo() for j in ev.jacobians))
    as_coo = replace(evaluation, evals=(coo,))
    expected = pr.jacobian_matrix(as_coo, 0, layout).toarray()
    assert np.count_nonzero(expected) > 0
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


def _dense_full(
    pr: Problem, block: RandomBlock, loss: HuberLoss | None, jac_p: np.ndarray, group: np.ndarray
) -> tuple[Evaluation, Layout, np.ndarray, np.ndarray]:
    """Full normal equations and gradient over (free coordinates, nuisance), dense."""
    evaluation = pr.evaluate()
    layout = pr.layout()
    h, g = dense_reference(pr, block, loss)
    n = jac_p.shape[0]
    w = np.ones(n) if loss is None else loss(block.r[:, 0] ** 2)[1]
    jp = np.zeros((n, NUM_GROUPS * K))
    jp[np.arange(n)[:, None], group[:, None] * K + np.arange(K)] = jac_p
    jx = pr.jacobian_matrix(evaluation, 0, layout).toarray()
    jp_w = jp * np.sqrt(w)[:, None]
    full = np.block([[h, jx.T @ jp_w], [jp_w.T @ jx, jp_w.T @ jp_w]])
    grad = np.concatenate([g, jp.T @ (w * block.r[:, 0])])
    return evaluation, layout, full, grad


def _dense_case(
    huber: bool, seed: int
) -> tuple[Linearization, NuisanceTerms, Layout, np.ndarray, np.ndarray]:
    """A random problem with nuisance: its normal equations, the nuisance's terms, the layout
    and the dense full matrix and gradient over (free coordinates, nuisance)."""
    loss = HuberLoss(1.5) if huber else None
    pr, block = make_problem(6, 900, 1, False, loss)
    jac_p, group = _nuisance(np.random.default_rng(seed), 900)
    evaluation, layout, full, grad = _dense_full(pr, block, loss, jac_p, group)
    lin = pr.linearize(evaluation, layout)
    terms = nuisance_terms(pr, evaluation, layout, 0, jac_p, group, NUM_GROUPS)
    return lin, terms, layout, full, grad


def _dense_step(full: np.ndarray, grad: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The Gauss-Newton step of the dense system over ``keep`` (zero elsewhere)."""
    step = np.zeros(full.shape[0])
    step[keep] = -np.linalg.solve(full[np.ix_(keep, keep)], grad[keep])
    return step


@pytest.mark.parametrize("huber", [False, True])
def test_nuisance_step_matches_the_dense_gauss_newton_step(huber: bool) -> None:
    lin, terms, layout, full, grad = _dense_case(huber, 17)
    np.testing.assert_allclose(terms.g_p.reshape(-1), grad[layout.num_free :], atol=1e-10)

    hold = np.array([0, 1, 2])
    step = nuisance_step(lin, terms, hold, truncation=Truncation(0.0))
    expected = _dense_step(full, grad, np.setdiff1d(np.arange(full.shape[0]), hold))
    got = np.concatenate([step.dx, step.dp.reshape(-1)])
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-8 * np.abs(expected).max())
    assert step.num_truncated == 0
    predicted = -(grad @ expected + 0.5 * expected @ full @ expected)
    assert step.predicted_reduction == pytest.approx(predicted, rel=1e-8)
    # the step's calibration information is the marginal one (the checks reuse it)
    marginal = marginal_schur(lin, terms, hold)
    np.testing.assert_allclose(
        step.information, marginal, rtol=1e-9, atol=1e-9 * np.abs(marginal).max()
    )


@pytest.mark.parametrize("huber", [False, True])
def test_a_chord_step_solves_the_eliminated_curvature_with_another_gradient(huber: bool) -> None:
    """The elimination of one linearisation gives, for the gradient at another estimate, the
    dense system's step on the same curvature; for its own gradient, the Gauss-Newton step."""
    lin, terms, layout, full, grad = _dense_case(huber, 19)
    hold = np.array([0, 1, 2])
    system = eliminate_nuisance(
        lin, [whole_trajectory(lin, terms, hold)], truncation=Truncation(0.0)
    )
    own = system.step()
    plain = nuisance_step(lin, terms, hold, truncation=Truncation(0.0))
    np.testing.assert_array_equal(own.dx, plain.dx)  # the same computation
    np.testing.assert_array_equal(own.dp, plain.dp)
    assert own.predicted_reduction == plain.predicted_reduction
    # the own gradient given explicitly takes the chord path: the same step to rounding
    again = system.step(lin.g, [terms.g_p])
    np.testing.assert_allclose(again.dx, own.dx, rtol=1e-7, atol=1e-9 * np.abs(own.dx).max())
    np.testing.assert_allclose(again.dp, own.dp, rtol=1e-7, atol=1e-9 * np.abs(own.dp).max())

    rng = np.random.default_rng(7)
    moved = grad + rng.normal(size=grad.shape) * np.abs(grad).mean()
    nf = layout.num_free
    chord = system.step(moved[:nf], [moved[nf:].reshape(NUM_GROUPS, K)])
    keep = np.setdiff1d(np.arange(full.shape[0]), hold)
    expected = _dense_step(full, moved, keep)
    got = np.concatenate([chord.dx, chord.dp.reshape(-1)])
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-8 * np.abs(expected).max())
    assert (
        np.abs(got - np.concatenate([own.dx, own.dp.reshape(-1)])).max() > 0.1 * np.abs(got).max()
    )  # another gradient, another step
    predicted = -(moved @ expected + 0.5 * expected @ full @ expected)
    assert chord.predicted_reduction == pytest.approx(predicted, rel=1e-8)
    np.testing.assert_array_equal(chord.information, own.information)


def test_a_chord_step_refuses_a_gradient_that_does_not_match() -> None:
    lin, terms = _plain_case(3, 300, 4)
    system = eliminate_nuisance(lin, [whole_trajectory(lin, terms)])
    with pytest.raises(ValueError, match="both"):
        system.step(lin.g)
    with pytest.raises(ValueError, match="does not match"):
        system.step(lin.g[:-1], [terms.g_p])
    with pytest.raises(ValueError, match="does not match"):
        system.step(lin.g, [terms.g_p[:-1]])


@pytest.mark.parametrize("huber", [False, True])
def test_the_nuisance_gradient_alone_is_the_terms_gradient(huber: bool) -> None:
    loss = HuberLoss(1.5) if huber else None
    pr, _ = make_problem(3, 500, 1, False, loss)
    jac_p, group = _nuisance(np.random.default_rng(8), 500)
    evaluation = pr.evaluate()
    terms = nuisance_terms(pr, evaluation, pr.layout(), 0, jac_p, group, NUM_GROUPS)
    got = nuisance_gradient(evaluation, 0, jac_p, group, NUM_GROUPS)
    np.testing.assert_array_equal(got, terms.g_p)
    with pytest.raises(ValueError, match="one residual per measurement"):
        nuisance_gradient(evaluation, 0, jac_p[:-1], group, NUM_GROUPS)


@pytest.mark.parametrize("huber", [False, True])
def test_marginal_system_gives_the_dense_calibration_step(huber: bool) -> None:
    lin, terms, layout, full, grad = _dense_case(huber, 23)
    nt, nc = layout.num_trajectory, layout.num_calibration
    hold = np.array([0, 1, 2])

    s, b = marginal_system(lin, terms, hold)
    np.testing.assert_allclose(s, marginal_schur(lin, terms, hold), rtol=1e-9, atol=1e-12)
    keep = np.setdiff1d(np.arange(full.shape[0]), hold)
    dense = _dense_step(full, grad, keep)
    np.testing.assert_allclose(np.linalg.solve(s, b), dense[nt : nt + nc], rtol=1e-6)

    # a subset of the calibration: the others held fixed (their rows and columns removed)
    subset = np.arange(0, nc, 2)
    s_sub, b_sub = marginal_system(lin, terms, hold, subset)
    dense = _dense_step(full, grad, np.setdiff1d(keep, nt + np.setdiff1d(np.arange(nc), subset)))
    np.testing.assert_allclose(np.linalg.solve(s_sub, b_sub), dense[nt + subset], rtol=1e-6)


def test_marginal_system_needs_the_gradient() -> None:
    lin, terms = _plain_case(2, 300, 5)
    with pytest.raises(ValueError, match="gradient"):
        marginal_system(lin, replace(terms, g_p=np.zeros((0, 0))))


def test_nuisance_step_holds_the_directions_the_joint_information_does_not_determine() -> None:
    pr, block = make_problem(9, 900, 1, False, None)
    rng = np.random.default_rng(3)
    jac_p, group = _nuisance(rng, 900)
    evaluation, layout, *_ = _dense_full(pr, block, None, jac_p, group)
    lin = pr.linearize(evaluation, layout)
    terms = nuisance_terms(pr, evaluation, layout, 0, jac_p, group, NUM_GROUPS)
    scale = layout.calibration_scale
    s_d = scale[:, None] * marginal_schur(lin, terms) * scale[None, :]
    vals, vecs = np.linalg.eigh(s_d)
    # halfway between two eigenvalues (an eigenvalue at the threshold itself falls on either
    # side with the rounding of another decomposition of the same matrix)
    k = vals.size // 2
    threshold = float(0.5 * (vals[k - 1] + vals[k]))
    step = nuisance_step(lin, terms, truncation=Truncation(threshold))
    weak = vecs[:, vals < threshold]
    assert step.num_truncated == weak.shape[1] > 0
    dc_scaled = step.dx[layout.num_trajectory :] / scale
    np.testing.assert_allclose(weak.T @ dc_scaled, 0.0, atol=1e-9 * np.abs(dc_scaled).max())
    assert step.predicted_reduction > 0.0


def test_nuisance_step_moves_along_a_weakly_determined_direction_as_the_solver_does() -> None:
    """Below the threshold but above its weak floor and made of unbounded coordinates (the
    solver's ``LMParams.weak_floor``): the step moves along it, as with the threshold lowered
    under it; the same direction made of bounded ones (intrinsics) is held."""
    pr, block = make_problem(9, 900, 1, False, None)
    jac_p, group = _nuisance(np.random.default_rng(3), 900)
    evaluation, layout, *_ = _dense_full(pr, block, None, jac_p, group)
    lin = pr.linearize(evaluation, layout)
    terms = nuisance_terms(pr, evaluation, layout, 0, jac_p, group, NUM_GROUPS)
    scale = layout.calibration_scale
    vals = np.linalg.eigvalsh(scale[:, None] * marginal_schur(lin, terms) * scale[None, :])
    k = vals.size // 2
    threshold = float(0.5 * (vals[k - 1] + vals[k]))
    below = float(0.5 * (vals[k - 2] + vals[k - 1]))  # one direction between it and the threshold
    floor = below / threshold
    weak = nuisance_step(lin, terms, truncation=Truncation(threshold, weak_floor=floor))
    lowered = nuisance_step(lin, terms, truncation=Truncation(below))
    held = nuisance_step(lin, terms, truncation=Truncation(threshold))
    assert weak.num_truncated == lowered.num_truncated == held.num_truncated - 1
    np.testing.assert_allclose(weak.dx, lowered.dx, rtol=1e-9, atol=1e-12)
    owners = tuple(layout.calibration_owner)
    bounded = nuisance_step(
        lin, terms, truncation=Truncation(threshold, weak_floor=floor, bounded_blocks=owners)
    )
    assert bounded.num_truncated == held.num_truncated
    np.testing.assert_allclose(bounded.dx, held.dx, rtol=1e-9, atol=1e-12)


def test_nuisance_step_needs_the_gradient() -> None:
    pr, _ = make_problem(8, 600, 1, False, None)
    evaluation = pr.evaluate()
    layout = pr.layout()
    lin = pr.linearize(evaluation, layout)
    terms = NuisanceTerms(sp.csr_matrix((layout.num_free, K)), np.ones((1, K, K)) * np.eye(K))
    with pytest.raises(ValueError, match="gradient"):
        nuisance_step(lin, terms)


# ------------------------------------------------------------------ segment by segment

_OWN = ("ctrl", "bias", "pair", "wide")
"""Blocks each segment has its own copy of (``wide`` is a calibration block: a per-segment
calibration coordinate, like a segment's time offset); the rest is shared."""


def _two_segments(seed: int) -> tuple[Problem, list[np.ndarray], list[np.ndarray]]:
    """Two random blocks as two segments: own trajectory and ``wide``, shared calibration.

    The segments' blocks are added interleaved, so each segment's trajectory coordinates are not
    contiguous in the solver order. Returns the problem and each segment's nuisance (Jacobian
    and group; 9 and 6 groups).
    """
    rng = np.random.default_rng(seed)
    pr = Problem()
    for name, shape, group in [
        ("ctrl", (14, 3), "trajectory"),
        ("bias", (3,), "trajectory"),
        ("pair", (6, 2), "trajectory"),
        ("wide", (3, 10), "calibration"),
    ]:
        for s in (1, 2):
            pr.add_parameter_block(ParameterBlock(f"s{s}:{name}", np.zeros(shape), group=group))
    pr.add_parameter_block(ParameterBlock("beam", np.zeros((5, 2)), group="calibration"))
    pr.add_parameter_block(ParameterBlock("ext", np.zeros(3), group="calibration"))
    pr.add_parameter_block(ParameterBlock("shared", np.zeros((4, 1)), group="calibration"))
    nuisance = []
    groups = []
    for s, (n, num_groups) in enumerate([(700, 9), (500, 6)], start=1):
        block = RandomBlock(rng, n, 1, False)
        block.jacobians = tuple(
            replace(j, block=f"s{s}:{j.block}" if j.block in _OWN else j.block)
            for j in block.jacobians
        )
        block.name = f"s{s}"
        pr.add_residual_block(block, HuberLoss(1.5))
        group = rng.integers(0, num_groups, n)
        group[:num_groups] = np.arange(num_groups)
        nuisance.append(rng.normal(size=(n, K)))
        groups.append(group)
    pr["s1:ctrl"].fix([0, 1, 2])  # the shared gauge's first coordinates fixed outright
    return pr, nuisance, groups


def _segments(
    pr: Problem, nuisance: list[np.ndarray], groups: list[np.ndarray], own_calibration: bool
) -> tuple[Evaluation, Layout, list[NuisanceSegment]]:
    evaluation = pr.evaluate()
    layout = pr.layout()
    nt = layout.num_trajectory
    segments = []
    for s in (1, 2):
        owner = np.asarray(layout.owner)
        traj = np.flatnonzero(np.char.startswith(owner[:nt].astype(str), f"s{s}:"))
        other = f"s{3 - s}:"
        cal = np.flatnonzero(~np.char.startswith(owner[nt:].astype(str), other))
        terms = nuisance_terms(
            pr,
            evaluation,
            layout,
            s - 1,
            nuisance[s - 1],
            groups[s - 1],
            int(groups[s - 1].max()) + 1,
        )
        hold = layout.index[f"s{s}:ctrl"][3:6]  # the second control point: each one's gauge
        segments.append(NuisanceSegment(traj, terms, hold, cal if own_calibration else None))
    return evaluation, layout, segments


def _segmented_case(
    seed: int, own_calibration: bool
) -> tuple[Linearization, Layout, list[NuisanceSegment], NuisanceTerms, np.ndarray]:
    """Two segments linearised, and every segment's nuisance at once as one set of groups with
    the segments' held coordinates together."""
    pr, nuisance, groups = _two_segments(seed)
    evaluation, layout, segments = _segments(pr, nuisance, groups, own_calibration)
    lin = pr.linearize(evaluation, layout)
    whole = NuisanceTerms(
        sp.hstack([s.terms.H_xp for s in segments]).tocsr(),
        np.concatenate([s.terms.H_pp for s in segments]),
        np.concatenate([s.terms.g_p for s in segments]),
    )
    return lin, layout, segments, whole, np.concatenate([s.hold for s in segments])


@pytest.mark.parametrize("own_calibration", [False, True])
@pytest.mark.parametrize("truncated", [False, True])
def test_segmented_step_equals_the_dense_nuisance_step(
    own_calibration: bool, truncated: bool
) -> None:
    lin, layout, segments, whole, hold = _segmented_case(21, own_calibration)
    tsvd, expected = 0.0, 0
    if truncated:  # between two eigenvalues, half the directions held
        scale = layout.calibration_scale
        vals = np.linalg.eigvalsh(scale[:, None] * marginal_schur(lin, whole, hold) * scale)
        expected = vals.size // 2
        tsvd = float(np.sqrt(vals[expected - 1] * vals[expected]))
    dense = nuisance_step(lin, whole, hold, truncation=Truncation(tsvd))
    got = segmented_nuisance_step(lin, segments, truncation=Truncation(tsvd))
    assert got.num_truncated == dense.num_truncated == expected
    np.testing.assert_allclose(got.dx, dense.dx, rtol=1e-7, atol=1e-9 * np.abs(dense.dx).max())
    np.testing.assert_allclose(got.dp, dense.dp, rtol=1e-7, atol=1e-9 * np.abs(dense.dp).max())
    assert got.predicted_reduction == pytest.approx(dense.predicted_reduction, rel=1e-9)
    assert np.abs(got.dx[layout.index["s2:wide"]]).min() > 0.0  # a segment's own coordinates


def test_a_segmented_chord_step_equals_the_dense_one() -> None:
    """Two segments eliminated once; a step for another gradient equals the one-segment chord
    step over every segment's nuisance at once."""
    lin, _, segments, whole, hold = _segmented_case(24, True)
    rng = np.random.default_rng(9)
    g = lin.g + rng.normal(size=lin.g.shape) * np.abs(lin.g).mean()
    g_p = [s.terms.g_p + rng.normal(size=s.terms.g_p.shape) for s in segments]
    got = eliminate_nuisance(lin, segments, truncation=Truncation(0.0)).step(g, g_p)
    dense = eliminate_nuisance(
        lin, [whole_trajectory(lin, whole, hold)], truncation=Truncation(0.0)
    ).step(g, [np.concatenate(g_p)])
    np.testing.assert_allclose(got.dx, dense.dx, rtol=1e-7, atol=1e-9 * np.abs(dense.dx).max())
    np.testing.assert_allclose(got.dp, dense.dp, rtol=1e-7, atol=1e-9 * np.abs(dense.dp).max())
    assert got.predicted_reduction == pytest.approx(dense.predicted_reduction, rel=1e-9)


def test_segmented_step_refuses_segments_that_do_not_partition_the_problem() -> None:
    pr, nuisance, groups = _two_segments(22)
    evaluation, layout, segments = _segments(pr, nuisance, groups, True)
    lin = pr.linearize(evaluation, layout)
    a, b = segments
    swapped = [replace(a, terms=b.terms), replace(b, terms=a.terms)]
    with pytest.raises(ValueError, match="outside"):
        segmented_nuisance_step(lin, swapped)
    wrong_calibration = [replace(a, calibration=b.calibration), b]
    with pytest.raises(ValueError, match="outside"):
        segmented_nuisance_step(lin, wrong_calibration)
    with pytest.raises(ValueError, match="cover"):
        segmented_nuisance_step(lin, [a])
    mixed = np.concatenate([a.trajectory[:-5], b.trajectory[-5:]])
    rest = np.setdiff1d(np.arange(layout.num_trajectory), mixed)
    with pytest.raises(ValueError, match="couples"):
        segmented_nuisance_step(lin, [replace(a, trajectory=mixed), replace(b, trajectory=rest)])
    with pytest.raises(ValueError, match="hold"):
        segmented_nuisance_step(lin, [replace(a, hold=b.hold), b])


@pytest.mark.parametrize("shuffled", [False, True])
@pytest.mark.parametrize("as_coo", [False, True])
def test_the_coupling_matches_the_product_of_the_two_jacobians(
    shuffled: bool, as_coo: bool
) -> None:
    """Runs of measurements sharing their elements and group are summed before they are
    scattered; the result is the product of the full Jacobians, with partly fixed blocks and
    with Jacobians given as COO triplets (the general path)."""
    loss = HuberLoss(1.5)
    pr, block = make_problem(7, 1200, 1, shuffled, loss)
    for name, mask in [("ctrl", np.arange(42) < 6), ("wide", np.arange(30) % 4 == 0)]:
        next(b for b in pr.parameter_blocks if b.name == name).set_fixed(mask)
    rng = np.random.default_rng(3)
    jac_p, group = _nuisance(rng, 1200)
    group[: 1200 // 2] = 4  # long runs of one group
    evaluation = pr.evaluate()
    if as_coo:
        ev = evaluation.evals[0]
        coo = ResidualEval(ev.residuals, tuple(j.to_coo() for j in ev.jacobians))
        evaluation = replace(evaluation, evals=(coo,))
    layout = pr.layout()
    w = loss(block.r[:, 0] ** 2)[1]
    got = pr.coupling_matrix(evaluation, 0, layout, jac_p * w[:, None], group, NUM_GROUPS)
    jp = np.zeros((1200, NUM_GROUPS * K))
    jp[np.arange(1200)[:, None], group[:, None] * K + np.arange(K)] = jac_p
    jx = pr.jacobian_matrix(evaluation, 0, layout).toarray()  # with sqrt(w)
    expected = jx.T @ (jp * np.sqrt(w)[:, None])
    assert got.shape == expected.shape
    np.testing.assert_allclose(got.toarray(), expected, atol=1e-12 * np.abs(expected).max())


def test_the_coupling_refuses_more_than_one_residual_per_measurement() -> None:
    pr, _ = make_problem(1, 100, 2, False, None)
    evaluation = pr.evaluate()
    with pytest.raises(ValueError, match="one residual per measurement"):
        pr.coupling_matrix(
            evaluation, 0, pr.layout(), np.zeros((100, K)), np.zeros(100, int), NUM_GROUPS
        )


@pytest.mark.parametrize("columns", [GRAM_SPLIT - 1, GRAM_SPLIT, GRAM_SPLIT + 301])
def test_the_gram_matrix_in_blocks_is_w_transpose_w_on_one_thread_or_two(
    columns: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    w = np.asfortranarray(np.random.default_rng(5).standard_normal((700, columns)))
    found = {}
    for threads in (1, 2):
        monkeypatch.setattr(thr, "THREADS", threads)
        found[threads] = gram(w)
    np.testing.assert_array_equal(found[1], found[2])  # the same blocks either way
    np.testing.assert_array_equal(found[2], found[2].T)
    np.testing.assert_allclose(found[2], w.T @ w, rtol=0, atol=1e-10 * np.abs(w.T @ w).max())


def test_the_solvers_settings_give_the_steps_truncation() -> None:
    """The planes-free steps move along the directions the solver's own steps move along."""
    params = LMParams(
        tsvd_threshold=2.0, tsvd_relative=True, weak_floor=0.2, bounded_blocks=("lidar.",)
    )
    assert params.truncation == Truncation(2.0, True, 0.2, ("lidar.",))
    plain = replace(params, use_tsvd=False).truncation
    assert (plain.threshold, plain.weak_floor) == (0.0, 0.0)
