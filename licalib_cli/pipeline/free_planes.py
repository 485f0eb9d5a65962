"""A last refinement with the map planes estimated together with the calibration.

The rounds fit the surfel planes to the points mapped with the current estimate and then hold
them fixed. Along directions that move whole planes (the common mode of the range offsets and
scales: every point moving along its ray), a fixed plane pulls the estimate back towards the
values the map was built with, so the rounds move it by less than their tolerance and stop
short of the optimum. This stage takes the final round's points and associations and runs
Gauss-Newton steps of the joint problem: trajectory, calibration and every plane (two normal
directions about the plane's centroid and its offset), the planes eliminated per plane
(:func:`licalib_cli.solver.nuisance.eliminate_nuisance`), the gauge (the whole map and
trajectory moving together) held at the first control point. A step is kept only when it lowers
the cost with the stepped planes. The steps after the first are chord steps: the first step's
elimination (the banded factor of the trajectory, the Gram product of its couplings with the
planes and the factor of the planes' block: about 0.9 s of a 1.5 s step on a 15 s VLP-16 bag)
solved with the gradient at the new estimate, a step of millimetres not changing the curvature
measurably (the dense round of that bag: the second step lowered the cost from 12887.5 to
12882.0 either way, in 0.7 s as a chord step and 1.6 s as a full one). The solver then settles
the state on the final planes and reports the sigmas there; the planes-free information kept
for the sigmas is the first step's (its linearisation and elimination).

A plane's normal fitted to the same noisy points whose distances it scores is biased: the range
noise moves each point along its ray, and the noise's own spread (``sigma^2 (n . u)^2`` per
point, ``u`` the ray) is least for a normal turned away from the rays, which a least-squares fit
rewards. The common range offset is determined only by how the incidence varies within each
plane, so that small tilt moved it by 12 mm (5 mm range noise) and 44 mm (10 mm) on a 10 s
VLP-16 shake. The steps here use the corrected cost (the errors-in-variables correction of a
total least-squares fit): the squared distances minus the noise's expected part
``sum w^2 sigma^2 (n . u)^2``, whose normal equations subtract the noise's part from the
planes' gradient and curvature.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from licalib_cli.estimation import (
    CalibrationState,
    Planes,
    SplineCoverageError,
    state_from_problem,
    state_from_values,
)
from licalib_cli.pipeline.points import PointSample, points_and_rays_in_global
from licalib_cli.pipeline.round import FreePlanesInformation, RoundInputs, SolvedProblem
from licalib_cli.residuals import TRAJ_R3, TRAJ_SO3, PointToPlaneResidual
from licalib_cli.solver import s2_basis
from licalib_cli.solver.lm import LMParams, SolverReport, solve_with_linearization
from licalib_cli.solver.nuisance import (
    NuisanceStep,
    NuisanceSystem,
    NuisanceTerms,
    eliminate_nuisance,
    nuisance_gradient,
    nuisance_terms,
    whole_trajectory,
)
from licalib_cli.solver.observability import undamped_schur
from licalib_cli.solver.problem import Evaluation, Layout, Linearization, Problem

__all__ = [
    "MAX_STEPS",
    "MIN_GAIN",
    "RELATIVE_DECREASE",
    "STEP_FRACTIONS",
    "PlanePoints",
    "PlaneRefinement",
    "PlanesFreeSteps",
    "corrected_plane_gradient",
    "corrected_plane_terms",
    "expected_noise_cost",
    "free_planes_information",
    "gauge_hold",
    "lidar_block",
    "noise_corrected",
    "noise_corrected_gradient",
    "noise_cost",
    "plane_jacobian",
    "planes_free_steps",
    "planes_free_steps_from",
    "refine_with_planes",
    "stepped_planes",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

T = TypeVar("T")
Stepped = tuple[T, Problem]
"""A stepped estimate (with its planes) and the problem built from it."""

MAX_STEPS = 4
"""Gauss-Newton steps at most (the first usually does nearly all of it)."""

RELATIVE_DECREASE = 1e-6
"""Stop when a step lowers the cost by less than this fraction."""

MIN_GAIN = 0.05
"""Stop when a step lowers the cost (half the whitened chi-square) by less than this: such a step
moves the estimate by less than ``sqrt(2 * 0.05)``, 0.32, of a sigma along its direction (and
the calibration by less than that of its own sigmas, the calibration's marginal information
being at most the joint one). On a 15 s VLP-16 sinusoid with every intrinsic free the dense
round's third step gained 0.1 of a cost of 12700 after 693 and 5.0: the second step already
announced it (5.0 * 5.0 / 693 = 0.04)."""

STEP_FRACTIONS = (1.0, 0.5, 0.25)
"""The fractions of a step tried in turn; the first that lowers the cost is kept."""


@dataclass(frozen=True)
class PlaneRefinement:
    """The outcome of the refinement.

    Attributes:
        state: the refined estimate.
        inputs: the final round's inputs with the refined planes.
        report: the solver's report at the refined estimate (planes held at their refined
            values).
        steps: steps kept.
        cost_start: cost with the final round's planes before the refinement, without the
            range noise's expected part (the cost the steps lower: module docstring).
        cost_end: the same with the refined planes after it.
        seconds: wall time.
        solved: the problem on the refined planes at the refined estimate, with the solver's
            evaluation and normal equations there (what the checks analyse).
    """

    state: CalibrationState
    inputs: RoundInputs
    report: SolverReport
    steps: int
    cost_start: float
    cost_end: float
    seconds: float
    solved: SolvedProblem


def plane_jacobian(p_g: F64, plane: npt.ArrayLike, normal: F64) -> tuple[F64, F64]:
    """Derivatives of point-to-plane distances with respect to their plane, and the centroids.

    The plane ``n^T x + d = 0`` is perturbed about the centroid ``c`` of its points: the normal
    by ``B delta`` (``B`` = :func:`~licalib_cli.solver.s2_basis` of ``n``) and the distance at
    the centroid by ``delta_d``, so ``dist = (n + B delta)^T (p - c) + n^T c + d + delta_d``.

    Args:
        p_g: (N, 3) points in the planes' frame, m.
        plane: (N,) plane of each point.
        normal: (P, 3) unit normals.

    Returns:
        (N, 3) ``[B^T (p - c), 1]`` per point (unwhitened) and the (P, 3) centroids.
    """
    idx = np.asarray(plane, dtype=np.intp)
    num = normal.shape[0]
    count = np.bincount(idx, minlength=num).astype(np.float64)
    centroid = (
        np.stack([np.bincount(idx, p_g[:, a], minlength=num) for a in range(3)], axis=1)
        / np.maximum(count, 1.0)[:, None]
    )
    basis = s2_basis(normal)[idx]  # (N, 3, 2)
    jac = np.empty((idx.shape[0], 3))
    jac[:, :2] = np.einsum("nij,ni->nj", basis, p_g - centroid[idx])
    jac[:, 2] = 1.0
    return jac, centroid


def stepped_planes(planes: Planes, centroid: F64, dp: F64) -> Planes:
    """The planes after a step ``dp`` (P, 3) of :func:`plane_jacobian`'s coordinates."""
    n = np.asarray(planes.normal, dtype=np.float64)
    basis = s2_basis(n)
    moved = n + np.einsum("pij,pj->pi", basis, dp[:, :2])
    at_centroid = np.einsum("pi,pi->p", n, centroid) + planes.d + dp[:, 2]
    length = np.linalg.norm(moved, axis=1)
    moved /= length[:, None]
    d = at_centroid / length - np.einsum("pi,pi->p", moved, centroid)
    return replace(planes, normal=moved, d=d)


