"""Levenberg-Marquardt with a Schur complement and an observability-aware (TSVD) update.

Each iteration solves the damped normal equations ``(H + lambda diag(D)) dx = -g`` where
``D = clip(diag(H), min_diagonal, max_diagonal)`` (Marquardt scaling):

1. Eliminate the trajectory group: factorise ``H_tt + lambda D_t`` (banded Cholesky of the
   reordered spline coordinates plus a dense border of biases and gravity; sparse LU when that
   does not apply, see :func:`licalib_cli.solver.schur.schur_complement`), Schur complement
   ``S = H_cc - H_ct (H_tt + lambda D_t)^-1 H_tc`` and right-hand side ``b`` (method.md section 8).
2. Scale the calibration system by the characteristic scales ``d`` (``S_d = D S D``, see
   :mod:`licalib_cli.solver.observability`). The eigen-decomposition ``S0_d = U diag(s) U^T`` of the
   *undamped* Schur complement (computed once per linearisation) decides the truncation: damping
   ``H_tt`` would charge the trajectory for absorbing a calibration direction and make such a
   direction look observable.
3. TSVD: keep the directions with ``s_i > epsilon`` (``LMParams.tsvd_threshold``; absolute in
   scaled information units, or relative to ``max s`` with ``tsvd_relative``) and solve the
   damped system restricted to them: ``dx_c = D U_l (U_l^T (S_d + lambda D_c') U_l)^-1 U_l^T D
   b``, which is the paper's ``sum_{i<=l} u_i^T b u_i / s_i`` at ``lambda = 0``. The
   calibration step has no component along truncated directions (in the scaled metric): those
   stay at their current value. A direction below the threshold but at least
   ``LMParams.weak_floor`` of it and made mostly of the extrinsic is weakly determined: kept,
   its standard deviation reported (:func:`weak_mask`).
4. Back-substitute the trajectory step, retract every block, and accept the step when the actual
   cost reduction is at least ``1e-3`` of the reduction predicted by the quadratic model; update
   ``lambda`` as in Nielsen (1999).

At the final estimate the report holds the undamped ``S_d`` spectrum, the truncated directions
named in parameter terms, and the standard deviation of every calibration coordinate from the
TSVD pseudo-inverse ``D U_l diag(1/s_l) U_l^T D`` (whitened residuals: unit covariance).
Coordinates with a weight of at least ``NOT_OBSERVABLE_WEIGHT`` (squared) in a truncated direction
are reported as not observable (standard deviation ``inf``). A truncated direction made mostly of
intrinsics known a priori to within their characteristic scale adds that scale along it instead;
:func:`widen_along_truncated` adds how far a fit of several linearisations moved along it.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla

from licalib_cli.errors import SolverError
from licalib_cli.solver.observability import (
    DirectionDescription,
    InformationSummary,
    Truncation,
    absolute_threshold,
    describe_direction,
    kept_directions,
    mostly_free,
    summarize_information,
    undamped_schur_system,
    weak_directions,
)
from licalib_cli.solver.problem import Evaluation, Linearization, Problem
from licalib_cli.solver.schur import schur_complement

__all__ = [
    "NOT_OBSERVABLE_WEIGHT",
    "IterationSummary",
    "LMParams",
    "Solution",
    "SolverReport",
    "Step",
    "compute_step",
    "kept_mask",
    "observable_basis",
    "observable_coordinates",
    "solve",
    "solve_with_linearization",
    "weak_mask",
    "widen_along_truncated",
]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

NOT_OBSERVABLE_WEIGHT = 1e-4
"""A coordinate whose squared components over the truncated directions sum to at least this is
reported as not observable."""

_WEAK_VERDICT = (
    "weakly determined by the data (singular value {:.2f}, below the threshold: one standard "
    "deviation of {:.1f} characteristic scales along it, which the sigmas include)"
)
"""How a weakly determined direction is described (``LMParams.weak_floor``)."""

_MOVED_VERDICT = (
    "not determined by the data (held in the last step); the fit moved the estimate {:.1f} "
    "characteristic scales along it from its initial value, which the sigmas include"
)
"""How a truncated direction is described once the fit has moved along it by more than one
characteristic scale (it then no longer "stays near its initial value")."""

_MIN_GAIN_RATIO = 1e-3


@dataclass(frozen=True)
class LMParams:
    """Levenberg-Marquardt settings.

    Attributes:
        max_iterations: Maximum number of iterations (accepted or rejected steps).
        initial_lambda: Initial damping ``lambda`` (relative to ``diag(H)``).
        min_decrease: Smallest factor by which ``lambda`` shrinks after a good step (Nielsen's
            rule uses 1/3; problems with weak, well-modelled directions converge faster with a
            smaller factor).
        max_lambda: Give up (status ``failed``) when ``lambda`` exceeds this.
        min_diagonal: Lower clip of ``diag(H)`` in the damping matrix.
        max_diagonal: Upper clip of ``diag(H)`` in the damping matrix.
        function_tolerance: Converged when an accepted step (or the model's prediction) reduces
            the cost by less than this fraction.
        step_tolerance: Converged when ``max_i |dx_i| / scale_i`` is below this (steps measured
            in characteristic scales).
        gradient_tolerance: Converged when ``max_i |g_i| * scale_i`` is below this (cost per
            characteristic scale).
        cost_tolerance: Converged when the next step is predicted to reduce the cost by less
            than this (absolute, in the cost's units: half the whitened chi-square); 0 leaves it
            to ``function_tolerance``.
        use_tsvd: Solve the calibration step with the truncated SVD (else a plain damped solve).
        tsvd_threshold: ``epsilon`` on the singular values of the scaled Schur complement
            ``S_d``; absolute by default (1.0 = standard deviation of one characteristic scale).
        tsvd_relative: Interpret ``tsvd_threshold`` as a fraction of the largest singular value.
        weak_floor: A direction below the threshold whose singular value is at least this
            fraction of it and which lies mostly outside ``bounded_blocks`` (the extrinsic, the
            time offset) is weakly determined: estimated like the others, its standard deviation
            (1 to ``1 / sqrt(weak_floor)`` characteristic scales) in the sigmas, and named in
            the report's ``weak`` (0: every direction below the threshold is truncated).
        bounded_blocks: Prefixes of calibration blocks whose coordinates are known a priori to
            within their characteristic scale (the intrinsics): a truncated direction made
            mostly of them adds that much uncertainty to the coordinates it touches instead of
            making them unobservable. Biases are not calibration blocks.
        verbose: Log every iteration at INFO (else DEBUG).
    """

    max_iterations: int = 50
    initial_lambda: float = 1e-4
    min_decrease: float = 1.0 / 3.0
    max_lambda: float = 1e16
    min_diagonal: float = 1e-6
    max_diagonal: float = 1e32
    function_tolerance: float = 1e-8
    step_tolerance: float = 1e-6
    gradient_tolerance: float = 1e-10
    cost_tolerance: float = 0.0
    use_tsvd: bool = True
    tsvd_threshold: float = 1.0
    tsvd_relative: bool = False
    weak_floor: float = 0.1
    bounded_blocks: tuple[str, ...] = (
        "imu.gyro_",
        "imu.accel_scale",
        "imu.accel_misalignment",
        "lidar.",
    )
    verbose: bool = False

    @property
    def truncation(self) -> Truncation:
        """The rule for which calibration directions a step moves along, for the steps taken
        outside :func:`solve` (:func:`~licalib_cli.solver.nuisance.eliminate_nuisance`)."""
        if not self.use_tsvd:
            return Truncation(0.0, bounded_blocks=self.bounded_blocks)
        return Truncation(
            self.tsvd_threshold, self.tsvd_relative, self.weak_floor, self.bounded_blocks
        )


@dataclass(frozen=True)
class IterationSummary:
    """One LM iteration, as passed to the progress callback.

    Attributes:
        iteration: 1-based iteration number.
        cost: Cost before the step.
        trial_cost: Cost at the trial point (``nan`` when no trial was evaluated).
        lambda_: Damping used.
        step_norm: ``max |dx_i| / scale_i``.
        gain_ratio: Actual / predicted cost reduction.
        accepted: Whether the step was taken.
        num_truncated: Calibration directions truncated by the TSVD in this step.
        elapsed_s: Wall time since the start of :func:`solve`.
    """

    iteration: int
    cost: float
    trial_cost: float
    lambda_: float
    step_norm: float
    gain_ratio: float
    accepted: bool
    num_truncated: int
    elapsed_s: float


@dataclass(frozen=True)
class Step:
    """A solved LM step.

    Attributes:
        dx: (Nt + Nc,) step in solver order.
        predicted_reduction: Cost reduction predicted by the undamped quadratic model.
        num_truncated: Calibration directions truncated.
    """

    dx: F64
    predicted_reduction: float
    num_truncated: int


@dataclass(frozen=True)
class SolverReport:
    """Why and where the solver stopped, and what the data determine.

    Attributes:
        status: ``"converged"``, ``"max_iterations"`` or ``"failed"``.
        reason: Why it stopped, in words.
        iterations: Iterations run (accepted or rejected steps).
        cost_history: Cost at the start and after every accepted step.
        initial_cost: ``cost_history[0]``.
        final_cost: ``cost_history[-1]``.
        num_residuals: Scalar residuals at the final estimate.
        num_parameters: Free tangent coordinates (trajectory + calibration).
        variance_factor: A-posteriori variance factor ``2 cost / (num_residuals -
            num_parameters)`` (``nan`` without redundancy); 1 when the noise model fits.
        calibration_names: (Nc,) free calibration coordinates.
        information: Undamped scaled calibration information at the final estimate (singular
            values, vectors and the scaling used).
        singular_values: (Nc,) same as ``information.singular_values`` (descending).
        scaling: Statement of the scaling used.
        tsvd_threshold: ``epsilon`` in absolute scaled units as applied.
        truncated: Truncated (not observable) directions, weakest first, named in parameter
            terms.
        std: (Nc,) standard deviation of each calibration coordinate in its own unit, from the
            TSVD pseudo-inverse of the undamped Schur complement; ``inf`` where not observable.
        observable: (Nc,) False for coordinates lying in a truncated direction.
        elapsed_s: Wall time of :func:`solve`.
        covariance: (Nc, Nc) covariance of the calibration coordinates (own units), the TSVD
            pseudo-inverse of the undamped Schur complement (zero along truncated directions).
        truncated_weight: (Nc,) share of each coordinate (scaled) lying in truncated
            directions: near 1 for a coordinate the data do not determine at all.
        weak: Weakly determined directions (below the threshold, estimated, their standard
            deviation in the sigmas: ``LMParams.weak_floor``), weakest first.
        weak_floor: ``LMParams.weak_floor`` as applied (0 without the TSVD: nothing weak).
    """

    status: Literal["converged", "max_iterations", "failed"]
    reason: str
    iterations: int
    cost_history: tuple[float, ...]
    initial_cost: float
    final_cost: float
    num_residuals: int
    num_parameters: int
    variance_factor: float
    calibration_names: tuple[str, ...]
    information: InformationSummary
    singular_values: F64
    scaling: str
    tsvd_threshold: float
    truncated: tuple[DirectionDescription, ...]
    std: F64
    observable: npt.NDArray[np.bool_]
    elapsed_s: float
    covariance: F64 = field(default_factory=lambda: np.zeros((0, 0)))
    truncated_weight: F64 = field(default_factory=lambda: np.zeros(0))
    weak: tuple[DirectionDescription, ...] = ()
    weak_floor: float = 0.0

    @property
    def converged(self) -> bool:
        """Whether the status is ``"converged"``."""
        return self.status == "converged"

    def std_of(self, name: str) -> float:
        """Standard deviation of the calibration coordinate called ``name``."""
        return float(self.std[self.calibration_names.index(name)])


@dataclass(frozen=True)
class Solution:
    """The solver's report with the problem's normal equations at the estimate.

    Attributes:
        report: the solver's report.
        evaluation: residuals and Jacobians at the estimate (the problem's values on return).
        linearization: the normal equations at the estimate, those the report's spectrum and
            sigmas come from.
    """

    report: SolverReport
    evaluation: Evaluation
    linearization: Linearization


def _damping_diagonal(diag: F64, params: LMParams) -> F64:
    return np.clip(diag, params.min_diagonal, params.max_diagonal)


def observable_basis(information: InformationSummary, params: LMParams) -> F64:
    """Directions the TSVD keeps (:func:`kept_mask`), decided on the undamped information.

    Args:
        information: Undamped scaled calibration information (:func:`undamped_schur`).
        params: Solver settings (TSVD threshold, weak floor).

    Returns:
        (Nc, l) orthonormal columns in scaled coordinates: the singular vectors kept (all
        coordinates when ``params.use_tsvd`` is False).
    """
    if not params.use_tsvd:
        return np.eye(information.singular_values.size)
    return information.singular_vectors[:, kept_mask(information, params)]


def kept_mask(information: InformationSummary, params: LMParams) -> npt.NDArray[np.bool_]:
    """(Nc,) which singular directions of ``information`` the TSVD keeps: those above the
    threshold, and the weakly determined ones (:func:`weak_mask`)."""
    return kept_directions(
        information.singular_values,
        information.singular_vectors,
        information.owners,
        params.tsvd_threshold,
        relative=params.tsvd_relative,
        floor=params.weak_floor if params.use_tsvd else 0.0,
        bounded_blocks=params.bounded_blocks,
    )


def weak_mask(information: InformationSummary, params: LMParams) -> npt.NDArray[np.bool_]:
    """(Nc,) the weakly determined singular directions of ``information``: below the threshold,
    at least ``params.weak_floor`` of it, made mostly of coordinates outside
    ``params.bounded_blocks`` (the extrinsic, the time offset).

    Such a direction is estimated and its standard deviation (1 to ``1 / sqrt(weak_floor)``
    characteristic scales) reported. Held, it kept the estimate where the fit left it: on a
    10 s OS1-64 shake with the simulator's intrinsic errors and the gyro-to-IMU rotation
    estimated, the extrinsic rotation along the direction it trades with that rotation had a
    singular value of 0.77; held, the result failed as not determined (and without the gyro
    rotation it was 25 mm / 0.96 deg off); estimated, 3.5 mm / 0.059 deg off within 1.7 of its
    sigmas. A direction of the intrinsics is truncated below the threshold: they start at their
    nominal values, known to their characteristic scale, and a pull far beyond that came from
    what the model lacked (a 10 s OS1-64 shake with per-beam horizontal offsets: the beams'
    common offset, pulled 5.8 standard deviations in the refit that added them, then 0.050 deg
    off in the extrinsic rotation instead of 0.012).
    """
    s = information.singular_values
    return weak_directions(
        s,
        information.singular_vectors,
        information.owners,
        _absolute_threshold(s, params),
        floor=params.weak_floor if params.use_tsvd else 0.0,
        bounded_blocks=params.bounded_blocks,
    )


def _absolute_threshold(singular_values: F64, params: LMParams) -> float:
    """``params.tsvd_threshold`` in singular-value units (times the largest when relative)."""
    return absolute_threshold(singular_values, params.tsvd_threshold, relative=params.tsvd_relative)


def _undamped_information(lin: Linearization) -> InformationSummary:
    """The undamped scaled calibration information."""
    layout = lin.layout
    return summarize_information(
        undamped_schur_system(lin).S,
        layout.calibration_names,
        layout.calibration_owner,
        layout.calibration_scale,
        lin.num_residuals,
    )


def _kept_basis(
    lin: Linearization, params: LMParams
) -> tuple[InformationSummary | None, F64 | None]:
    """The undamped information (None without the TSVD) and the directions a step may take."""
    if not params.use_tsvd:
        return None, None
    info = _undamped_information(lin)
    return info, observable_basis(info, params)


def compute_step(
    lin: Linearization, lam: float, params: LMParams, basis: F64 | None = None
) -> Step:
    """Solve one damped step with the Schur complement and (optionally) the TSVD.

    The truncation is decided on the undamped Schur complement: damping the trajectory block
    charges the trajectory for absorbing a calibration direction and so makes a direction that
    the trajectory can absorb look observable. The damped system is then solved restricted to the
    kept directions.

    Args:
        lin: Normal equations at the current estimate.
        lam: Damping ``lambda`` (0 for a Gauss-Newton step).
        params: Solver settings (damping clips, TSVD threshold).
        basis: (Nc, l) kept directions in scaled coordinates (:func:`observable_basis`); computed
            from ``lin`` when omitted.

    Returns:
        The step.
    """
    layout = lin.layout
    nc = layout.num_calibration
    if nc and basis is None:
        basis = _kept_basis(lin, params)[1] if params.use_tsvd else np.eye(nc)
    d_t = lam * _damping_diagonal(lin.H_tt.diagonal(), params)
    sch = schur_complement(lin, d_t)
    num_truncated = 0
    if nc:
        assert basis is not None
        scale = layout.calibration_scale
        s_d = scale[:, None] * sch.S * scale[None, :]
        b_d = scale * sch.b
        damp = lam * _damping_diagonal(np.diag(lin.H_cc), params) * scale**2
        num_truncated = int(nc - basis.shape[1])
        reduced = basis.T @ s_d @ basis + (basis.T * damp) @ basis
        y = basis @ _solve_spd(0.5 * (reduced + reduced.T), basis.T @ b_d)
        dc = scale * y
    else:
        dc = np.zeros(0)
    dx = np.concatenate([sch.back_substitute(dc), dc])
    predicted = -(float(lin.g @ dx) + 0.5 * lin.quadratic(dx))
    return Step(dx, predicted, num_truncated)


def _solve_spd(a: F64, b: F64) -> F64:
    if a.size == 0:
        return np.zeros(0)
    try:
        return np.asarray(sla.solve(a, b, assume_a="pos"), dtype=np.float64)
    except (np.linalg.LinAlgError, sla.LinAlgError):
        return np.asarray(np.linalg.lstsq(a, b, rcond=None)[0], dtype=np.float64)


def solve(
    problem: Problem,
    params: LMParams | None = None,
    callback: Callable[[IterationSummary], None] | None = None,
) -> SolverReport:
    """Minimise the problem's cost in place with Levenberg-Marquardt.

    Args:
        problem: The problem; its parameter blocks hold the initial values and receive the
            estimate.
        params: Solver settings (default :class:`LMParams`).
        callback: Called after every iteration (progress hook).

    Returns:
        The solver report.

    Raises:
        SolverError: When the initial cost is not finite.
    """
    return solve_with_linearization(problem, params, callback).report


def solve_with_linearization(
    problem: Problem,
    params: LMParams | None = None,
    callback: Callable[[IterationSummary], None] | None = None,
    *,
    evaluation: Evaluation | None = None,
) -> Solution:
    """:func:`solve`, also returning the evaluation and the normal equations at the estimate
    (for later analyses of the same problem at the same state, which then need not evaluate
    and linearise it again).

    ``evaluation``: the problem's evaluation with Jacobians at its current values, when the
    caller has it (it is not evaluated again); None: evaluated here.

    Raises:
        SolverError: When the initial cost is not finite.
    """
    params = LMParams() if params is None else params
    start = time.perf_counter()
    log = logger.info if params.verbose else logger.debug
    layout = problem.layout()
    if evaluation is None:
        evaluation = problem.evaluate(jacobians=True)
    if not math.isfinite(evaluation.cost):
        msg = (
            "The residuals are not finite at the initial estimate; check the initial values "
            "and the input data for NaN or infinite numbers."
        )
        raise SolverError(msg)
    lin = problem.linearize(evaluation, layout)
    # The truncation is decided once per linearisation (without the TSVD only the report needs
    # the undamped information, at the end).
    info, basis = _kept_basis(lin, params)
    cost = evaluation.cost
    history = [cost]
    lam, nu = params.initial_lambda, 2.0
    scale = layout.scale
    status: Literal["converged", "max_iterations", "failed"] = "max_iterations"
    reason = f"reached max_iterations={params.max_iterations}"
    iteration = 0
    while iteration < params.max_iterations:
        grad_norm = float(np.max(np.abs(lin.g * scale))) if lin.g.size else 0.0
        if grad_norm <= params.gradient_tolerance:
            status = "converged"
            reason = f"gradient {grad_norm:.3g} below gradient_tolerance"
            break
        iteration += 1
        step = compute_step(lin, lam, params, basis)
        step_norm = float(np.max(np.abs(step.dx / scale))) if step.dx.size else 0.0
        if step_norm <= params.step_tolerance:
            status = "converged"
            reason = f"step {step_norm:.3g} below step_tolerance"
            break
        tolerance = max(params.function_tolerance * cost, params.cost_tolerance)
        if step.predicted_reduction <= tolerance:
            status = "converged"
            reason = "predicted cost reduction below " + (
                "cost_tolerance" if tolerance == params.cost_tolerance else "function_tolerance"
            )
            break
        trial_values = problem.retracted_values(step.dx, layout)
        trial = problem.evaluate(trial_values, jacobians=True)
        actual = cost - trial.cost
        gain = actual / step.predicted_reduction if math.isfinite(trial.cost) else -math.inf
        accepted = gain > _MIN_GAIN_RATIO
        summary = IterationSummary(
            iteration,
            cost,
            trial.cost,
            lam,
            step_norm,
            gain,
            accepted,
            step.num_truncated,
            time.perf_counter() - start,
        )
        log(
            "LM %3d cost %.6e -> %.6e lambda %.1e step %.2e gain %.2f %s truncated %d",
            iteration,
            cost,
            trial.cost,
            lam,
            step_norm,
            gain,
            "accepted" if accepted else "rejected",
            step.num_truncated,
        )
        if callback is not None:
            callback(summary)
        if accepted:
            problem.set_values(trial_values)
            evaluation = trial
            lin = problem.linearize(trial, layout)
            info, basis = _kept_basis(lin, params)
            old_cost, cost = cost, trial.cost
            history.append(cost)
            lam *= max(params.min_decrease, 1.0 - (2.0 * gain - 1.0) ** 3)
            lam = max(lam, 1e-15)
            nu = 2.0
            if actual <= params.function_tolerance * old_cost:
                status = "converged"
                relative = actual / max(old_cost, 1e-300)
                reason = f"relative cost reduction {relative:.3g} below function_tolerance"
                break
        else:
            lam *= nu
            nu *= 2.0
            if lam > params.max_lambda:
                status = "failed"
                reason = f"no step reduced the cost before lambda exceeded {params.max_lambda:g}"
                break
    if info is None:
        info = _undamped_information(lin)
    report = _report(lin, info, params, status, reason, iteration, history, start)
    return Solution(report, evaluation, lin)


def _report(
    lin: Linearization,
    info: InformationSummary,
    params: LMParams,
    status: Literal["converged", "max_iterations", "failed"],
    reason: str,
    iterations: int,
    history: list[float],
    start: float,
) -> SolverReport:
    layout = lin.layout
    s, u = info.singular_values, info.singular_vectors
    keep = kept_mask(info, params)  # without the TSVD: nothing weak, the threshold alone
    weak = tuple(
        describe_direction(
            u[:, i],
            layout.calibration_names,
            layout.calibration_owner,
            verdict=_WEAK_VERDICT.format(s[i], 1.0 / math.sqrt(s[i])),
        )
        for i in np.flatnonzero(weak_mask(info, params))[::-1]
    )
    verdict = (
        "unobservable, not estimated (stays near its initial value)"
        if params.use_tsvd
        else "unobservable (below the TSVD threshold), updated without truncation"
    )
    truncated = tuple(
        describe_direction(
            u[:, i], layout.calibration_names, layout.calibration_owner, verdict=verdict
        )
        for i in np.flatnonzero(~keep)[::-1]
    )
    scale = layout.calibration_scale
    owners = layout.calibration_owner
    trunc = u[:, ~keep] if u.size else np.zeros((0, 0))
    observable, free_dir = observable_coordinates(trunc, owners, params.bounded_blocks)
    if s.size:
        cov_d = (u[:, keep] / s[keep]) @ u[:, keep].T
        if trunc.size and np.any(~free_dir):
            prior = trunc[:, ~free_dir]
            cov_d = cov_d + prior @ prior.T  # one characteristic scale along each
        std = scale * np.sqrt(np.clip(np.diag(cov_d), 0.0, None))
        covariance = scale[:, None] * cov_d * scale[None, :]
    else:
        std = np.zeros(0)
        covariance = np.zeros((0, 0))
    std = np.where(observable, std, np.inf)
    redundancy = lin.num_residuals - layout.num_free
    variance_factor = 2.0 * history[-1] / redundancy if redundancy > 0 else math.nan
    threshold = _absolute_threshold(s, params)
    for d in truncated:
        logger.debug("calibration direction %s", d.text)
    return SolverReport(
        status=status,
        reason=reason,
        iterations=iterations,
        cost_history=tuple(history),
        initial_cost=history[0],
        final_cost=history[-1],
        num_residuals=lin.num_residuals,
        num_parameters=layout.num_free,
        variance_factor=variance_factor,
        calibration_names=layout.calibration_names,
        information=info,
        singular_values=s,
        scaling=info.scaling,
        tsvd_threshold=threshold,
        truncated=truncated,
        std=std,
        observable=observable,
        elapsed_s=time.perf_counter() - start,
        covariance=covariance,
        truncated_weight=np.sum(trunc**2, axis=1) if trunc.size else np.zeros(len(owners)),
        weak=weak,
        weak_floor=params.weak_floor if params.use_tsvd else 0.0,
    )


def observable_coordinates(
    truncated: F64, owners: Sequence[str], bounded_blocks: Sequence[str]
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Which coordinates the truncated directions leave observable, and which of those
    directions leave their coordinates unknown.

    A truncated direction made mostly of bounded coordinates (``bounded_blocks``: intrinsics
    known a priori to within their characteristic scale) only adds that prior uncertainty to the
    coordinates it touches; a direction made mostly of unbounded ones (the extrinsic) leaves them
    unknown: a coordinate with a squared weight of at least :data:`NOT_OBSERVABLE_WEIGHT` in such
    directions is not observable.

    Args:
        truncated: (Nc, k) unit truncated directions (columns), scaled coordinates.
        owners: (Nc,) owning block of each coordinate.
        bounded_blocks: prefixes of the bounded blocks (``LMParams.bounded_blocks``).

    Returns:
        ``(observable, free)``: (Nc,) per coordinate, and (k,) per direction whether it leaves
        its coordinates unknown.
    """
    if truncated.size == 0:
        return np.ones(len(owners), dtype=bool), np.zeros(0, dtype=bool)
    free = mostly_free(truncated, owners, bounded_blocks)
    weight = np.sum(truncated[:, free] ** 2, axis=1)
    return weight < NOT_OBSERVABLE_WEIGHT, free


def widen_along_truncated(
    report: SolverReport, moved: npt.ArrayLike, initial_sd: npt.ArrayLike | None = None
) -> SolverReport:
    """The report with each truncated direction's variance made to cover where the fit's
    initial value put the estimate along it, and how far the fit moved it from there.

    The last linearisation truncates what the data do not determine, and the estimate then
    sits along that direction where the fit left it: at its initial value, plus whatever a fit
    of several linearisations moved along it before (rounds that rebuild the map, intrinsics that
    join late; the direction's information sat near the threshold, or the map moved with the
    estimate). A direction of bounded intrinsics adds one characteristic scale (their prior);
    this makes it ``u^T P0 u + m^2`` (scaled), with ``P0`` the initial value's variance per
    coordinate and ``m = u . (moved / d)`` the fit's move along ``u``. A coordinate already
    reported as not observable stays so. Directions moved by more than one characteristic scale
    are described as such.

    Args:
        report: a solver report at the fit's final estimate.
        moved: (Nc,) final estimate minus initial value of every calibration coordinate, in
            ``report.calibration_names`` order and the coordinates' own units (tangent
            coordinates for rotations).
        initial_sd: (Nc,) standard deviation of each coordinate's initial value, own units
            (default: one characteristic scale each).

    Returns:
        The report with ``covariance``, ``std`` and the truncated directions' text updated (the
        same report when nothing changes).
    """
    moved = np.asarray(moved, dtype=np.float64).reshape(-1)
    names = report.calibration_names
    if not report.truncated or moved.shape[0] != len(names) or report.covariance.size == 0:
        return report
    scale = np.asarray(report.information.scale, dtype=np.float64)
    sd0 = scale if initial_sd is None else np.asarray(initial_sd, dtype=np.float64).reshape(-1)
    vectors = np.stack([d.vector for d in report.truncated], axis=1)  # (Nc, k) scaled
    along = vectors.T @ (moved / scale)  # (k,) characteristic scales
    start = np.sum((vectors * (sd0 / scale)[:, None]) ** 2, axis=0)  # (k,) u^T P0 u
    extra = np.maximum(start - 1.0, 0.0) + along**2  # one scale is in the report already
    if not np.any(extra > 1e-12):
        return report
    own = vectors * scale[:, None] * np.sqrt(extra)[None, :]
    covariance = report.covariance + own @ own.T
    std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    std = np.where(report.observable, std, np.inf)
    owners = report.information.owners
    truncated = tuple(
        describe_direction(d.vector, names, owners, verdict=_MOVED_VERDICT.format(abs(m)))
        if abs(m) > 1.0
        else d
        for d, m in zip(report.truncated, along, strict=True)
    )
    for d, m, v in zip(truncated, along, start, strict=True):
        logger.debug("%.2f characteristic scales moved, %.2f initial, along %s", m, v**0.5, d.text)
    return replace(report, covariance=covariance, std=std, truncated=truncated)
