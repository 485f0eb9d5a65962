"""How much the map's own uncertainty adds to the calibration's.

The solver holds the surfel planes fixed within a round, but every plane was fitted to the points
whose distances to it are the LiDAR residuals. Its sigmas therefore credit the data with knowing
the map exactly. This stage treats each plane (two normal directions and its offset) as an
unknown of the same residuals, eliminates the planes and the trajectory
(:func:`licalib_cli.solver.nuisance.marginal_schur`) and compares the calibration covariance with
the solver's, coordinate by coordinate, within the directions the solver kept. The ratio is at
least 1; the checks multiply the solver's sigmas by it.

The effect is small for the extrinsic when the rig moves through a structured scene (a few per
cent to about 20 %), and large for LiDAR intrinsics that shift whole planes: a range offset is
nearly indistinguishable from moving every plane towards the sensor.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.estimation import CalibrationState
from licalib_cli.pipeline.free_planes import gauge_hold, lidar_block, plane_jacobian
from licalib_cli.pipeline.points import points_in_global
from licalib_cli.pipeline.round import RoundInputs, SolvedProblem
from licalib_cli.residuals import PointToPlaneResidual
from licalib_cli.solver import SolverReport
from licalib_cli.solver.nuisance import marginal_schur, nuisance_terms
from licalib_cli.solver.observability import undamped_schur

__all__ = ["MapUncertainty", "map_uncertainty"]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class MapUncertainty:
    """The calibration sigmas' growth once the map planes are estimated with them.

    Attributes:
        names: (Nc,) calibration coordinates, as in the solver's report.
        factor: (Nc,) ratio of the sigma with the planes marginalised to the solver's (>= 1;
            1 for coordinates the solver found unobservable).
        planes: planes marginalised.
        seconds: wall time of the computation.
    """

    names: tuple[str, ...]
    factor: F64
    planes: int
    seconds: float

    def of(self, name: str) -> float:
        """The factor of one coordinate (1 when it is not in the problem)."""
        try:
            return float(self.factor[self.names.index(name)])
        except ValueError:
            return 1.0


def map_uncertainty(
    state: CalibrationState,
    inputs: RoundInputs,
    report: SolverReport,
    solved: SolvedProblem | None = None,
) -> MapUncertainty:
    """Sigma factors of the calibration coordinates with the final round's planes marginalised.

    Args:
        state: the final estimate.
        inputs: what the final round's problem was built from.
        report: the final round's solver report (its kept directions and sigmas).
        solved: that problem at ``state`` with the solver's evaluation and normal equations
            there (reused instead of building, evaluating and linearising it again); None:
            they are computed here. When it carries the information of the planes-free step
            that led to it (``free_planes``), that is used instead of eliminating the planes
            again.

    Returns:
        The factors (all 1 when the round had no LiDAR points).
    """
    start = time.perf_counter()
    names = tuple(report.calibration_names)
    num_planes = int(np.asarray(inputs.planes.d).shape[0])
    reused = solved.free_planes if solved is not None else None
    if solved is not None and reused is not None and reused.names == names:
        # the planes-free step nearest the estimate eliminated the same planes: its information
        # with them held and estimated (a step of a fraction of a sigma away changes the
        # geometry, and so the ratio, by nothing that shows)
        scale = solved.linearization.layout.calibration_scale
        factor = _sigma_ratio(reused.plain, reused.marginal, scale, report)
        return MapUncertainty(names, factor, num_planes, time.perf_counter() - start)
    if solved is not None:
        problem = solved.problem
        layout = solved.linearization.layout
    else:
        problem = inputs.problem(state)
        layout = problem.layout()
    block = lidar_block(problem)
    ones = np.ones(len(names))
    if block is None or tuple(layout.calibration_names) != names:
        return MapUncertainty(names, ones, 0, time.perf_counter() - start)
    if solved is not None:
        evaluation, lin = solved.evaluation, solved.linearization
    else:
        evaluation = problem.evaluate(jacobians=True)
        lin = problem.linearize(evaluation, layout)
    residual = problem.residual_blocks[block]
    assert isinstance(residual, PointToPlaneResidual)
    plane = np.asarray(inputs.lidar.plane, dtype=np.intp)
    # the points the residuals measure
    p_g = solved.points_global if solved is not None else points_in_global(state, inputs.points)
    jac_p, _ = plane_jacobian(p_g, plane, np.asarray(inputs.planes.normal, dtype=np.float64))
    jac_p *= residual.whitening()[:, None]
    terms = nuisance_terms(problem, evaluation, layout, block, jac_p, plane, num_planes)
    s_marg = marginal_schur(lin, terms, gauge_hold(layout))
    s_plain = undamped_schur(lin)
    factor = _sigma_ratio(s_plain, s_marg, layout.calibration_scale, report)
    return MapUncertainty(names, factor, num_planes, time.perf_counter() - start)


def _sigma_ratio(s_plain: F64, s_marg: F64, scale: F64, report: SolverReport) -> F64:
    """Per coordinate ``sigma_marg / sigma_plain`` within the solver's kept directions (those
    above the threshold and its weakly determined ones)."""
    d = np.asarray(scale, dtype=np.float64)
    plain_d = d[:, None] * s_plain * d[None, :]
    marg_d = d[:, None] * s_marg * d[None, :]
    vals, vecs = np.linalg.eigh(0.5 * (plain_d + plain_d.T))
    keep = vals > max(float(report.tsvd_threshold), 1e-12 * max(float(vals.max(initial=0.0)), 1.0))
    if report.weak:  # the same linearisation: each weak direction is one of these vectors
        weak = np.stack([w.vector for w in report.weak], axis=1)
        keep |= np.max(np.abs(vecs.T @ weak), axis=1) > 0.9
    out = np.ones(d.shape[0])
    if not np.any(keep):
        return out
    u = vecs[:, keep]
    cov_plain = (u / vals[keep]) @ u.T
    reduced = u.T @ marg_d @ u
    reduced = 0.5 * (reduced + reduced.T)
    r_vals, r_vecs = np.linalg.eigh(reduced)
    floor = 1e-12 * max(float(r_vals.max(initial=0.0)), 1e-300)
    cov_red = (r_vecs / np.maximum(r_vals, floor)) @ r_vecs.T
    cov_marg = u @ cov_red @ u.T
    var_plain = np.diag(cov_plain)
    var_marg = np.diag(cov_marg)
    ok = (var_plain > 0) & np.isfinite(var_marg) & np.asarray(report.observable, dtype=bool)
    out[ok] = np.sqrt(np.maximum(var_marg[ok] / var_plain[ok], 1.0))
    return out