def noise_corrected(
    terms: NuisanceTerms, plane: npt.NDArray[np.intp], normal: F64, rays: F64, noise: F64
) -> NuisanceTerms:
    """The planes' gradient and curvature without the range noise's expected part.

    Args:
        terms: :func:`~licalib_cli.solver.nuisance.nuisance_terms` of :func:`plane_jacobian`'s
            (whitened) coordinates.
        plane: (N,) plane of each point.
        normal: (P, 3) unit normals.
        rays: (N, 3) unit ray of each point.
        noise: (N,) each point's whitened range noise sigma (the whitening times the sigma).

    Returns:
        The terms with ``sum noise^2 (B^T u)(n . u)`` taken from the normal's gradient and
        ``sum noise^2 (B^T u)(B^T u)^T`` from its curvature (the module docstring).
    """
    across = _noise_across(plane, normal, rays, noise)
    h_pp = terms.H_pp.copy()
    np.add.at(h_pp[:, :2, :2], plane, -across[:, :, None] * across[:, None, :])
    g_p = noise_corrected_gradient(terms.g_p, plane, normal, rays, noise, across)
    return replace(terms, g_p=g_p, H_pp=h_pp)


def noise_corrected_gradient(
    g_p: F64,
    plane: npt.NDArray[np.intp],
    normal: F64,
    rays: F64,
    noise: F64,
    across: F64 | None = None,
) -> F64:
    """:func:`noise_corrected`'s gradient alone: ``g_p`` (P, 3) less ``sum noise^2 (B^T u)
    (n . u)`` in the normal's coordinates (``across``: (N, 2) ``noise B^T u`` when the caller
    has it)."""
    if across is None:
        across = _noise_across(plane, normal, rays, noise)
    along = _noise_along(plane, normal, rays, noise)
    out = np.array(g_p, dtype=np.float64)
    np.add.at(out[:, :2], plane, -across * along[:, None])
    return out


