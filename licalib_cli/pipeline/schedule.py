"""The refinement rounds: which thresholds when, and when to stop (method.md section 7).

Coarse to fine: the first map is blurred by the initial guess, so the first round associates
points up to :data:`COARSE_FACTOR` times ``surfels.max_distance_m`` from a surfel (and accepts
surfels as much thicker); each later round tightens the distance to three times how far the
previous round moved the points, and to :data:`WANDER_SHRINK` of it at least when the rounds
crawl (never below the configured distance). Rounds that crawl at the configured distance take
a Gauss-Newton step with the map's planes estimated too before the next round; so do rounds whose
map stalls at any distance (:func:`stalls`: it gets blurrier, or stays blurred with few points
on its planes); a round that takes such a step back (:func:`takes_back`) is no crawl and ends
the steps. Rounds run until
one moves the estimate by less than the tolerances (or by less than half its own 1-sigma,
whichever is larger) at the configured distance; a last, denser round
then refines the settled estimate with Gauss-Newton steps that estimate the map's planes too
(one without LiDAR intrinsics, up to :data:`~licalib_cli.pipeline.free_planes.MAX_STEPS` with
them). Reaching ``schedule.max_rounds`` while the estimate still
moves is a non-convergence, reported as such by the checks.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ExcitationError, MapLost
from licalib_cli.estimation import (
    CALIBRATION_SCALES,
    CalibrationState,
    ImuData,
    calibration_moved,
    intrinsic_coordinates,
)
from licalib_cli.measurements import Recording
from licalib_cli.models.lidar import lidar_point
from licalib_cli.pipeline.free_planes import (
    MAX_STEPS,
    PlaneRefinement,
    planes_free_steps_from,
    refine_with_planes,
)
from licalib_cli.pipeline.initialise import InitialGuess
from licalib_cli.pipeline.lost_map import beams_advice, beams_held
from licalib_cli.pipeline.points import (
    PointBudget,
    PointSample,
    point_budget,
    round_points,
    sample_points,
)
from licalib_cli.pipeline.prior_directions import data_translation_std
from licalib_cli.pipeline.round import (
    MappedSample,
    RoundInputs,
    RoundSummary,
    SolvedProblem,
    extrinsic_of,
    plane_distances,
    run_round,
)
from licalib_cli.pipeline.settings import (
    NoiseLevels,
    association_distance,
    estimates_intrinsics,
    prior_sd,
    round_settings,
    with_clock_rate,
)
from licalib_cli.progress import Progress
from licalib_cli.residuals import EXT_ROTATION, EXT_TRANSLATION, GYRO_ROTATION, TIME_OFFSET
from licalib_cli.solver.lm import SolverReport, widen_along_truncated

__all__ = [
    "COARSE_FACTOR",
    "CRAWL_RATIO",
    "FINAL_SETTLE_SIGMAS",
    "MAX_CRAWL_STEPS",
    "MAX_FINAL_ROUNDS",
    "STALL_ENTROPY",
    "STALL_FRACTION",
    "STEP_CHECK_ROUNDS",
    "WANDER_SHRINK",
    "Change",
    "Fit",
    "cover_truncated",
    "crawls",
    "dense_rounds_rested",
    "final_jump",
    "refined_summary",
    "run_schedule",
    "stalls",
    "takes_back",
    "within",
]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

COARSE_FACTOR = 3.0
"""The first round associates points up to this many times ``surfels.max_distance_m``."""

TYPICAL_RANGE_M = 10.0
"""Range at which a change of rotation is converted into a displacement of the points."""

INTRINSICS_FACTOR = 2.0
"""When the intrinsics join, the association distance opens to at least this many times
``surfels.max_distance_m`` (the map changes as they move)."""

JOIN_BY = 3
"""Without ``schedule.intrinsics_from_round``, the intrinsics join after this many rounds at the
latest."""

CRAWL_RATIO = 0.5
"""Rounds crawl when one moves the translation by more than this fraction of what the round
before moved it (a settling estimate shrinks its steps faster): at the configured association
distance the planes-free refinement then takes a step before the next round; above it the
distance tightens (:data:`WANDER_SHRINK`)."""

WANDER_SHRINK = 0.8
"""From the third round on, a round above the configured association distance that crawls (moved
the translation by more than :data:`CRAWL_RATIO` of what the round before moved it) makes the
next round associate within this fraction of its distance (or closer, as the map's movement
says). Three times a map movement of 20-30 mm a round held a crawling schedule at 6.5 cm, where
no planes-free step is taken, for ten rounds."""

MAX_CRAWL_STEPS = 3
"""Planes-free steps between the rounds at most, for crawls and stalls together (each costs
about a round)."""

STEP_CHECK_ROUNDS = 2
"""Rounds after a planes-free step that check, on maps rebuilt from it, that the estimate has
settled. A step within the last of them before ``schedule.max_rounds`` extends the cap to give
them (at most ``MAX_CRAWL_STEPS * STEP_CHECK_ROUNDS`` rounds more): a 20 s VLP-16 sinusoid with
every intrinsic estimated crawled 14 then 24 mm in rounds 10 and 11 of 12, stepped after round
11 and failed as not converged 1.1 mm from the truth; given two more rounds it settled in
round 14."""

STALL_ENTROPY = 0.05
"""Mean map entropy (nats) by which a map must sharpen over two rounds: one that gets blurrier by
more has stalled, and so has one that sharpens by less while at most :data:`STALL_FRACTION` of
the sample lies on its planes (:func:`stalls`). In a schedule that settles the entropy falls by
0.2-0.9 a round while the estimate moves by centimetres."""

STALL_FRACTION = 0.1
"""Share of the sample associated with the map's planes below which a map that does not sharpen
has stalled (a settled map holds about 60 % of a simulated room's sample; the stalled 20 s
sinusoid of :func:`stalls` held 3 %)."""

FINAL_SETTLE_SIGMAS = 5.0
"""A denser final round that moves the extrinsic by more than this many of its own sigmas (and
beyond the configured tolerances) has not settled: another dense round follows."""

MAX_FINAL_ROUNDS = 3
"""Dense final rounds at most, unless they converge (:data:`FINAL_SHRINK`); one still moving
after them is a non-convergence."""

FINAL_SHRINK = 0.5
"""Past :data:`MAX_FINAL_ROUNDS`, another dense round follows while each one's move (in its own
sigmas) is at most this fraction of the one before, up to :data:`MAX_CONVERGING_FINAL_ROUNDS`.
On a 20 s planar figure-8 with a 1.6 m lever arm along a weakly determined direction the
regular rounds stalled 1.45 m short of it; the dense rounds moved 954, 369 and 130 mm (340,
30 and 10 of their sigmas) towards it and the run failed as not converged, 0.7 mm from the
truth where the data determine it; a fourth dense round moved 0.4 mm."""

MAX_CONVERGING_FINAL_ROUNDS = 6
"""Dense final rounds at most while they converge (:data:`FINAL_SHRINK`)."""

DENSE_REST_SIGMAS = 1.0
"""A last dense final round that moved the extrinsic by at most this many of its sigmas, after
an earlier one had moved it by more (:func:`dense_rounds_rested`), shows the estimate at rest on
a map rebuilt at it, whatever the regular rounds did before. After regular rounds that ran out
unsettled the dense rounds go on until one (the second or later) moves this little, within
:data:`MAX_FINAL_ROUNDS` (:data:`MAX_CONVERGING_FINAL_ROUNDS` while they converge): a clean Avia
sinusoid with the IMU intrinsics estimated crawled 2.7 mm a round at the cap, and its dense
rounds moved 8.5 and then 1.4 of their sigmas, 3.7 mm from the truth; it failed as not
converged."""


_PROBE_POINTS = 5000
"""Points whose displacement between rounds measures how much the map moved."""

_MAP_MOVED_QUANTILE = 0.9

JITTER_FACTOR = 2.0
"""At the round cap, a last change within this many times the settle threshold counts as the
rounds' jitter (the map is rebuilt each round), not as a non-convergence; the sigmas then cover
the last change."""


@dataclass(frozen=True)
class Change:
    """How far a round moved the extrinsic.

    Attributes:
        translation_m: norm of the translation change, m.
        rotation_deg: rotation angle, deg.
        time_offset_s: absolute time-offset change, s.
    """

    translation_m: float
    rotation_deg: float
    time_offset_s: float


@dataclass(frozen=True)
class Fit:
    """The rounds' outcome.

    Attributes:
        state: the final estimate.
        rounds: one summary per round (the denser final round last).
        report: the final round's solver report (spectrum and sigmas at the estimate).
        inputs: what the final round's problem was built from.
        converged: whether a regular round settled (or only jittered) before the cap, and the
            denser final rounds settled too.
        jitter: the estimate moved within the jitter band at the cap (sigmas must cover it).
        last_change: how far the last regular round moved the extrinsic.
        settle_threshold: the tolerances that applied to that change.
        solved: the final round's problem (after its planes-free steps, on their planes),
            evaluated and linearised at ``state`` for the checks; None when none was kept.
        final_unsettled: the denser final rounds still moved the estimate by more than
            :data:`FINAL_SETTLE_SIGMAS` of its sigmas after :data:`MAX_FINAL_ROUNDS` of them,
            or more while they converge (:data:`FINAL_SHRINK`; ``last_change`` is then the last
            dense round's change).
        final_rounds: the denser final rounds run (0 without them).
        final_jump: how far the last denser final round moved the extrinsic, in its own
            sigmas (:func:`final_jump`; 0 without one).
        extra_rounds: regular rounds run beyond ``schedule.max_rounds`` to check a planes-free
            step taken near it (:data:`STEP_CHECK_ROUNDS`).
        points: the last round's points per sweep against the sweeps' (None: not known).
    """

    state: CalibrationState
    rounds: tuple[RoundSummary, ...]
    report: SolverReport
    inputs: RoundInputs
    converged: bool
    jitter: bool
    last_change: Change
    settle_threshold: Change
    solved: SolvedProblem | None = field(default=None, repr=False, compare=False)
    final_unsettled: bool = False
    final_jump: float = 0.0
    final_rounds: int = 0
    extra_rounds: int = 0
    points: PointBudget | None = None


def dense_rounds_rested(fit: Fit) -> bool:
    """Whether the denser final rounds came to rest (:data:`DENSE_REST_SIGMAS`) after at least
    two of them: the estimate is where the rounds, on the denser sample, stop moving it."""
    return not fit.final_unsettled and fit.final_rounds >= 2 and fit.final_jump <= DENSE_REST_SIGMAS


def _change(before: CalibrationState, after: CalibrationState) -> Change:
    err = extrinsic_of(before).error_to(extrinsic_of(after))
    return Change(err["translation_m"], err["rotation_deg"], err["time_offset_s"])


def takes_back(
    step_from: CalibrationState, step_to: CalibrationState, after: CalibrationState
) -> bool:
    """Whether the round from ``step_to`` to ``after`` took back at least half of the
    planes-free step from ``step_from`` to ``step_to``, along the step (the extrinsic's
    coordinates in characteristic scales: 1 cm, 1 mrad, 1 ms).

    The rounds hold each map's planes fixed and the step frees them: where the two disagree
    about a weakly determined direction, each undoes the other, and a round that takes a step
    back moves about as far as the step did, which reads as a crawl and calls for the next step
    (an OS1-64 shake with every intrinsic estimated: 0.17 deg there and back three times, then
    twelve rounds were up and it failed as not converged, 1.3 mm / 0.04 deg from the truth)."""
    scale = np.r_[
        CALIBRATION_SCALES[EXT_TRANSLATION],
        CALIBRATION_SCALES[EXT_ROTATION],
        CALIBRATION_SCALES[TIME_OFFSET],
    ]
    step = extrinsic_of(step_from).moved_to(extrinsic_of(step_to)) / scale
    back = extrinsic_of(step_to).moved_to(extrinsic_of(after)) / scale
    size = float(step @ step)
    return size > 0.0 and float(back @ step) <= -0.5 * size


def _diverged(
    err: ExcitationError,
    index: int,
    first: RoundSummary,
    moved: Change,
    given: Sequence[str] = (),
    beams_held: bool = False,
) -> MapLost:
    """The error of a map that lost its planes after the first round: the rounds diverged from
    the initial guess, which the scene's sentence would not say.

    Args:
        first: the first round (its points on planes, and their share of the points sampled).
        given: the initial guesses that came from the config (``rotation_rpy_deg``,
            ``translation_m``): the advice is to check those rather than to give them.
        beams_held: the model holds the beams of a spinning LiDAR at nominal (no
            ``model.lidar``): beams that disagree by centimetres blur the map from the first
            round on (per-beam range offsets of 5 cm RMS on a 10 s VLP-16 sinusoid: 2.5 % of the
            points on planes in round 1, none by round 9; with ``--intrinsics lidar`` the same
            bag calibrates), and the advice says so.
    """
    if given:
        named = " and ".join(f"initialization.{k}" for k in given)
        advice = (
            f"check the {named} the config gives (the LiDAR's pose in the IMU frame, "
            "p_imu = R p_lidar + t, in degrees and metres), or remove "
            f"{'them' if len(given) > 1 else 'it'} to start from what the data show."
        )
    else:
        advice = (
            "give initialization.rotation_rpy_deg and initialization.translation_m (a tape "
            "measure or CAD is enough) to start closer."
        )
    if beams_held:
        share = f"round 1 had {100 * first.associated_fraction:.1f} % of its points on planes"
        advice = f"{advice.rstrip('.')}, or, {beams_advice(share)}."
    msg = (
        f"{str(err).split(';')[0].rstrip('.')} in round {index}, although round 1 had "
        f"{first.points} points on them: the estimate diverged from the initial guess (it moved "
        f"{_describe(moved)}); {advice}"
    )
    return MapLost(msg, beams_held=beams_held)


def _describe(c: Change) -> str:
    return (
        f"{1e3 * c.translation_m:.2f} mm / {c.rotation_deg:.4f} deg / "
        f"{1e3 * c.time_offset_s:.3f} ms"
    )


def _largest_std(report: SolverReport, prefix: str) -> float:
    """The largest finite 1-sigma of the calibration coordinates named ``prefix...`` (0 if
    none)."""
    vals = [
        s
        for n, s in zip(report.calibration_names, report.std, strict=True)
        if n.startswith(prefix) and np.isfinite(s)
    ]
    return float(max(vals)) if vals else 0.0


def _translation_std(report: SolverReport, cfg: CalibConfig) -> float:
    """The translation's largest finite 1-sigma; with a measured lever arm, along what the data
    determine (:func:`~licalib_cli.pipeline.prior_directions.data_translation_std`)."""
    prior = prior_sd(cfg)
    if prior and report.information.information.size:
        return data_translation_std(report, prior)
    return _largest_std(report, "ext.translation")


def _threshold(report: SolverReport, cfg: CalibConfig) -> Change:
    """Settle tolerances: the configured ones or half the estimate's own 1-sigma (the
    translation's along what the data determine, not a measured lever arm's prior)."""
    sch = cfg.schedule

    return Change(
        max(sch.translation_tolerance_m, 0.5 * _translation_std(report, cfg)),
        max(
            sch.rotation_tolerance_deg,
            0.5 * float(np.degrees(_largest_std(report, "ext.rotation"))),
        ),
        max(sch.time_offset_tolerance_s, 0.5 * _largest_std(report, "ext.time_offset")),
    )


def final_jump(change: Change, report: SolverReport, cfg: CalibConfig) -> float:
    """How far a round moved the extrinsic in its own sigmas: the largest of the translation's
    change over its largest 1-sigma (along what the data determine, as the settle tolerance),
    the rotation's and the time offset's. A part within its configured tolerance, or without a
    finite sigma (not observable), counts as 0."""
    sch = cfg.schedule
    parts = (
        (change.translation_m, sch.translation_tolerance_m, _translation_std(report, cfg)),
        (
            change.rotation_deg,
            sch.rotation_tolerance_deg,
            float(np.degrees(_largest_std(report, "ext.rotation"))),
        ),
        (
            change.time_offset_s,
            sch.time_offset_tolerance_s,
            _largest_std(report, "ext.time_offset"),
        ),
    )
    worst = 0.0
    for moved, tolerance, sigma in parts:
        if moved > tolerance and sigma > 0.0:
            worst = max(worst, moved / sigma)
    return worst


def refined_summary(summary: RoundSummary, refined: PlaneRefinement) -> RoundSummary:
    """A round's summary after the planes-free refinement that followed it: the extrinsic, the
    point-to-plane distances and their RMS (on the refined planes), the final cost and the time
    are the refinement's; the iterations add its steps and the solver's iterations after them."""
    planes = refined.inputs.planes
    plane = np.asarray(refined.inputs.lidar.plane, dtype=np.intp)
    dist = plane_distances(planes.normal, planes.d, plane, refined.solved.points_global)
    return replace(
        summary,
        rms_m=float(np.sqrt(np.mean(dist**2))),
        cost_end=float(refined.report.final_cost),
        iterations=summary.iterations + refined.steps + int(refined.report.iterations),
        extrinsic=extrinsic_of(refined.state),
        seconds=summary.seconds + refined.seconds,
        distances_after_m=dist.astype(np.float32),
    )


def map_movement(before: CalibrationState, after: CalibrationState, probe: PointSample) -> float:
    """How far a round moved the map, m: the extrinsic's change (a rotation change counted at
    :data:`TYPICAL_RANGE_M`) plus a high quantile of how far the LiDAR intrinsics moved the
    sample points in the LiDAR frame."""
    c = _change(before, after)
    moved = c.translation_m + np.radians(c.rotation_deg) * TYPICAL_RANGE_M
    if len(probe):
        old = lidar_point(before.lidar_intrinsics, probe.beam, probe.rho, probe.theta)
        new = lidar_point(after.lidar_intrinsics, probe.beam, probe.rho, probe.theta)
        moved += float(np.quantile(np.linalg.norm(new - old, axis=1), _MAP_MOVED_QUANTILE))
    return moved


def intrinsic_change(
    before: CalibrationState, after: CalibrationState, report: SolverReport
) -> float:
    """Largest change of a free intrinsic coordinate over a round, in its own 1-sigma."""
    old = intrinsic_coordinates(before)
    new = intrinsic_coordinates(after)
    worst = 0.0
    for name, std in zip(report.calibration_names, report.std, strict=True):
        if name in old and np.isfinite(std) and std > 0:
            worst = max(worst, abs(new[name] - old[name]) / std)
    return worst


def within(c: Change, t: Change, factor: float = 1.0) -> bool:
    """Whether every part of a round's change lies below ``factor`` times the tolerance ``t``."""
    return (
        c.translation_m < factor * t.translation_m
        and c.rotation_deg < factor * t.rotation_deg
        and c.time_offset_s < factor * t.time_offset_s
    )


