"""How far estimating a fixed effect would move the extrinsic, with the map planes estimated too.

The score tests (:func:`~licalib_cli.pipeline.fitcheck.effect_evidence`) linearise the final
problem with the surfel planes held where the final round fitted them. Those planes were fitted
to points mapped with the biased estimate, so they already absorb part of an effect the model
lacks, and a step with them held fixed pulls the extrinsic back towards the values the map was
built with. For a LiDAR effect that moves whole planes (a range offset moves every point along
its ray) the held planes hide most of the bias: on a 10 s OS1-64 shake with per-beam range
offsets of twice the paper's size, the extrinsic was 18 mm off, the planes-fixed step moved it
by 2.2 mm, a refit with the range offsets and the planes free by 16 mm, and the step computed
here by 14 mm.

This stage computes the same step with the planes as unknowns of the same residuals
(:func:`~licalib_cli.solver.nuisance.marginal_system`; each plane's two normal directions and
its offset, the range noise's expected part taken out as in
:mod:`licalib_cli.pipeline.free_planes`, the gauge held at the first control point; a plane
whose own information is singular or indefinite held where it is), for the LiDAR effects
whose shift the reported sigmas may have to cover. The tests' statistics are not changed: with
the planes free, a range offset's common mode is nearly a move of every plane towards the
sensor, and the test would lose the power that names it. IMU effects keep the planes-fixed
shift (see :func:`~licalib_cli.pipeline.fitcheck.effect_evidence`), but what the IMU blocks
held to their priors add to the sigmas is computed with the planes free too
(:func:`planes_free_spreads`): a posterior spread is bounded by its prior. Not beside estimated
LiDAR intrinsics (see :func:`~licalib_cli.pipeline.fitcheck._planes_free_prior`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from licalib_cli.consistency import score_effects
from licalib_cli.estimation import CalibrationState, Planes
from licalib_cli.pipeline.free_planes import (
    PlanePoints,
    corrected_plane_terms,
    gauge_hold,
    lidar_block,
)
from licalib_cli.pipeline.points import PointSample
from licalib_cli.residuals import PointToPlaneResidual
from licalib_cli.solver.nuisance import marginal_system
from licalib_cli.solver.problem import Evaluation, Linearization, Problem

__all__ = [
    "MIN_PLANE_INFORMATION",
    "freed_before",
    "planes_free_shifts",
    "planes_free_spreads",
    "planes_free_system",
]

F64 = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

MIN_PLANE_INFORMATION = 1e-6
"""A plane is held where it is when the smallest eigenvalue of its own (Jacobi-scaled)
information, the range noise's part taken out, is below this."""


def planes_free_shifts(
    system: tuple[F64, F64, IntArray],
    base: Sequence[int],
    wanted: Mapping[str, tuple[IntArray, Sequence[IntArray]]],
    variance_factor: float,
) -> dict[str, tuple[F64, F64]]:
    """The shift of the estimated coordinates, and its null spread, per effect, planes free.

    Args:
        system: :func:`planes_free_system` over ``base`` and every coordinate of ``wanted``
            (more are held: only those rows are used).
        base: calibration coordinates the round estimated (indices into ``lin``'s).
        wanted: effect name -> (its coordinates, the groups freed with it: the effects selected
            before it).
        variance_factor: the fit's a-posteriori variance factor.

    Returns:
        name -> ``(shift, shift_sigma)``, each (len(base),) in ``base``'s order.
    """
    s, b, at = system
    base_idx = np.asarray(base, dtype=np.intp)
    out = {}
    for name, (group, freed) in wanted.items():
        current = np.concatenate([at[base_idx], *(at[np.asarray(c)] for c in freed)])
        score = score_effects(s, b, current, {name: at[np.asarray(group)]}, variance_factor)[0]
        out[name] = (score.shift[: base_idx.size], score.shift_sigma[: base_idx.size])
    return out