def _noise_across(plane: npt.NDArray[np.intp], normal: F64, rays: F64, noise: F64) -> F64:
    """(N, 2) each point's whitened range noise across its plane's normal, ``noise B^T u``."""
    basis = s2_basis(normal)[plane]  # (N, 3, 2)
    return np.einsum("nij,ni->nj", basis, rays) * noise[:, None]


def noise_cost(plane: npt.NDArray[np.intp], normal: F64, rays: F64, noise: F64) -> float:
    """The range noise's expected part of the cost, ``0.5 sum noise^2 (n . u)^2`` (arguments as
    :func:`noise_corrected`'s)."""
    along = _noise_along(plane, normal, rays, noise)
    return 0.5 * float(along @ along)


def expected_noise_cost(
    residual: PointToPlaneResidual,
    inputs: RoundInputs,
    state: CalibrationState,
    planes: Planes,
    range_noise: F64,
    rays: F64 | None = None,
) -> float:
    """:func:`noise_cost` of ``inputs``' points at ``state`` on ``planes``, whitened as
    ``residual`` (the LiDAR block of the problem at ``state``; its whitening follows the range
    scales the problem was built with); ``range_noise`` (N,) is each point's range noise, m;
    ``rays`` (N, 3) the points' rays at ``state`` when the caller has them (else mapped here)."""
    if rays is None:
        _, rays = points_and_rays_in_global(state, inputs.points)
    return noise_cost(
        np.asarray(inputs.lidar.plane, dtype=np.intp),
        np.asarray(planes.normal, dtype=np.float64),
        rays,
        residual.whitening() * range_noise,
    )


def _noise_along(plane: npt.NDArray[np.intp], normal: F64, rays: F64, noise: F64) -> F64:
    """(N,) each point's whitened range noise along its plane's normal, ``noise (n . u)``."""
    return noise * np.einsum("ij,ij->i", normal[plane], rays)


def lidar_block(problem: Problem) -> int | None:
    """Index of the problem's point-to-plane block (None when it has no LiDAR points)."""
    return next(
        (
            i
            for i, r in enumerate(problem.residual_blocks)
            if isinstance(r, PointToPlaneResidual) and len(r) > 0
        ),
        None,
    )