def crawls(
    change: Change,
    previous: Change | None,
    *,
    at_base_distance: bool,
    steps_taken: int,
) -> bool:
    """Whether the rounds crawl and a planes-free step should be taken before the next one.

    Once the association is at its configured distance (the coarse rounds shrink their steps
    for another reason, and :data:`WANDER_SHRINK` brings them there), while fewer than
    :data:`MAX_CRAWL_STEPS` steps were taken, and when this round moved the translation by more
    than :data:`CRAWL_RATIO` of what the round before moved it.

    Args:
        change: how far this (unsettled) round moved the extrinsic.
        previous: how far the round before moved it (None for the first round, and when that
            round associated at more than ``1 / WANDER_SHRINK`` times this one's distance:
            this round then moved for the tighter association).
        at_base_distance: the round associated at the configured distance.
        steps_taken: planes-free steps already taken between rounds.
    """
    return at_base_distance and steps_taken < MAX_CRAWL_STEPS and _crawled(change, previous)


def _crawled(change: Change, previous: Change | None) -> bool:
    """This round moved the translation by more than :data:`CRAWL_RATIO` of what the round
    before moved it (False without a round before)."""
    return previous is not None and change.translation_m > CRAWL_RATIO * previous.translation_m


def stalls(rounds: Sequence[RoundSummary], *, settled: bool, steps_taken: int) -> bool:
    """Whether the rounds' map has stalled and a planes-free step should be taken before the
    next round, at whatever association distance.

    Each round builds its map at the estimate it starts from and holds those planes fixed, so a
    map blurred by the estimate's errors holds the estimate where it is: on a 20 s sinusoid
    (VLP-16, the paper's intrinsic errors, seed 8) twelve rounds kept 3 % of the sample on
    their planes at a mean map entropy of -2.5 (a settled map: -4.2), the estimate 12-19 cm and
    0.3-0.5 deg off; on a 20 s OS1-64 shake (lever arm 1.8 m) the map got blurrier round
    after round (entropy -3.04 to -2.65, associated points 96 000 to 25 000). One planes-free
    step, its planes estimated with the estimate, took either to a sharp map in the next round.

    True from the third round on, while the rounds have not settled and fewer than
    :data:`MAX_CRAWL_STEPS` steps were taken, when the last round's map is blurrier than the
    one two rounds before by more than :data:`STALL_ENTROPY`, or sharper by less than that
    with at most :data:`STALL_FRACTION` of the sample associated.

    Args:
        rounds: the summaries of the rounds so far, the last one just run.
        settled: the last round moved the estimate by less than the tolerances.
        steps_taken: planes-free steps already taken between rounds.
    """
    if settled or steps_taken >= MAX_CRAWL_STEPS or len(rounds) < 3:
        return False
    last, earlier = rounds[-1], rounds[-3]
    sharpened = earlier.map_entropy - last.map_entropy
    if not np.isfinite(sharpened):
        return False
    return bool(
        sharpened < -STALL_ENTROPY
        or (sharpened < STALL_ENTROPY and last.associated_fraction <= STALL_FRACTION)
    )


