"""A planes-free refinement of the joint multi-segment problem.

With LiDAR intrinsics estimated, the joint rounds hold each segment's map planes fixed, which
pull the common mode of the range offsets and scales towards the values the maps were built
with, as in a single segment's rounds (:mod:`licalib_cli.pipeline.free_planes`). Gauss-Newton
steps here estimate the trajectories, the calibration and every segment's planes together. A
segment's planes couple only with its own trajectory and blocks and with the shared
calibration, so the step eliminates one segment at a time (its trajectory by the banded
factor, then its planes) and adds its reduced system to the shared calibration's
(:func:`~licalib_cli.solver.nuisance.segmented_nuisance_step`): memory is bounded by one
segment's dense blocks, not by the product of all trajectories and all planes. Each segment's
gauge is held at its first control point; a step is kept only when it lowers the joint cost.
The solver then settles the joint problem on the refined planes and its report gives the joint
sigmas.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.estimation import CalibrationState, FreeParameters, Planes, state_from_values
from licalib_cli.pipeline.free_planes import (
    PlanePoints,
    Stepped,
    corrected_plane_terms,
    expected_noise_cost,
    gauge_hold,
    noise_cost,
    planes_free_steps,
    stepped_planes,
)
from licalib_cli.pipeline.joint_problem import (
    RenamedBlock,
    joint_problem,
    segment_name,
    segment_values,
    values_of_segment,
)
from licalib_cli.pipeline.round import RoundInputs
from licalib_cli.residuals import TRAJ_R3, TRAJ_SO3, PointToPlaneResidual
from licalib_cli.solver.lm import LMParams, SolverReport, solve
from licalib_cli.solver.nuisance import (
    NuisanceSegment,
    NuisanceStep,
    segmented_nuisance_step,
)
from licalib_cli.solver.problem import Evaluation, Layout, Problem

__all__ = ["JointPlaneRefinement", "refine_segments_with_planes"]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class JointPlaneRefinement:
    """The outcome of :func:`refine_segments_with_planes`.

    Attributes:
        states: each segment's refined state (shared blocks equal).
        inputs: each segment's inputs with its refined planes.
        report: the joint solver's report at the refined estimate (planes held at their refined
            values).
        steps: steps kept.
        cost_start: joint cost with the rounds' planes before the refinement, without the range
            noise's expected part (the cost the steps lower).
        cost_end: the same with the refined planes after it.
        seconds: wall time.
    """

    states: tuple[CalibrationState, ...]
    inputs: tuple[RoundInputs, ...]
    report: SolverReport
    steps: int
    cost_start: float
    cost_end: float
    seconds: float


def _lidar_blocks(problem: Problem, count: int) -> list[int] | None:
    """Index of each segment's point-to-plane block in the joint problem (None if one has
    none)."""
    found: list[int] = []
    for k in range(count):
        prefix = segment_name(k, "")
        index = next(
            (
                i
                for i, r in enumerate(problem.residual_blocks)
                if isinstance(r, RenamedBlock)
                and r.name.startswith(prefix)
                and isinstance(r.inner, PointToPlaneResidual)
                and len(r.inner) > 0
            ),
            None,
        )
        if index is None:
            return None
        found.append(index)
    return found


def _nuisance_segment(
    problem: Problem,
    evaluation: Evaluation,
    layout: Layout,
    k: int,
    block: int,
    state: CalibrationState,
    data: RoundInputs,
    planes: Planes,
    range_noise: F64,
) -> tuple[NuisanceSegment, F64, float]:
    """Segment ``k``'s part of the joint problem with its planes as nuisance (their terms
    without the range noise's expected part: :func:`~licalib_cli.pipeline.free_planes.
    noise_corrected`), the planes' centroids and the noise's expected part of its cost
    (``range_noise``: (N,) each of its points' range noise, m).

    Its trajectory coordinates are those of its own blocks; its calibration coordinates the
    shared ones and its own (time offset, drifts); its gauge is its first control point.
    """
    residual = problem.residual_blocks[block]
    assert isinstance(residual, RenamedBlock) and isinstance(residual.inner, PointToPlaneResidual)
    points = PlanePoints.mapped(
        state, data.points, residual.inner.whitening(), data.lidar.plane, planes, range_noise
    )
    terms, centroid, noise = corrected_plane_terms(problem, evaluation, layout, block, points)
    expected = noise_cost(points.plane, points.normal, points.rays, noise)
    nt = layout.num_trajectory
    prefix = segment_name(k, "")
    owner = np.asarray(layout.owner, dtype=str)
    mine = np.char.startswith(owner, prefix)
    trajectory = np.flatnonzero(mine[:nt])
    foreign = [b for b in layout.block_names if _per_segment(b) and not b.startswith(prefix)]
    calibration = np.flatnonzero(~np.isin(owner[nt:], foreign))
    hold = gauge_hold(layout, segment_name(k, TRAJ_SO3), segment_name(k, TRAJ_R3))
    return NuisanceSegment(trajectory, terms, hold, calibration), centroid, expected


def _per_segment(block: str) -> bool:
    """Whether a joint block name is some segment's own copy."""
    head, sep, _ = block.partition(":")
    return bool(sep) and head.startswith("seg") and head[3:].isdigit()


def refine_segments_with_planes(
    states: Sequence[CalibrationState],
    inputs: Sequence[RoundInputs],
    free: FreeParameters,
    lm: LMParams,
) -> JointPlaneRefinement | None:
    """Gauss-Newton steps of the joint problem with every segment's planes free, then the solver.

    As :func:`~licalib_cli.pipeline.free_planes.refine_with_planes` for one segment: the joint
    rounds hold each segment's map planes fixed, which pull the common mode of the range offsets
    and scales back towards the values the maps were built with. Each step estimates the
    trajectories, the calibration and every plane together
    (:func:`~licalib_cli.solver.nuisance.segmented_nuisance_step`: a segment's planes couple only
    with its own trajectory and blocks and with the shared calibration, so the segments are
    eliminated one at a time and only one segment's dense blocks exist at once), each segment's
    gauge held at its first control point. A step (or a half or a quarter of it) is kept only
    when it lowers the joint cost with the stepped planes.

    Args:
        states: each segment's estimate after the joint rounds (shared blocks equal).
        inputs: each segment's final round inputs (points, associations, planes).
        free: what the joint problem estimates.
        lm: the solver settings (their truncation rule applies to the steps too).

    Returns:
        The refinement, or None when a segment has no LiDAR points.

    Raises:
        SolverError: the solver failed on the refined planes.
    """
    start = time.perf_counter()

    def build(st: Sequence[CalibrationState], pl: Sequence[Planes]) -> Problem:
        return joint_problem(
            st, [replace(d, planes=p) for d, p in zip(inputs, pl, strict=True)], free
        )

    problem = build(states, [d.planes for d in inputs])
    blocks = _lidar_blocks(problem, len(states))
    if blocks is None:
        return None
    Current = tuple[list[CalibrationState], list[Planes]]
    range_noise = [d.noise.range_noise(d.points.beam) for d in inputs]

    def step_at(
        problem: Problem, current: Current
    ) -> tuple[float, NuisanceStep, Callable[[float], Stepped[Current]]]:
        states, planes = current
        layout = problem.layout()
        evaluation = problem.evaluate(jacobians=True)
        lin = problem.linearize(evaluation, layout)
        parts = [
            _nuisance_segment(
                problem, evaluation, layout, k, b, states[k], inputs[k], planes[k], range_noise[k]
            )
            for k, b in enumerate(blocks)
        ]
        step = segmented_nuisance_step(lin, [seg for seg, _, _ in parts], lm.truncation)
        split = np.cumsum([p.d.shape[0] for p in planes])[:-1]
        dps = np.split(step.dp, split)

        def trial(fraction: float) -> Stepped[Current]:
            values = problem.retracted_values(fraction * step.dx, layout)
            moved = [
                state_from_values(s, values_of_segment(values, k)) for k, s in enumerate(states)
            ]
            stepped = [
                stepped_planes(p, c, fraction * dp)
                for p, (_, c, _), dp in zip(planes, parts, dps, strict=True)
            ]
            return (moved, stepped), build(moved, stepped)

        # the evaluation and the normal equations are freed on return: while the fractions
        # are tried only the step and the segments' terms and centroids are held
        return evaluation.cost - sum(e for _, _, e in parts), step, trial

    def corrected_cost(problem: Problem, current: Current) -> float:
        states, planes = current
        expected = 0.0
        for k, b in enumerate(blocks):
            residual = problem.residual_blocks[b]
            assert isinstance(residual, RenamedBlock)
            assert isinstance(residual.inner, PointToPlaneResidual)
            expected += expected_noise_cost(
                residual.inner, inputs[k], states[k], planes[k], range_noise[k]
            )
        return problem.evaluate(jacobians=False).cost - expected

    (states, planes), problem, steps, cost_start = planes_free_steps(
        problem,
        (list(states), [d.planes for d in inputs]),
        step_at,
        "Joint planes-free step",
        corrected_cost,
    )
    report = solve(problem, lm)
    states = [state_from_values(s, segment_values(problem, k)) for k, s in enumerate(states)]
    return JointPlaneRefinement(
        states=tuple(states),
        inputs=tuple(replace(d, planes=p) for d, p in zip(inputs, planes, strict=True)),
        report=report,
        steps=steps,
        cost_start=cost_start,
        cost_end=corrected_cost(problem, (states, planes)),
        seconds=time.perf_counter() - start,
    )