def gauge_hold(layout: Layout, so3: str = TRAJ_SO3, r3: str = TRAJ_R3) -> npt.NDArray[np.intp]:
    """The reduced indices of the first control point of the ``so3`` and ``r3`` trajectory
    blocks (those free): held, they fix the gauge the trajectory and free planes share."""
    hold = np.concatenate([layout.index[so3][:3], layout.index[r3][:3]])
    return np.asarray(hold[hold >= 0], dtype=np.intp)


@dataclass(frozen=True)
class PlanePoints:
    """The points of a point-to-plane block on their planes, as the planes' nuisance terms read
    them.

    Attributes:
        whitening: (N,) the block's whitening per point.
        p_g: (N, 3) the points in the planes' frame, m.
        rays: (N, 3) their unit rays there.
        plane: (N,) each point's plane.
        normal: (P, 3) the planes' unit normals.
        range_noise: (N,) each point's range noise, m.
    """

    whitening: F64
    p_g: F64
    rays: F64
    plane: npt.NDArray[np.intp]
    normal: F64
    range_noise: F64

    @classmethod
    def mapped(
        cls,
        state: CalibrationState,
        sample: PointSample,
        whitening: F64,
        plane: npt.ArrayLike,
        planes: Planes,
        range_noise: F64,
    ) -> PlanePoints:
        """The points of ``sample`` mapped with ``state`` (:func:`points_and_rays_in_global`),
        each on its plane ``plane`` of ``planes``."""
        p_g, rays = points_and_rays_in_global(state, sample)
        normal = np.asarray(planes.normal, dtype=np.float64)
        return cls(whitening, p_g, rays, np.asarray(plane, dtype=np.intp), normal, range_noise)

    def whitened_jacobian(self) -> tuple[F64, F64, F64]:
        """:func:`plane_jacobian` whitened, the centroids and each point's whitened range
        noise."""
        jac, centroid = plane_jacobian(self.p_g, self.plane, self.normal)
        jac *= self.whitening[:, None]
        return jac, centroid, self.whitening * self.range_noise


def corrected_plane_terms(
    problem: Problem, evaluation: Evaluation, layout: Layout, block: int, points: PlanePoints
) -> tuple[NuisanceTerms, F64, F64]:
    """The planes as nuisance of the point-to-plane block ``block``, without the range noise's
    expected part (:func:`noise_corrected`).

    Args:
        problem, evaluation, layout: the problem, its evaluation with Jacobians and its layout.
        block: the point-to-plane block.
        points: its points on their planes.

    Returns:
        ``(terms, centroids (P, 3), whitened range noise (N,))``.
    """
    jac, centroid, noise = points.whitened_jacobian()
    plane, normal = points.plane, points.normal
    terms = nuisance_terms(problem, evaluation, layout, block, jac, plane, normal.shape[0])
    return noise_corrected(terms, plane, normal, points.rays, noise), centroid, noise


def corrected_plane_gradient(
    evaluation: Evaluation, block: int, points: PlanePoints
) -> tuple[F64, F64, F64]:
    """:func:`corrected_plane_terms`'s gradient alone (arguments as its): ``(g_p (P, 3),
    centroids (P, 3), whitened range noise (N,))``."""
    jac, centroid, noise = points.whitened_jacobian()
    plane, normal = points.plane, points.normal
    g_p = nuisance_gradient(evaluation, block, jac, plane, normal.shape[0])
    return noise_corrected_gradient(g_p, plane, normal, points.rays, noise), centroid, noise


