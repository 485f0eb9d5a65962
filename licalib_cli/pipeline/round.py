"""One refinement round: map from the estimate, surfels, associations, problem, solve.

Between rounds the map is rebuilt from the latest estimate (EM fashion, method.md section 6);
within a round the surfel planes are held fixed in ``{G}`` (method.md section 4, implementation
note), so that a point's residual touches only the control points around its own time.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import DataError, ExcitationError, SolverError
from licalib_cli.estimation import (
    CalibrationState,
    FreeParameters,
    ImuData,
    LidarPoints,
    NoiseModel,
    Planes,
    build_problem,
    state_from_problem,
)
from licalib_cli.map_quality import mean_map_entropy
from licalib_cli.pipeline.points import (
    PointSample,
    points_in_global,
    solver_points,
    usable_mask,
)
from licalib_cli.pipeline.settings import RoundSettings, model_priors
from licalib_cli.pipeline.timing import StageTime, Stopwatch
from licalib_cli.results import Extrinsic
from licalib_cli.solver.lm import SolverReport, solve_with_linearization
from licalib_cli.solver.problem import Evaluation, Linearization, Problem
from licalib_cli.surfels import associate_points, build_surfels

__all__ = [
    "MappedSample",
    "RoundInputs",
    "RoundResult",
    "RoundSummary",
    "SolvedProblem",
    "extrinsic_of",
    "free_names",
    "plane_distances",
    "run_round",
]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

_ENTROPY_POINTS = 4000
"""Points at which the map entropy of a round is evaluated (a Monte-Carlo mean)."""

_ENTROPY_MAP_POINTS = 40_000
"""The map whose entropy is evaluated keeps at most about this many of the round's points (every
k-th): the cost grows with the neighbours within 0.3 m. With 100 000 (no thinning of a VLP-16
round) the entropy took 0.22-0.26 s of every round and 0.47 s of the dense final one on a 12 s
shake, a tenth of the optimisation; with 30 000 half that. A sparser map lowers every round's
value alike (-0.06 nats at 30 000, -0.02 to -0.04 at 50 000 on that shake), so the rounds'
trend, which is what the entropy shows, is kept; values of runs with different thinning are not
comparable to a few hundredths."""


@dataclass(frozen=True)
class RoundInputs:
    """What a round's problem was built from (for the checks, which rebuild variants of it).

    Attributes:
        imu: IMU readings on the problem's time axis.
        lidar: associated points.
        points: the same points as sampled (times, sweep starts, raw measurements).
        planes: the surfel planes in ``{G}``.
        noise: residual weights.
        free: what the round estimated.
    """

    imu: ImuData
    lidar: LidarPoints
    points: PointSample
    planes: Planes
    noise: NoiseModel
    free: FreeParameters

    def problem(
        self,
        state: CalibrationState,
        planes: Planes | None = None,
        free: FreeParameters | None = None,
    ) -> Problem:
        """The round's problem at ``state`` (the intrinsics' priors included), on other
        ``planes`` or with other ``free`` parameters when given."""
        free = self.free if free is None else free
        return build_problem(
            state,
            self.imu,
            self.lidar,
            self.planes if planes is None else planes,
            self.noise,
            free,
            extra_residuals=model_priors(state, free),
        )


@dataclass(frozen=True)
class FreePlanesInformation:
    """The calibration information of one linearisation with the map planes held fixed and with
    them estimated too (the trajectory eliminated in both), from a planes-free step.

    Attributes:
        names: (Nc,) the calibration coordinates.
        plain: (Nc, Nc) the information with the planes held.
        marginal: (Nc, Nc) the information with the planes estimated.
    """

    names: tuple[str, ...]
    plain: F64
    marginal: F64


@dataclass(frozen=True)
class SolvedProblem:
    """A round's problem at its estimate, with the solver's evaluation and normal equations there
    (the checks analyse the final round's problem at the same state without evaluating and
    linearising it again).

    Attributes:
        problem: the problem, its blocks at the estimate.
        evaluation: residuals and Jacobians at the estimate.
        linearization: the normal equations at the estimate (the report's spectrum and sigmas).
        points_global: (P, 3) the problem's points (``RoundInputs.points``) mapped into ``{G}``
            with the estimate, m.
        free_planes: the information of the planes-free step nearest the estimate when planes-
            free steps led to it (the checks' map uncertainty reads it), else None.
    """

    problem: Problem
    evaluation: Evaluation
    linearization: Linearization
    points_global: F64
    free_planes: FreePlanesInformation | None = None


@dataclass(frozen=True)
class MappedSample:
    """A round's usable points mapped into ``{G}`` with its estimate: the next round's map when it
    starts from that estimate on the same sample and the same points are usable.

    Attributes:
        state: the estimate the points were mapped with.
        sample: the sample the points were taken from.
        usable: (len(sample),) which of its points were usable.
        points: those points.
        p_g: (N, 3) the points in ``{G}``, m (read-only).
    """

    state: CalibrationState
    sample: PointSample
    usable: npt.NDArray[np.bool_]
    points: PointSample
    p_g: F64


@dataclass(frozen=True)
class RoundSummary:
    """One refinement round (map rebuild + LM).

    Attributes:
        index: 1-based round number.
        free: names of the parameter groups estimated.
        max_distance_m: association distance of the round, m.
        points: associated points used.
        surfels: surfels in the map.
        associated_fraction: share of sampled points associated with a surfel.
        rms_m: RMS point-to-plane distance after the round, m.
        cost_start: cost before the round.
        cost_end: cost after the round.
        iterations: LM iterations (after a planes-free refinement, also its steps and the
            solver's iterations on the refined planes).
        extrinsic: estimate after the round.
        seconds: wall time of the round.
        distances_before_m: (P,) signed point-to-plane distances at the start of the round.
        distances_after_m: (P,) the same after the round (same map; after a planes-free
            refinement, on its refined planes), m.
        map_entropy: mean map entropy (method.md section 9) of the round's sampled points mapped
            with its estimate, nats; lower is sharper.
        stage_times: wall and CPU seconds of the round's steps, in order: ``map`` (the sampled
            points mapped into ``{G}``), ``surfels``, ``associations``, ``problem`` (the
            problem built and first evaluated), ``solver`` (Levenberg-Marquardt with its
            spectrum and sigmas) and ``summary`` (map entropy and distances after the round).
    """

    index: int
    free: tuple[str, ...]
    max_distance_m: float
    points: int
    surfels: int
    associated_fraction: float
    rms_m: float
    cost_start: float
    cost_end: float
    iterations: int
    extrinsic: Extrinsic
    seconds: float
    distances_before_m: F32 = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    distances_after_m: F32 = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    map_entropy: float = float("nan")
    stage_times: dict[str, StageTime] = field(default_factory=dict)


def plane_distances(normal: F64, d: F64, plane: npt.NDArray[np.intp], p_g: F64) -> F64:
    """(P,) signed distances of the points ``p_g`` (P, 3) from their planes ``n^T x + d = 0``,
    ``plane`` (P,) the index of each point's plane in ``normal`` and ``d``, m."""
    return np.asarray(np.einsum("ij,ij->i", normal[plane], p_g) + d[plane])


def extrinsic_of(state: CalibrationState) -> Extrinsic:
    """The state's extrinsic and time offset."""
    return Extrinsic(state.R_imu_lidar.copy(), state.t_imu_lidar.copy(), state.time_offset_s)


def free_names(free: FreeParameters) -> tuple[str, ...]:
    """Names of the parameter groups a round estimates."""
    names = ["trajectory", "biases", "gravity", "extrinsic", "time offset"]
    if free.any_imu_intrinsics:
        names.append("IMU intrinsics")
    if free.any_lidar_intrinsics:
        names.append("LiDAR intrinsics")
    return tuple(names)


@dataclass(frozen=True)
class RoundResult:
    """What a round produces.

    Attributes:
        state: the estimate after the round.
        summary: the round's figures.
        report: the solver's report (spectrum and sigmas at the new estimate).
        inputs: what the round's problem was built from.
        solved: the round's problem with its evaluation and normal equations at the estimate.
        mapped: the round's usable points mapped with the estimate.
    """

    state: CalibrationState
    summary: RoundSummary
    report: SolverReport
    inputs: RoundInputs
    solved: SolvedProblem | None = field(default=None, repr=False, compare=False)
    mapped: MappedSample | None = field(default=None, repr=False, compare=False)


def run_round(
    state: CalibrationState,
    sample: PointSample,
    imu: ImuData,
    settings: RoundSettings,
    index: int,
    mapped: MappedSample | None = None,
) -> RoundResult:
    """Rebuild surfels and associations from ``state``, then one LM round.

    ``mapped`` (the previous round's :attr:`RoundResult.mapped`) is the map when it holds the same
    points of ``sample`` mapped with ``state`` itself; else the points are mapped here.

    Raises:
        ExcitationError: the map has no planar surfaces, or too few points lie on them.
        SolverError: the optimisation failed.
    """
    watch, total = Stopwatch(), Stopwatch()
    times: dict[str, StageTime] = {}
    usable = usable_mask(state, sample, settings.margin_s(state.knots))
    if (
        mapped is not None
        and mapped.state is state
        and mapped.sample is sample
        and np.array_equal(mapped.usable, usable)
    ):
        pts, p_g = mapped.points, mapped.p_g
    else:
        pts = sample.subset(usable)
        p_g = points_in_global(state, pts)
    times["map"] = watch.lap()
    scfg = settings.surfels
    surfels = build_surfels(p_g, scfg)
    times["surfels"] = watch.lap()
    if len(surfels.d) == 0:
        msg = (
            "No planar surfaces were found in the LiDAR map; calibrate in a structured scene "
            "(walls, floor) or raise surfels.cell_sizes_m."
        )
        raise ExcitationError(msg)
    assoc = associate_points(p_g, surfels, scfg)
    times["associations"] = watch.lap()
    if assoc.point_index.size < 100:
        msg = (
            f"Only {assoc.point_index.size} LiDAR points lie on planar surfaces; calibrate in a "
            "structured scene or raise surfels.max_distance_m."
        )
        raise ExcitationError(msg)
    order = np.argsort(assoc.point_index)
    used = pts.subset(assoc.point_index[order])
    plane_of = assoc.surfel_index[order]
    lidar = solver_points(state, used, plane_of)
    planes = Planes(normal=surfels.normal, d=surfels.d, thickness=surfels.thickness)
    free = settings.free
    inputs = RoundInputs(imu, lidar, used, planes, settings.weights, free)
    problem = inputs.problem(state)
    times["problem"] = watch.lap()
    solution = solve_with_linearization(problem, settings.solver)
    report = solution.report
    times["solver"] = watch.lap()
    if report.status == "failed":
        msg = f"The optimisation failed in round {index}: {report.reason}."
        raise SolverError(msg)
    new_state = state_from_problem(state, problem)
    # The usable points are mapped once with the new estimate: the entropy's map, the distances
    # after the round and the next round's map (from the same estimate) are subsets of them.
    # A round that ran no iteration (evaluate-only) left the estimate where it mapped them.
    p_new = p_g if report.iterations == 0 else points_in_global(new_state, pts)
    p_new.flags.writeable = False
    try:
        stride = -(-len(pts) // _ENTROPY_MAP_POINTS)
        thinned = np.ascontiguousarray(p_new[::stride]) if stride > 1 else p_new
        entropy = mean_map_entropy(thinned, max_query_points=_ENTROPY_POINTS).mean
    except DataError:
        entropy = float("nan")
    p_after = p_new[assoc.point_index[order]]
    dist = plane_distances(surfels.normal, surfels.d, plane_of, p_after)
    p_before = p_g[assoc.point_index[order]]
    dist0 = plane_distances(surfels.normal, surfels.d, plane_of, p_before)
    times["summary"] = watch.lap()
    summary = RoundSummary(
        index=index,
        free=free_names(free),
        max_distance_m=scfg.max_distance_m,
        points=len(used),
        surfels=len(surfels.d),
        associated_fraction=len(used) / max(len(pts), 1),
        rms_m=float(np.sqrt(np.mean(dist**2))),
        cost_start=float(report.initial_cost),
        cost_end=float(report.final_cost),
        iterations=int(report.iterations),
        extrinsic=extrinsic_of(new_state),
        seconds=total.lap().wall_s,
        distances_before_m=dist0.astype(np.float32),
        distances_after_m=dist.astype(np.float32),
        map_entropy=entropy,
        stage_times=times,
    )
    logger.debug(
        "Round %d steps (wall/CPU s): %s.",
        index,
        ", ".join(f"{k} {t.wall_s:.2f}/{t.cpu_s:.2f}" for k, t in times.items()),
    )
    solved = SolvedProblem(problem, solution.evaluation, solution.linearization, p_after)
    following = MappedSample(new_state, sample, usable, pts, p_new)
    return RoundResult(new_state, summary, report, inputs, solved, following)