def initial_sd(names: Sequence[str], scale: F64, gyro_rotation_moved: float = 0.0) -> F64:
    """(len(names),) standard deviation of each calibration coordinate's initial value, own
    units: one characteristic scale, except the extrinsic rotation's when the gyro-to-IMU
    rotation is estimated: initialisation finds the rotation between the LiDAR and the gyro,
    and so leaves the extrinsic as uncertain as that rotation: its prior, or, when the fit
    moved it further, that move too (``gyro_rotation_moved``, rad: the angle between the
    gyro-to-IMU rotation's initial value and its estimate). A 2.4 deg R_wI against a 0.57 deg
    prior (an OS1-64 shake whose accelerometer frame the data leave open) ended 1.08 deg off,
    at 3.0 of sigmas that assumed the prior and at 1.35 of these."""
    sd = np.array(scale, dtype=np.float64)
    if any(n.startswith(GYRO_ROTATION) for n in names):
        rot = np.array([n.startswith(EXT_ROTATION) for n in names], dtype=bool)
        sd[rot] = float(np.hypot(max(CALIBRATION_SCALES[GYRO_ROTATION]), gyro_rotation_moved))
    return sd


def cover_truncated(
    report: SolverReport, initial: CalibrationState, final: CalibrationState
) -> SolverReport:
    """``report`` (at ``final``) with the sigmas of what lies in its truncated directions covering
    where ``initial`` and the rounds from it put the estimate along them
    (:func:`~licalib_cli.solver.lm.widen_along_truncated`): the last linearisation truncates
    what the data do not determine, but the estimate sits along it where the initial guess and
    the rounds before put it."""
    if not report.truncated:
        return report
    names = report.calibration_names
    moved = calibration_moved(initial, final, names)
    gyro = np.array([n.startswith(GYRO_ROTATION) for n in names], dtype=bool)
    return widen_along_truncated(
        report,
        moved,
        initial_sd(names, report.information.scale, float(np.linalg.norm(moved[gyro]))),
    )