def planes_free_steps(
    problem: Problem,
    current: T,
    step_at: Callable[[Problem, T], tuple[float, NuisanceStep, Callable[[float], Stepped[T]]]],
    what: str,
    cost_of: Callable[[Problem, T], float] | None = None,
    max_steps: int = MAX_STEPS,
) -> tuple[T, Problem, int, float]:
    """Gauss-Newton steps with the planes free, each kept only when it lowers the cost.

    ``step_at(problem, current)`` linearises ``problem`` (built from ``current``: the estimate
    and its planes) and returns its cost there, the step over trajectory, calibration and planes,
    and a function of a step fraction that gives the stepped estimate and its problem. The
    fractions :data:`STEP_FRACTIONS` are tried in turn; the first whose cost is lower is kept.
    At most ``max_steps`` steps; the steps stop when one would gain, or gained, less than
    :data:`RELATIVE_DECREASE` of the cost or :data:`MIN_GAIN`, or when the next is expected to
    (its gain taken as this step's times the ratio of this step's gain to the one before's).

    Args:
        problem: the problem at ``current``.
        current: the estimate and its planes, in the caller's form.
        step_at: see above.
        what: what the debug log calls a step.
        cost_of: the cost of a problem at an estimate, as ``step_at`` returns it; None: the
            problem's own cost.
        max_steps: the most steps taken (:data:`MAX_STEPS` by default).

    Returns:
        The last kept estimate, its problem, the steps kept and the cost before them.
    """

    def cost_at(problem: Problem, current: T) -> float:
        if cost_of is None:
            return problem.evaluate(jacobians=False).cost
        return cost_of(problem, current)

    cost_start: float | None = None
    steps = 0
    previous = 0.0  # what the step before gained
    for _ in range(max_steps):
        cost, step, trial_at = step_at(problem, current)
        if cost_start is None:
            cost_start = cost  # step_at's cost is cost_at's: not evaluated twice
        if step.predicted_reduction <= max(RELATIVE_DECREASE * cost, MIN_GAIN):
            break
        accepted: tuple[T, Problem, float] | None = None
        for fraction in STEP_FRACTIONS:
            try:
                candidate, trial = trial_at(fraction)
            except SplineCoverageError:
                # the step moves the time offset past the spline's padding: a shorter one may not
                continue
            trial_cost = cost_at(trial, candidate)
            if np.isfinite(trial_cost) and trial_cost < cost:
                accepted = (candidate, trial, trial_cost)
                break
        if accepted is None:
            break
        current, problem, new_cost = accepted
        steps += 1
        logger.debug(
            "%s %d: cost %.1f -> %.1f (predicted %.1f), %d directions held.",
            what,
            steps,
            cost,
            new_cost,
            cost - step.predicted_reduction,
            step.num_truncated,
        )
        gained = cost - new_cost
        # Gauss-Newton converges linearly here (the planes and the range intrinsics' common
        # mode trade off): the next step would gain about gained * (gained / the step before's);
        # when that is below the tolerance it is not worth a linearisation.
        expected = gained * gained / previous if previous > 0.0 else np.inf
        done = min(gained, expected) < max(RELATIVE_DECREASE * cost, MIN_GAIN)
        previous = gained
        cost = new_cost
        if done:
            break
    if cost_start is None:  # no step was asked for
        cost_start = cost_at(problem, current)
    return current, problem, steps, cost_start


@dataclass(frozen=True)
class PlanesFreeSteps:
    """Where the Gauss-Newton steps with the planes free arrive (before any solve on the
    refined planes).

    Attributes:
        state: the estimate after the steps.
        planes: the planes after them.
        problem: the problem at ``state`` on ``planes``.
        steps: steps kept.
        cost_start: cost before the steps, without the range noise's expected part.
        noise_part: the range noise's expected part of a problem's cost at an estimate on
            planes, ``noise_part(problem, state, planes)``.
        points_and_rays: the round's points and their unit rays in the planes' frame under an
            estimate, ``points_and_rays(state)`` (the last estimate's are kept).
        evaluation: ``problem``'s evaluation with Jacobians at ``state``.
        last_step: the last step computed (taken or not) and the linearisation it was
            computed from.
    """

    state: CalibrationState
    planes: Planes
    problem: Problem
    steps: int
    cost_start: float
    noise_part: Callable[[Problem, CalibrationState, Planes], float] = field(repr=False)
    points_and_rays: Callable[[CalibrationState], tuple[F64, F64]] = field(repr=False)
    evaluation: Evaluation = field(repr=False)
    last_step: tuple[Linearization, NuisanceStep] = field(repr=False)