def planes_free_system(
    problem: Problem,
    evaluation: Evaluation,
    lin: Linearization,
    state: CalibrationState,
    sample: PointSample,
    plane: IntArray,
    planes: Planes,
    range_noise: F64,
    columns: IntArray,
) -> tuple[F64, F64, IntArray] | None:
    """The calibration coordinates' information with the map planes free as well.

    Args:
        problem: the final problem with every effect free (its LiDAR block's whitening as the
            tests use it).
        evaluation: its evaluation with Jacobians at ``state``.
        lin: its normal equations.
        state: the final estimate.
        sample: the points of the LiDAR block, as sampled (the same order).
        plane: (N,) each point's plane.
        planes: the planes.
        range_noise: (N,) each point's range noise, m.
        columns: the calibration coordinates to keep (indices into ``lin``'s, sorted); the
            others are held.

    Returns:
        ``(S, b, at)``: the Schur complement over ``columns`` (trajectory and planes
        eliminated), its right-hand side, and ``at`` mapping each of ``lin``'s calibration
        coordinates to its row (-1: not kept); None when the problem has no LiDAR points.
    """
    block = lidar_block(problem)
    if block is None:
        return None
    residual = problem.residual_blocks[block]
    assert isinstance(residual, PointToPlaneResidual)
    layout = lin.layout
    points = PlanePoints.mapped(state, sample, residual.whitening(), plane, planes, range_noise)
    terms, _, _ = corrected_plane_terms(problem, evaluation, layout, block, points)
    held = _degenerate(terms.H_pp)
    if np.any(held):
        # Held where they are: a plane whose own information is singular or, with the range
        # noise's part taken out, indefinite (a few points, or points along one scan line).
        # Its undetermined directions would be dropped anyway; held, the rest of the planes'
        # elimination takes a Cholesky factor instead of an eigen-decomposition (0.2 s
        # instead of 1.7 s for 750 planes).
        keep = np.repeat(~held, 3).astype(np.float64)
        terms = replace(
            terms,
            H_xp=sp.csr_matrix(terms.H_xp @ sp.diags(keep)),
            H_pp=np.where(held[:, None, None], np.eye(3), terms.H_pp),
            g_p=np.where(held[:, None], 0.0, terms.g_p),
        )
    columns = np.asarray(columns, dtype=np.intp)
    s, b = marginal_system(lin, terms, gauge_hold(layout), columns)
    at = np.full(layout.num_calibration, -1, dtype=np.intp)
    at[columns] = np.arange(columns.size)
    return s, b, at


def _degenerate(h_pp: F64) -> npt.NDArray[np.bool_]:
    """(G,) planes whose own (G, 3, 3) information is singular or indefinite
    (:data:`MIN_PLANE_INFORMATION`)."""
    diag = np.einsum("gii->gi", h_pp)
    ok = np.all(diag > 0.0, axis=1)
    d = 1.0 / np.sqrt(np.where(diag > 0.0, diag, 1.0))
    scaled = d[:, :, None] * h_pp * d[:, None, :]
    low = np.linalg.eigvalsh(0.5 * (scaled + np.swapaxes(scaled, 1, 2)))[:, 0]
    return ~ok | (low < MIN_PLANE_INFORMATION)


def freed_before(name: str, selected: Sequence[str]) -> Sequence[str]:
    """The effects a test of ``name`` frees with it, as the forward selection tested it: the
    ones ``selected`` before it, or all of them when it was not selected."""
    return selected[: selected.index(name)] if name in selected else selected


def planes_free_spreads(
    system: tuple[F64, F64, IntArray],
    base: Sequence[int],
    groups: Mapping[str, Sequence[int]],
    prior: Mapping[str, F64],
    selected: Sequence[str],
    variance_factor: float,
) -> dict[str, F64]:
    """What each block held to its prior adds to the estimate, with the map planes free.

    Args:
        system: :func:`planes_free_system` over ``base``, every group with a prior and the
            ``selected`` groups.
        base: calibration coordinates the round estimated (indices into the layout's).
        groups: effect name -> its coordinates.
        prior: effect name -> (k,) prior sigma of each coordinate (the blocks with a prior).
        selected: the effects the forward selection added, in order: each block is freed with
            :func:`freed_before`, as the tests were.
        variance_factor: the fit's a-posteriori variance factor.

    Returns:
        Per block with a prior, the spread its posterior adds to the estimated coordinates
        (len(base),) (:attr:`~licalib_cli.consistency.EffectScore.prior_shift_sigma`).
    """
    s, b, at = system
    base_idx = np.asarray(base, dtype=np.intp)
    spread = {}
    for name in prior:
        freed = [np.asarray(groups[n], dtype=np.intp) for n in freed_before(name, selected)]
        current = np.concatenate([at[base_idx], *(at[c] for c in freed)])
        (score,) = score_effects(
            s,
            b,
            current,
            {name: at[np.asarray(groups[name], dtype=np.intp)]},
            max(variance_factor, 1.0),
            prior_sigma={name: prior[name]},
        )
        spread[name] = score.prior_shift_sigma[: base_idx.size]
    return spread