def run_schedule(
    rec: Recording,
    guess: InitialGuess,
    noise: NoiseLevels,
    cfg: CalibConfig,
    progress: Progress,
    *,
    warm: bool = False,
) -> Fit:
    """Run the rounds from the initial guess until the estimate settles, then a denser round.

    With ``warm`` the guess is a previous fit: the model's intrinsics are estimated from the
    first round and the association starts at :data:`INTRINSICS_FACTOR` instead of
    :data:`COARSE_FACTOR` times the configured distance.

    Raises:
        ExcitationError: a map without planar surfaces.
        SolverError: the optimisation failed.
    """
    sch = cfg.schedule
    state = guess.state
    phi = guess.nominal_elevation
    regular, final = round_points(cfg, len(rec.scans))  # final: the denser round's, or None
    sample = sample_points(rec.scans, phi, regular, cfg)
    probe = sample.subset(np.arange(0, len(sample), max(1, len(sample) // _PROBE_POINTS)))
    imu = ImuData.from_samples(rec.imu, state.t0_ns)
    base = association_distance(cfg, noise)
    max_dist = base * (INTRINSICS_FACTOR if warm else COARSE_FACTOR)
    rounds: list[RoundSummary] = []
    report: SolverReport | None = None
    inputs: RoundInputs | None = None
    solved: SolvedProblem | None = None
    settled = False
    change = Change(np.inf, np.inf, np.inf)
    threshold = change
    want_intrinsics = estimates_intrinsics(cfg)
    intrinsics_on = want_intrinsics and (warm or sch.intrinsics_from_round == 1)
    joined = 1 if intrinsics_on else 0
    intrinsic_sigmas = 0.0
    mapped: MappedSample | None = None  # the last round's points mapped with its estimate
    previous: Change | None = None  # the change of the round before
    previous_at = np.inf  # the association distance of the round before
    crawl_steps = 0
    step: tuple[CalibrationState, CalibrationState] | None = None  # the last step, from and to
    dense_after = final is not None
    cap, index = sch.max_rounds, 0
    while index < cap:
        index += 1
        before = state
        solved = None  # the previous round's evaluation is not kept while this one runs
        try:
            done = run_round(
                state,
                sample,
                imu,
                with_clock_rate(
                    round_settings(cfg, noise, max_dist, intrinsics_on, provisional=dense_after),
                    rec.clock_rate,
                ),
                index,
                mapped,
            )
        except ExcitationError as err:
            if not rounds:
                raise
            given = [
                key
                for key, source in (
                    ("rotation_rpy_deg", guess.rotation_source),
                    ("translation_m", guess.translation_source),
                )
                if source == "config"
            ]
            raise _diverged(
                err, index, rounds[0], _change(guess.state, state), given, beams_held(cfg)
            ) from err
        state, summary, report, inputs = done.state, done.summary, done.report, done.inputs
        solved, mapped = done.solved, done.mapped
        del done
        rounds.append(summary)
        progress.advance(index, cap)
        change = _change(before, state)
        threshold = _threshold(report, cfg)
        intrinsic_sigmas = intrinsic_change(before, state, report) if intrinsics_on else 0.0
        moved = map_movement(before, state, probe)
        logger.info(
            "Round %d: %d points on %d surfels (within %.1f cm), RMS %.2f cm, change %.2f mm / "
            "%.4f deg / %.3f ms%s; the map moved %.1f mm, its entropy is %.3f.",
            index,
            summary.points,
            summary.surfels,
            100 * max_dist,
            100 * summary.rms_m,
            1e3 * change.translation_m,
            change.rotation_deg,
            1e3 * change.time_offset_s,
            f", intrinsics up to {intrinsic_sigmas:.2f} sigma" if intrinsics_on else "",
            1e3 * moved,
            summary.map_entropy,
        )
        settled = within(change, threshold) and (
            not intrinsics_on or intrinsic_sigmas < sch.intrinsic_tolerance_sigmas
        )
        if want_intrinsics and not intrinsics_on:
            due = sch.intrinsics_from_round
            # Default: once the extrinsic settles, or after JOIN_BY rounds if it does not
            # (a model without intrinsics may not settle on data that need them).
            ready = (settled and index >= 2) or index >= JOIN_BY
            if (due == 0 and ready) or (due > 0 and index + 1 >= due):
                # The intrinsics join: the map will change as they move, so associate more
                # generously again and tighten as they settle.
                intrinsics_on, joined = True, index + 1
                settled = False
                max_dist = max(max_dist, base * INTRINSICS_FACTOR)
                previous = None  # the next round's change is the intrinsics', not a crawl
                logger.info("The intrinsics of the model join from round %d.", joined)
                continue
        enough_rounds = index >= 2 and (not want_intrinsics or index >= joined + 1)
        if settled and enough_rounds and max_dist <= base:
            break
        # a step compares two rounds at about the configured distance: a round after a much
        # tighter association (or after a coarse round that stopped at once) moves for that
        comparable = previous if previous_at * WANDER_SHRINK <= max_dist * (1 + 1e-9) else None
        if step is not None and before is step[1] and takes_back(*step, state):
            # the rounds and the planes-free step disagree: this round's move is the step
            # taken back, not a crawl, and another step would be taken back again
            logger.info(
                "Round %d took back the planes-free step before it; no more steps between the "
                "rounds.",
                index,
            )
            comparable, crawl_steps = None, MAX_CRAWL_STEPS
        stalled = stalls(rounds, settled=settled, steps_taken=crawl_steps)
        if stalled or (
            not settled
            and crawls(
                change, comparable, at_base_distance=max_dist <= base, steps_taken=crawl_steps
            )
        ):
            # The rounds crawl (or the map stalls, see stalls()): each holds its map's planes
            # fixed, and a map built at the estimate pulls the round back towards it, so the
            # estimate moves by a nearly constant fraction of what is left per round. With LiDAR
            # intrinsics the common mode of the range offsets and scales crawls so (on a 10 s
            # shake with 2-7 cm range offsets: 2.3, 2.1, 2.0, ... 1.2 mm over eight rounds, then
            # 12 mm at once with the planes free); without them a translation the initial guess
            # had 13 cm off (a clean sinusoid with the LiDAR's spin axis horizontal) came 20-48
            # mm a round and was still 57 mm away after twelve. A step with the planes free goes
            # there; the next rounds, on a map rebuilt from it, check that it has settled (so no
            # solve on the stepped planes follows it: the next round solves on its own map).
            stepped = planes_free_steps_from(
                state, inputs, round_settings(cfg, noise, base, True).solver, solved=solved
            )
            if stepped is not None:
                if stalled:
                    why = (
                        f"The map stalls (entropy {rounds[-3].map_entropy:.3f} two rounds ago, "
                        f"{summary.map_entropy:.3f} now; "
                        f"{100 * summary.associated_fraction:.0f} % of the points on its planes)"
                    )
                else:
                    assert comparable is not None  # crawls() needs the round before
                    why = (
                        f"The rounds crawl (change {1e3 * change.translation_m:.2f} mm after "
                        f"{1e3 * comparable.translation_m:.2f} mm)"
                    )
                logger.info(
                    "%s: planes-free step, change %s.",
                    why,
                    _describe(_change(state, stepped.state)),
                )
                step = (state, stepped.state)
                state, crawl_steps = stepped.state, crawl_steps + 1
                mapped = solved = None  # both were at the round's estimate
                if stepped.steps > 0:
                    # a step near the cap still gets the rounds that check it (steps are few)
                    cap = max(cap, index + STEP_CHECK_ROUNDS)
        wanders = index >= 3 and _crawled(change, previous)
        previous, previous_at = change, max_dist
        max_dist = max(base, min(max_dist * (WANDER_SHRINK if wanders else 1.0), 3.0 * moved))
    assert report is not None and inputs is not None
    jitter = not settled and within(change, threshold, JITTER_FACTOR)
    converged = settled or jitter
    if not converged:
        logger.warning(
            "The estimate still moved %.2f mm / %.4f deg / %.3f ms in round %d of %d.",
            1e3 * change.translation_m,
            change.rotation_deg,
            1e3 * change.time_offset_s,
            len(rounds),
            cap,
        )
    final_unsettled = False
    last_jump = 0.0  # how far the last dense round moved the extrinsic, in its sigmas
    final_rounds = 0
    if dense_after:
        # One more round on a denser sample from the settled estimate: the uncertainty of the
        # time offset and the translation shrinks with the number of points. The denser data
        # may also determine a direction the regular rounds held (below the truncation
        # threshold there). The round maps and associates, then takes Gauss-Newton steps with
        # the map's planes estimated too instead of solving on fixed planes: the regular rounds
        # hold each map's planes fixed, and a map built at the estimate pulls the next round
        # back towards it, so they stop short of the optimum whatever the model (a clean OS1-32
        # sinusoid 8.3, 6.6, 6.1 mm off in y over three rounds, 3.8 mm after a dense round on
        # fixed planes, 2.1 mm with them free). Without LiDAR intrinsics one step does it (the
        # first gained 680.7 of the cost there, the second 0.2); with them, up to MAX_STEPS (the
        # common mode of the range offsets and scales trades off against the planes). A move of
        # many of its own sigmas is checked by another dense round on a map rebuilt at the
        # moved estimate, as the regular rounds are.
        assert final is not None
        dense = sample_points(rec.scans, phi, final, cfg, seed=1)
        steps = MAX_STEPS if intrinsics_on and inputs.free.any_lidar_intrinsics else 1
        solved = None
        previous_jump = np.inf
        for attempt in range(1, MAX_CONVERGING_FINAL_ROUNDS + 1):
            final_rounds = attempt
            before = state
            done = run_round(
                state,
                dense,
                imu,
                with_clock_rate(
                    round_settings(cfg, noise, base, intrinsics_on, evaluate_only=True),
                    rec.clock_rate,
                ),
                len(rounds) + 1,
            )
            state, summary, report, inputs = done.state, done.summary, done.report, done.inputs
            solved = done.solved
            del done
            refined = refine_with_planes(
                state, inputs, round_settings(cfg, noise, base, True).solver, steps, solved
            )
            if refined is not None:
                logger.info(
                    "Planes-free steps: %d, cost without the range noise %.1f -> %.1f (%.1f s).",
                    refined.steps,
                    refined.cost_start,
                    refined.cost_end,
                    refined.seconds,
                )
                summary = refined_summary(summary, refined)
                state, report, inputs = refined.state, refined.report, refined.inputs
                solved = refined.solved
            rounds.append(summary)
            dense_change = _change(before, state)
            jump = last_jump = final_jump(dense_change, report, cfg)
            logger.info(
                "Final round%s (planes free): %d points on %d surfels, RMS %.2f cm, change %.2f "
                "mm / %.4f deg / %.3f ms (%.1f of its sigmas).",
                f" {attempt}" if attempt > 1 else "",
                summary.points,
                summary.surfels,
                100 * summary.rms_m,
                1e3 * dense_change.translation_m,
                dense_change.rotation_deg,
                1e3 * dense_change.time_offset_s,
                jump,
            )
            # After regular rounds that ran out unsettled the dense rounds go on until one,
            # the second or later, comes to rest (dense_rounds_rested), within the same caps
            if converged and jump <= FINAL_SETTLE_SIGMAS:
                break
            if not converged and jump <= DENSE_REST_SIGMAS and attempt >= 2:
                break
            converging = jump <= FINAL_SHRINK * previous_jump
            previous_jump = jump
            if attempt >= MAX_FINAL_ROUNDS and (
                not converging or attempt == MAX_CONVERGING_FINAL_ROUNDS
            ):
                if jump <= FINAL_SETTLE_SIGMAS:
                    break  # settled as dense rounds do, not at rest: the regular rounds' finding
                final_unsettled = True
                change = dense_change
                logger.warning(
                    "The denser final round still moved the estimate %.2f mm / %.4f deg / "
                    "%.3f ms (%.1f of its sigmas) after %d dense rounds.",
                    1e3 * dense_change.translation_m,
                    dense_change.rotation_deg,
                    1e3 * dense_change.time_offset_s,
                    jump,
                    attempt,
                )
                break
    elif intrinsics_on and inputs.free.any_lidar_intrinsics:
        # No denser round: the rounds hold each map fixed and stall along the common mode of
        # the range offsets and scales; a last refinement estimates the planes with everything
        # else.
        refined = refine_with_planes(
            state, inputs, round_settings(cfg, noise, base, True).solver, MAX_STEPS, solved
        )
        if refined is not None:
            logger.info(
                "Planes-free refinement: %d steps, cost without the range noise %.1f -> %.1f, "
                "change %s (%.1f s).",
                refined.steps,
                refined.cost_start,
                refined.cost_end,
                _describe(_change(state, refined.state)),
                refined.seconds,
            )
            rounds[-1] = refined_summary(rounds[-1], refined)
            state, report, inputs = refined.state, refined.report, refined.inputs
            solved = refined.solved
    report = cover_truncated(report, guess.state, state)
    return Fit(
        state=state,
        rounds=tuple(rounds),
        report=report,
        inputs=inputs,
        converged=converged and not final_unsettled,
        jitter=jitter and not final_unsettled,
        last_change=change,
        settle_threshold=threshold,
        solved=solved,
        final_unsettled=final_unsettled,
        final_jump=last_jump,
        final_rounds=final_rounds,
        extra_rounds=max(0, index - sch.max_rounds),
        points=point_budget(cfg, rec.scans),
    )