def refine_with_planes(
    state: CalibrationState,
    inputs: RoundInputs,
    lm: LMParams,
    max_steps: int = MAX_STEPS,
    solved: SolvedProblem | None = None,
) -> PlaneRefinement | None:
    """Gauss-Newton steps with the planes free (:func:`planes_free_steps_from`), then the
    solver on the refined planes.

    Args:
        state: the final round's estimate.
        inputs: what the final round's problem was built from.
        lm: the solver settings (its truncation rule applies to the joint steps too).
        max_steps: the most Gauss-Newton steps (one does nearly all of it when no LiDAR
            intrinsic trades off against the planes).
        solved: the round's problem at ``state`` on ``inputs``' planes with the solver's
            evaluation and normal equations there (the first step starts from them instead of
            evaluating and linearising the same problem again); None: built here.

    Returns:
        The refinement, or None when the round had no LiDAR points.

    Raises:
        SolverError: the solver failed on the refined planes.
    """
    start = time.perf_counter()
    stepped = planes_free_steps_from(state, inputs, lm, max_steps, solved)
    if stepped is None:
        return None
    problem, planes = stepped.problem, stepped.planes
    solution = solve_with_linearization(problem, lm, evaluation=stepped.evaluation)
    state = state_from_problem(stepped.state, problem)
    # the solver's last evaluation is at the estimate: the cost is not evaluated again
    cost_end = solution.evaluation.cost - stepped.noise_part(problem, state, planes)
    refined = replace(inputs, planes=planes)
    return PlaneRefinement(
        state=state,
        inputs=refined,
        report=solution.report,
        steps=stepped.steps,
        cost_start=stepped.cost_start,
        cost_end=cost_end,
        seconds=time.perf_counter() - start,
        solved=SolvedProblem(
            problem,
            solution.evaluation,
            solution.linearization,
            stepped.points_and_rays(state)[0],
            free_planes_information(*stepped.last_step),
        ),
    )


def free_planes_information(lin: Linearization, step: NuisanceStep) -> FreePlanesInformation:
    """The calibration information of a planes-free step's linearisation with the planes held
    and with them estimated (the step's own elimination)."""
    return FreePlanesInformation(
        tuple(lin.layout.calibration_names), undamped_schur(lin), step.information
    )


