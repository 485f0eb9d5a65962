"""Split-half agreement: the extrinsic estimated on each half of the segment, compared.

Each half gets the final estimate restricted to it (the same spline on a sub-range of its
knots), the final round's IMU samples and associated points that fall in it, and the final
map's planes; a few Levenberg-Marquardt iterations re-estimate everything the final round
estimated except the intrinsics, which the halves hold at the whole segment's estimate (their
uncertainty enters the comparison through how each half follows them). If the model explains
the data, the two halves agree within their combined sigmas; an effect that changes over time
(a drifting bias, a clock running at another rate, a sensor moving on its mount) makes them
disagree.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.consistency.distributions import chi2_sf
from licalib_cli.errors import LicalibError
from licalib_cli.estimation import (
    IMU_INTRINSIC_BLOCKS,
    CalibrationState,
    FreeParameters,
    ImuData,
    build_problem,
    state_from_problem,
)
from licalib_cli.parallel.threads import map_blocks
from licalib_cli.pipeline.round import RoundInputs, extrinsic_of
from licalib_cli.pipeline.settings import lm_params, spline_margin_s
from licalib_cli.residuals import LIDAR_INTRINSICS
from licalib_cli.solver.lm import SolverReport, solve
from licalib_cli.solver.observability import calibration_information
from licalib_cli.solver.problem import Problem
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

__all__ = [
    "COORDINATES",
    "MIN_HALF_S",
    "SplitResult",
    "common_covariance",
    "compare_halves",
    "half_problem",
    "held_free",
    "intrinsic_response",
    "split_half",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

MIN_HALF_S = 2.0
"""Each half must hold at least this much data (the calibration's own minimum segment)."""

_MIN_HALF_POINTS = 2000

_HALF_ITERATIONS = 12
"""Most iterations of a half, which starts at the whole segment's optimum and stops once it
reaches its own (6 on the sample). The four of before stopped the sample's halves short of it,
which pulls the two estimates towards their common start: chi-square 5.1 at four iterations
against 7.9 at the halves' optima (2.5 against 3.8 on a fit 0.03 mm away, whose final round
rebuilt its map)."""

MAX_HALF_POINTS = 30_000
"""Points per half (a regular subset of the final round's): enough for sigmas of a fraction of
a millimetre, and the check stays a small part of the run time."""


COORDINATES = (
    "translation.x",
    "translation.y",
    "translation.z",
    "rotation.x",
    "rotation.y",
    "rotation.z",
    "time_offset",
)
"""The compared coordinates, in ``SplitResult.difference`` order (rotation about the LiDAR
axes)."""


@dataclass(frozen=True)
class SplitResult:
    """The two halves' estimates and their comparison (or why it was not run).

    Attributes:
        ran: whether both halves were estimated.
        reason: why not (empty when it ran).
        half_s: duration of each half, s.
        difference: (7,) second half minus first: translation (m, IMU frame), rotation (rad,
            about the LiDAR axes), time offset (s).
        sigma: (7,) combined 1-sigma of the difference (``inf`` where a half cannot observe).
        z: (7,) ``|difference| / sigma``.
        chi2: ``difference^T (C_1 + C_2)^+ difference`` with the halves' covariances, over the
            coordinates both halves determine (finite ``sigma``).
        dof: rank of ``C_1 + C_2`` over those coordinates.
        p_value: probability of a ``chi2`` at least this large if the halves agree.
    """

    ran: bool
    reason: str = ""
    half_s: float = 0.0
    difference: F64 = field(default_factory=lambda: np.zeros(7))
    sigma: F64 = field(default_factory=lambda: np.full(7, np.inf))
    z: F64 = field(default_factory=lambda: np.zeros(7))
    chi2: float = 0.0
    dof: int = 0
    p_value: float = 1.0

    @property
    def compared(self) -> tuple[str, ...]:
        """Names (:data:`COORDINATES`) of the coordinates both halves determine: the ones the
        chi-square compares."""
        if not self.ran:
            return ()
        return tuple(n for n, s in zip(COORDINATES, self.sigma, strict=True) if np.isfinite(s))

    @property
    def max_z(self) -> float:
        """Largest ``z`` over the coordinates a half observes."""
        finite = self.z[np.isfinite(self.z)]
        return float(finite.max()) if finite.size else 0.0


def _sub_state(state: CalibrationState, lo_s: float, hi_s: float) -> CalibrationState:
    """``state`` with its splines restricted to the knot segments covering ``[lo, hi]``."""
    knots = state.knots
    first = max(int(np.floor((lo_s - knots.t0_s) / knots.dt_s)), 0)
    last = min(int(np.ceil((hi_s - knots.t0_s) / knots.dt_s)), knots.num_segments)
    n = (last - first) + 3
    sub = UniformKnots(knots.t0_s + first * knots.dt_s, knots.dt_s, n)
    quats = np.asarray(state.so3_spline.control_quats)[first : first + n]
    cps = np.asarray(state.r3_spline.control_points)[first : first + n]
    return state.with_(so3_spline=SO3Spline(sub, quats), r3_spline=R3Spline(sub, cps))


_EXT = (
    *(f"ext.translation.{a}" for a in "xyz"),
    *(f"ext.rotation.r{a}" for a in "xyz"),
    "ext.time_offset",
)


def _sigmas(report: SolverReport) -> F64:
    out = []
    for n in _EXT:
        try:
            out.append(report.std_of(n))
        except ValueError:
            out.append(float("inf"))
    return np.asarray(out)


def _covariance(report: SolverReport) -> F64:
    """(7, 7) covariance of the extrinsic coordinates (zero rows for ones not estimated or not
    observable)."""
    names = list(report.calibration_names)
    idx = [names.index(n) if n in names else -1 for n in _EXT]
    cov = np.zeros((7, 7))
    ok = [i for i, j in enumerate(idx) if j >= 0 and np.isfinite(report.std[j])]
    src = [idx[i] for i in ok]
    cov[np.ix_(ok, ok)] = report.covariance[np.ix_(src, src)]
    return cov


def held_free(free: FreeParameters) -> FreeParameters:
    """What a half estimates: the whole segment's free parameters less the intrinsics, which a
    half holds at the whole segment's estimate (constants of the sensors, not what changes over
    a recording; a half alone seldom determines them, and with the gyro-to-IMU rotation free it
    leaves the extrinsic rotation to the accelerometer)."""
    return replace(
        free,
        imu_intrinsics=False,
        imu_blocks=frozenset(),
        g_sensitivity=False,
        lidar_intrinsics=False,
        lidar_columns=frozenset(),
    )


def half_problem(
    state: CalibrationState,
    inputs: RoundInputs,
    lo_s: float,
    hi_s: float,
    cfg: CalibConfig,
    free: FreeParameters | None = None,
) -> tuple[CalibrationState, Problem] | str:
    """The problem of IMU-clock seconds ``[lo, hi]``: the state's splines cut to the half
    (with the spline margin), the IMU samples over that sub-spline and the associated points of
    the half, estimating ``free`` (default :func:`held_free` of the round's); a sentence when
    the half holds too few points."""
    margin = spline_margin_s(cfg.spline.time_offset_padding_s, state.knots)
    sub = _sub_state(state, lo_s - margin, hi_s + margin)
    knots = sub.knots
    imu = inputs.imu
    # The IMU samples over the whole sub-spline, margins included: with the samples of
    # [lo, hi] only, the control points of the margins were touched by a few samples' tails
    # alone (information 1e-20 of the others'), and the half's steps along them (1e7 of their
    # scale) made its estimate depend on the last digits of the input (chi-square 5 or 17 in
    # runs of the same bag). The margins are a few knots: the halves share no LiDAR point.
    in_imu = knots.contains(imu.t_s)
    lid = inputs.lidar
    t_pt = np.asarray(lid.t_s) + state.time_offset_s
    in_pts = (t_pt >= lo_s) & (t_pt <= hi_s)
    if np.count_nonzero(in_pts) < _MIN_HALF_POINTS:
        return f"a half holds only {int(np.count_nonzero(in_pts))} associated points"
    idx = np.flatnonzero(in_pts)
    picked = idx[:: max(1, idx.size // MAX_HALF_POINTS)]
    half_imu = ImuData(imu.t_s[in_imu], imu.gyro[in_imu], imu.accel[in_imu])
    half_lidar = lid.subset(picked)
    free = held_free(inputs.free) if free is None else free
    # each half is the data's own estimate: without the translation's prior (and its scale),
    # nor the clock drift's from the stamps
    free = replace(free, translation_prior=None, time_drift_prior=None)
    problem = build_problem(sub, half_imu, half_lidar, inputs.planes, inputs.noise, free)
    return sub, problem


def intrinsic_response(problem: Problem) -> tuple[tuple[str, ...], F64]:
    """How a half's extrinsic follows the intrinsics it holds: ``J = -S_xx^+ S_xh``.

    ``problem`` is the half's problem at its estimate with the intrinsics free; ``S`` its
    calibration information (the trajectory eliminated), ``x`` the coordinates the half
    estimates and ``h`` the intrinsics. An error ``dh`` of the held intrinsics moves the half's
    estimate by ``J dh``.

    Returns:
        The intrinsics' coordinate names and the (7, Nh) response of the extrinsic coordinates
        (:data:`COORDINATES` order; zero rows for ones not estimated), in the coordinates' own
        units.
    """
    info = calibration_information(problem)
    names = list(info.names)
    held = np.array([_is_intrinsic(o) for o in info.owners], dtype=bool)
    kept = ~held
    s_d, d = info.information, np.asarray(info.scale, dtype=np.float64)
    s_xx = s_d[np.ix_(kept, kept)]
    s_xh = s_d[np.ix_(kept, held)]
    j_d = -np.linalg.pinv(0.5 * (s_xx + s_xx.T), rcond=1e-12, hermitian=True) @ s_xh
    j = d[kept][:, None] * j_d / d[held][None, :]
    kept_names = [n for n, k in zip(names, kept, strict=True) if k]
    out = np.zeros((7, int(held.sum())))
    for i, n in enumerate(_EXT):
        if n in kept_names:
            out[i] = j[kept_names.index(n)]
    return tuple(n for n, h in zip(names, held, strict=True) if h), out


def _is_intrinsic(owner: str) -> bool:
    return owner in IMU_INTRINSIC_BLOCKS or owner == LIDAR_INTRINSICS


def common_covariance(
    responses: tuple[tuple[tuple[str, ...], F64], tuple[tuple[str, ...], F64]],
    report: SolverReport | None,
) -> F64:
    """(7, 7) covariance the held intrinsics' uncertainty adds to the halves' difference:
    ``(J_2 - J_1) C_h (J_2 - J_1)^T``, ``C_h`` the whole segment's covariance of the
    intrinsics (``report``); zero without intrinsics or a report."""
    if report is None:
        return np.zeros((7, 7))
    names = list(report.calibration_names)
    union = sorted({n for r in responses for n in r[0]} & set(names))
    if not union:
        return np.zeros((7, 7))
    diff = np.zeros((7, len(union)))
    for sign, (held, j) in zip((-1.0, 1.0), responses, strict=True):
        for col, n in enumerate(held):
            if n in union:
                diff[:, union.index(n)] += sign * j[:, col]
    idx = [names.index(n) for n in union]
    c_h = np.asarray(report.covariance, dtype=np.float64)[np.ix_(idx, idx)]
    return diff @ c_h @ diff.T


def _estimate_half(
    state: CalibrationState, inputs: RoundInputs, lo_s: float, hi_s: float, cfg: CalibConfig
) -> tuple[CalibrationState, SolverReport, tuple[tuple[str, ...], F64]] | str:
    """Re-estimate on IMU-clock seconds ``[lo, hi]`` with the intrinsics held, and how that
    estimate follows them; a sentence when it cannot be done."""
    built = half_problem(state, inputs, lo_s, hi_s, cfg)
    if isinstance(built, str):
        return built
    sub, problem = built
    report = solve(problem, lm_params(cfg, max_iterations=_HALF_ITERATIONS))
    if report.status == "failed":
        return f"the optimisation of a half failed ({report.reason})"
    estimate = state_from_problem(sub, problem)
    response: tuple[tuple[str, ...], F64] = ((), np.zeros((7, 0)))
    if inputs.free.any_imu_intrinsics or inputs.free.any_lidar_intrinsics:
        with_intrinsics = half_problem(estimate, inputs, lo_s, hi_s, cfg, free=inputs.free)
        if not isinstance(with_intrinsics, str):
            response = intrinsic_response(with_intrinsics[1])
    return estimate, report, response


def split_half(
    state: CalibrationState,
    inputs: RoundInputs,
    cfg: CalibConfig,
    report: SolverReport | None = None,
) -> SplitResult:
    """Estimate the extrinsic on each half of the segment and compare.

    The halves hold the intrinsics at the whole segment's estimate; their uncertainty (from
    ``report``) enters the difference's covariance through how each half's estimate follows
    them (:func:`common_covariance`): what both halves share cancels, what they see
    differently does not.

    Args:
        state: the final estimate.
        inputs: the final round's problem inputs (IMU, associated points, planes, weights).
        cfg: the configuration.
        report: the final solve's report (the intrinsics' covariance); without it the
            intrinsics count as exact.

    Returns:
        The comparison, or a result with ``ran=False`` and the reason.
    """
    t = np.asarray(inputs.imu.t_s)
    start, end = float(t[0]), float(t[-1])
    half = 0.5 * (end - start)
    if half < MIN_HALF_S:
        return SplitResult(
            False,
            f"the segment ({2 * half:.1f} s) is too short to split into two halves of at least "
            f"{MIN_HALF_S:g} s",
            half,
        )
    mid = start + half
    bounds = ((start, mid), (mid, end))

    def estimate(
        i: int,
    ) -> tuple[CalibrationState, SolverReport, tuple[tuple[str, ...], F64]] | str:
        try:
            return _estimate_half(state, inputs, *bounds[i], cfg)
        except (LicalibError, ValueError, np.linalg.LinAlgError) as err:
            return f"a half could not be estimated ({err})"

    # one half per block thread: each is estimated as it would be alone
    results = []
    for res in map_blocks(estimate, len(bounds)):
        if isinstance(res, str):
            return SplitResult(False, res, half)
        results.append(res)
    (s1, rep1, resp1), (s2, rep2, resp2) = results
    diff = extrinsic_of(s1).moved_to(extrinsic_of(s2))
    result = compare_halves(
        diff,
        _sigmas(rep1),
        _sigmas(rep2),
        _covariance(rep1),
        _covariance(rep2),
        half,
        common=common_covariance((resp1, resp2), report),
    )
    if not result.ran:
        return result
    logger.info(
        "Split-half: the halves (%.1f s each) differ by %.2f mm / %.4f deg / %.3f ms; largest "
        "difference %.1f sigma, chi-square %.1f on %d (p = %.2g).",
        half,
        1e3 * float(np.linalg.norm(diff[:3])),
        float(np.degrees(np.linalg.norm(diff[3:6]))),
        1e3 * abs(float(diff[6])),
        result.max_z,
        result.chi2,
        result.dof,
        result.p_value,
    )
    return result


def compare_halves(
    diff: F64,
    sigma1: F64,
    sigma2: F64,
    cov1: F64,
    cov2: F64,
    half_s: float,
    common: F64 | None = None,
) -> SplitResult:
    """The halves' difference against their combined covariance.

    Only the coordinates both halves determine (finite sigma in each) are compared: a half that
    does not determine one holds it near the whole segment's value, so the other half's spread
    alone would stand for the difference's (a walk's window with one calm half: chi-square 56
    on 7 with every coordinate within 0.4 of its sigmas).

    Args:
        diff: (7,) second half minus first.
        sigma1, sigma2: (7,) each half's 1-sigma (``inf`` where it does not determine one).
        cov1, cov2: (7, 7) each half's covariance.
        half_s: duration of each half, s.
        common: (7, 7) covariance the difference gets from what both halves hold fixed at a
            shared uncertain value (:func:`common_covariance`; default none).

    Returns:
        The comparison; ``ran=False`` when no coordinate is determined by both halves.
    """
    common = np.zeros((7, 7)) if common is None else np.asarray(common, dtype=np.float64)
    sigma = np.sqrt(sigma1**2 + sigma2**2 + np.clip(np.diag(common), 0.0, None))
    z = np.where(np.isfinite(sigma), np.abs(diff) / np.maximum(sigma, 1e-300), np.nan)
    both = np.isfinite(sigma)
    if not np.any(both):
        return SplitResult(
            False,
            f"no coordinate of the extrinsic is determined by both halves ({half_s:.1f} s each; "
            "a half with too little motion)",
            half_s,
        )
    cov = (cov1 + cov2 + common)[np.ix_(both, both)]
    unit = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(unit, unit)
    w, v = np.linalg.eigh(0.5 * (corr + corr.T))
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    proj = v[:, keep].T @ (diff[both] / unit)
    chi2 = float(np.sum(proj**2 / w[keep]))
    dof = int(keep.sum())
    p_value = float(chi2_sf(chi2, dof)) if dof else 1.0
    return SplitResult(True, "", half_s, diff, sigma, z, chi2, dof, p_value)