def planes_free_steps_from(
    state: CalibrationState,
    inputs: RoundInputs,
    lm: LMParams,
    max_steps: int = MAX_STEPS,
    solved: SolvedProblem | None = None,
) -> PlanesFreeSteps | None:
    """Gauss-Newton steps with the planes free from a round's estimate (:func:`planes_free_steps`
    on the round's problem), without a solve on the refined planes after them.

    Arguments as :func:`refine_with_planes`'s. Returns None when the round had no LiDAR points.
    """
    plane = np.asarray(inputs.lidar.plane, dtype=np.intp)
    problem = solved.problem if solved is not None else inputs.problem(state, inputs.planes)
    block = lidar_block(problem)
    if block is None:
        return None
    range_noise = inputs.noise.range_noise(inputs.points.beam)
    mapped: list[tuple[CalibrationState, F64, F64]] = []  # the last state's points and rays

    def points_and_rays(state: CalibrationState) -> tuple[F64, F64]:
        # a kept trial's points are the next step's: mapped once
        if not mapped or mapped[0][0] is not state:
            mapped[:] = [(state, *points_and_rays_in_global(state, inputs.points))]
        return mapped[0][1], mapped[0][2]

    def noise_part(problem: Problem, state: CalibrationState, planes: Planes) -> float:
        # the range noise's expected part of the problem's cost at ``state`` on ``planes``
        residual = problem.residual_blocks[block]
        assert isinstance(residual, PointToPlaneResidual)
        rays = points_and_rays(state)[1]
        return expected_noise_cost(residual, inputs, state, planes, range_noise, rays)

    # the last trial's evaluation: with Jacobians, since a kept trial is linearised next (by
    # the next step, or by the solve after the steps) at the same estimate
    evaluated: list[tuple[Problem, Evaluation]] = []
    last_step: list[tuple[Linearization, NuisanceStep]] = []
    # the first step's elimination: the steps after it are chord steps on its curvature
    eliminated: list[NuisanceSystem] = []
    if solved is not None:
        evaluated.append((solved.problem, solved.evaluation))

    def evaluation_of(problem: Problem) -> Evaluation:
        if not evaluated or evaluated[0][0] is not problem:
            evaluated[:] = [(problem, problem.evaluate(jacobians=True))]
        return evaluated[0][1]

    def corrected_cost(problem: Problem, current: tuple[CalibrationState, Planes]) -> float:
        state, planes = current
        return evaluation_of(problem).cost - noise_part(problem, state, planes)

    def step_at(
        problem: Problem, current: tuple[CalibrationState, Planes]
    ) -> tuple[float, NuisanceStep, Callable[[float], Stepped[tuple[CalibrationState, Planes]]]]:
        state, planes = current
        residual = problem.residual_blocks[block]
        assert isinstance(residual, PointToPlaneResidual)
        p_g, rays = points_and_rays(state)
        normal = np.asarray(planes.normal, dtype=np.float64)
        points = PlanePoints(residual.whitening(), p_g, rays, plane, normal, range_noise)
        system = eliminated[0] if eliminated else None
        if system is not None and not problem.layout().same_coordinates(system.lin.layout):
            system = None  # other free coordinates: a step of its own
        if system is not None:
            # a chord step: the first step's elimination with the gradient here
            layout = system.lin.layout
            evaluation = evaluation_of(problem)
            g_p, centroid, noise = corrected_plane_gradient(evaluation, block, points)
            step = system.step(problem.gradient(evaluation, layout), [g_p])
        else:
            if solved is not None and problem is solved.problem and planes is inputs.planes:
                # the round's own evaluation and normal equations at this estimate
                evaluation, lin = solved.evaluation, solved.linearization
                layout = lin.layout
            else:
                layout = problem.layout()
                evaluation = evaluation_of(problem)
                lin = problem.linearize(evaluation, layout)
            terms, centroid, noise = corrected_plane_terms(
                problem, evaluation, layout, block, points
            )
            system = eliminate_nuisance(
                lin, [whole_trajectory(lin, terms, gauge_hold(layout))], lm.truncation
            )
            eliminated[:] = [system]
            step = system.step()
        cost = evaluation.cost - noise_cost(plane, normal, rays, noise)
        last_step[:] = [(system.lin, step)]

        def trial(fraction: float) -> Stepped[tuple[CalibrationState, Planes]]:
            moved = state_from_values(state, problem.retracted_values(fraction * step.dx, layout))
            stepped = stepped_planes(planes, centroid, fraction * step.dp)
            moved_problem = inputs.problem(moved, stepped)
            # the same points and residuals: the assembly's pattern and groupings carry over
            moved_problem.share_assembly_caches(problem)
            return (moved, stepped), moved_problem

        return cost, step, trial

    (state, planes), problem, steps, cost_start = planes_free_steps(
        problem, (state, inputs.planes), step_at, "Planes-free step", corrected_cost, max_steps
    )
    return PlanesFreeSteps(
        state,
        planes,
        problem,
        steps,
        cost_start,
        noise_part,
        points_and_rays,
        evaluation_of(problem),
        last_step[0],
    )
