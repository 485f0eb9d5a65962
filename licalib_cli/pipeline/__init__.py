"""``licalib calibrate``: one call from a bag to a checked calibration, stage by stage.

Data flow (method.md sections 5-8), one module per stage::

    bag --read------------> Recording (IMU samples, LiDAR scans; int64 ns) and the noise
        --initialise------> odometry, rotation, coarse time offset, lever arm, gravity, splines
        --schedule/round--> rounds of surfel map + associations + Levenberg-Marquardt (Schur
                            complement, truncated SVD), coarse to fine, until it settles
        --fitcheck/split--> residuals per sensor, score tests of fixed effects, split halves
        --checks----------> verdict, inflated sigmas, observability
        --evident---------> an effect the data show beyond doubt estimated when it pays its BIC
        --effect_refit----> one left fixed refitted to measure its shift; checks judge again
        --noise_draws-----> on a noisy LiDAR, refits with more range noise floor the sigmas
        --assemble--------> CalibrationResult (schema v1 with typed sections)

Frames and time: ``{G}`` is the IMU frame at the first IMU sample of the segment (``t0_ns``),
the splines carry ``T_G_I(t)`` on the IMU clock in seconds since ``t0_ns``, and a point stamped
``tau`` on the LiDAR clock is evaluated at ``tau + time_offset_s``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

from licalib_cli.config import CalibConfig
from licalib_cli.errors import LicalibError
from licalib_cli.estimation import CalibrationState
from licalib_cli.measurements import Recording
from licalib_cli.pipeline.assemble import assemble
from licalib_cli.pipeline.checks import Checks, check, rejudge
from licalib_cli.pipeline.effect_refit import refit_shifts
from licalib_cli.pipeline.fitcheck import EffectEvidence
from licalib_cli.pipeline.initialise import InitialGuess, initialise, lidar_odometry
from licalib_cli.pipeline.knot_spacing import with_knot_spacing
from licalib_cli.pipeline.read import read
from licalib_cli.pipeline.round import RoundSummary
from licalib_cli.pipeline.scan_pattern import SPINNING, ScanPattern, with_scan_pattern
from licalib_cli.pipeline.schedule import Fit, run_schedule
from licalib_cli.pipeline.settings import NoiseLevels
from licalib_cli.pipeline.timing import StageTime, Timer
from licalib_cli.progress import NullProgress, Progress
from licalib_cli.results import CalibrationResult
from licalib_cli.sections import RecordingSection, VerdictSection
from licalib_cli.solver.lm import SolverReport

__all__ = [
    "CalibrationRun",
    "InitialGuess",
    "Prepared",
    "RoundSummary",
    "StageTime",
    "Timer",
    "calibrate",
    "fit_and_check",
    "judged_again",
    "noise_spread",
    "prepare",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationRun:
    """Everything ``calibrate`` produces.

    Attributes:
        result: the result file content.
        state: the final estimate of every parameter (splines included).
        initial: the initial guess.
        fit: the rounds' outcome.
        checks: the checks' outcome (verdict, sigmas, consistency).
        noise: the noise the fit was weighted with.
        timings: wall seconds per stage, in order.
        warnings: non-fatal findings of the reading stage.
        effects: the score tests of the effects the fit held fixed (selected ones first).
        segment: the segment's measurements (for the report and the map files), or None.
        stage_times: wall and CPU seconds per stage, in order (the same stages as ``timings``).
        config: the configuration of the model estimated when ``calibrate`` added effects the
            data show beyond doubt (:mod:`~licalib_cli.pipeline.evident`) or took the clouds for
            a non-repetitive scanner's (``lidar.scan_pattern``); None: the one given.
        pattern: what the clouds' beam field means (spinning or non-repetitive).
    """

    result: CalibrationResult
    state: CalibrationState
    initial: InitialGuess
    fit: Fit
    checks: Checks
    noise: NoiseLevels
    timings: dict[str, float]
    warnings: tuple[str, ...] = ()
    effects: tuple[EffectEvidence, ...] = ()
    segment: Recording | None = None
    stage_times: dict[str, StageTime] = field(default_factory=dict)
    config: CalibConfig | None = None
    pattern: ScanPattern = SPINNING

    @property
    def rounds(self) -> tuple[RoundSummary, ...]:
        """One summary per round."""
        return self.fit.rounds

    @property
    def solver(self) -> SolverReport:
        """The final round's solver report."""
        return self.fit.report

    @property
    def verdict(self) -> VerdictSection:
        """The verdict section."""
        return self.checks.verdict

    @property
    def recording(self) -> RecordingSection:
        """The recording section."""
        assert self.result.recording is not None
        return self.result.recording


def calibrate(
    bag: Path, cfg: CalibConfig, progress: Progress | None = None, *, rivals: bool | None = None
) -> CalibrationRun:
    """Calibrate ``T_imu_lidar`` and the time offset from one segment of a bag, and check it.

    Args:
        bag: a ROS1 ``.bag`` (or folder of split bags), a ROS2 bag folder, or a bare ``.db3`` /
            ``.mcap`` file. It is only read.
        cfg: the configuration tree.
        progress: where stage progress goes (nothing by default).
        rivals: size in the checks which effects can stand in for each other (read when effects
            are added); by default when ``cfg`` adds the effects the data show beyond doubt.

    Returns:
        The run: result, verdict, sigmas, observability, fit checks, per-round and per-stage
        figures.

    Raises:
        BagError, TopicError, DataError, TimestampError, ConfigError: unusable input.
        ExcitationError: the motion or the scene does not support a calibration.
        SolverError: the optimisation failed.
    """
    progress = progress or NullProgress()
    timer = Timer()
    given = cfg
    prepared = prepare(Path(bag), cfg, progress, timer)
    cfg = prepared.cfg
    # the checks size which effects can stand in for each other when effects may be added
    sized = cfg.model.add_evident_effects if rivals is None else rivals
    run = fit_and_check(prepared, prepared.guess, cfg, progress, timer, rivals=sized)
    from licalib_cli.pipeline.evident import Evident, add_evident, with_added  # builds on this

    evident = (
        add_evident(prepared, run, cfg, progress, timer)
        if cfg.model.add_evident_effects
        else Evident(run, cfg)
    )
    from licalib_cli.pipeline.undetermined import weigh_undetermined, with_choice

    run = _refit_unmistakable(prepared, evident.run, evident.cfg, progress, timer, evident.declined)
    run, choice = weigh_undetermined(prepared, run, evident.cfg, progress, timer)
    run = noise_spread(prepared, run, evident.cfg, progress, timer)
    if evident.added or evident.notes:
        run = with_added(run, evident.added, evident.notes)
    run = with_choice(run, choice)
    if evident.added or prepared.cfg is not given:
        # the model with the effects added, or the scan pattern the data showed
        run = replace(run, config=evident.cfg)
    progress.close()
    return run


def noise_spread(
    prepared: Prepared, run: CalibrationRun, cfg: CalibConfig, progress: Progress, timer: Timer
) -> CalibrationRun:
    """``run`` judged again with its sigmas at least the spread of refits with more range noise
    (:mod:`licalib_cli.pipeline.noise_draws`); ``run`` itself below the noise that asks for
    them, or when its rounds did not converge."""
    from licalib_cli.pipeline.noise_draws import draws_due, range_noise_spread, spread_text

    if (
        not draws_due(prepared.noise, cfg)
        or run.checks.exit_status == "not converged"
        or run.checks.split is None
    ):
        return run
    with timer.stage("noise draws", progress):
        spread = range_noise_spread(prepared.rec, prepared.guess, run.state, prepared.noise, cfg)
    if spread is None:
        return run
    text = spread_text(prepared.noise, cfg.checks.range_noise_draws)
    judged = rejudge(run.fit, run.checks, run.checks.effects, cfg, (spread, text))
    return judged_again(prepared, run, judged, cfg, timer)


def judged_again(
    prepared: Prepared, run: CalibrationRun, checks: Checks, cfg: CalibConfig, timer: Timer
) -> CalibrationRun:
    """``run`` with the checks judged again on its fit, its result assembled from them and the
    stage times so far."""
    result = assemble(prepared.bag, prepared.rec, prepared.guess, run.fit, checks, cfg)
    return replace(
        run,
        result=result,
        checks=checks,
        effects=checks.effects,
        timings=timer.timings,
        stage_times=dict(timer.stages),
    )


def _refit_unmistakable(
    prepared: Prepared,
    run: CalibrationRun,
    cfg: CalibConfig,
    progress: Progress,
    timer: Timer,
    known: tuple[str, CalibrationState] | None = None,
) -> CalibrationRun:
    """``run`` judged again with the shift of an effect the data show beyond doubt measured by
    a refit with it estimated (:mod:`licalib_cli.pipeline.effect_refit`); ``run`` itself when
    there is none, or when the rounds did not converge (a refit would go on where they stopped,
    and its move would be theirs as much as the effect's). ``known``: an effect already
    refitted from ``run`` and that refit's estimate (taken instead of refitting again)."""
    from licalib_cli.pipeline.effect_models import with_effect  # builds on this module

    if not cfg.checks.refit_effects or run.checks.exit_status == "not converged":
        return run

    def refit(effect: str) -> CalibrationState | None:
        if known is not None and known[0] == effect:
            return known[1]
        start = replace(prepared.guess, state=run.state)
        try:
            with timer.stage("refit", progress, total=cfg.schedule.max_rounds):
                fit = run_schedule(
                    prepared.rec,
                    start,
                    prepared.noise,
                    with_effect(cfg, effect),
                    progress,
                    warm=True,
                )
        except LicalibError as exc:
            logger.warning("The refit with %s failed (%s); its shift stays predicted.", effect, exc)
            return None
        return fit.state

    effects = refit_shifts(run.checks.effects, run.state, refit)
    if effects is None:
        return run
    return judged_again(prepared, run, rejudge(run.fit, run.checks, effects, cfg), cfg, timer)


@dataclass(frozen=True)
class Prepared:
    """What every fit of one segment shares: the data, the noise and the initial guess.

    Attributes:
        bag: the bag read.
        rec: the segment.
        noise: the noise the fits are weighted with.
        guess: the initial guess.
        pattern: what the clouds' beam field means (spinning or non-repetitive).
        cfg: the configuration given, with ``lidar.scan_pattern`` and ``spline.knot_spacing_s``
            the data's (what every fit of the segment uses).
    """

    bag: Path
    rec: Recording
    noise: NoiseLevels
    guess: InitialGuess
    pattern: ScanPattern
    cfg: CalibConfig


def prepare(bag: Path, cfg: CalibConfig, progress: Progress, timer: Timer) -> Prepared:
    """Read the segment, measure the noise, run the odometry and initialise."""
    with timer.stage("read", progress):
        segment = read(bag, cfg)
    rec, noise = segment.recording, segment.noise
    cfg = with_scan_pattern(cfg, segment.pattern)
    if segment.knots is not None:
        cfg = with_knot_spacing(cfg, segment.knots.spacing_s)
    with timer.stage("odometry", progress, total=len(rec.scans)):
        odo = lidar_odometry(rec, cfg, progress=progress.advance)
    with timer.stage("initialisation", progress):
        guess = initialise(rec, odo, segment.nominal_elevation, noise, cfg)
    return Prepared(bag, rec, noise, guess, segment.pattern, cfg)


def fit_and_check(
    prepared: Prepared,
    start: InitialGuess,
    cfg: CalibConfig,
    progress: Progress,
    timer: Timer,
    *,
    warm: bool = False,
    rivals: bool = False,
) -> CalibrationRun:
    """The rounds from ``start``, the checks and the result file content.

    Args:
        prepared: the segment, noise and initial guess.
        start: where the rounds start (``prepared.guess``, or a previous fit's state).
        cfg: the configuration (its ``model:`` section says what is estimated).
        progress: progress sink.
        timer: stage timer (times add up over several fits).
        warm: ``start`` is already a fit: the model's intrinsics are estimated from the first
            round and the association starts less loose.
        rivals: size which candidates stand in for each significant effect
            (:attr:`~licalib_cli.pipeline.fitcheck.EffectEvidence.explained_by`; read by
            ``diagnose`` and by the evident effects' rivals).
    """
    rec, noise, guess = prepared.rec, prepared.noise, prepared.guess
    with timer.stage("optimisation", progress, total=cfg.schedule.max_rounds):
        fit = run_schedule(rec, start, noise, cfg, progress, warm=warm)
    with timer.stage("checks", progress):
        checks = check(fit, guess, noise, cfg, rivals=rivals, clock_rate=rec.clock_rate)
    fit = replace(fit, solved=None)  # the final problem's Jacobians are not kept with the run
    result = assemble(prepared.bag, rec, guess, fit, checks, cfg)
    return CalibrationRun(
        result=result,
        state=fit.state,
        initial=guess,
        fit=fit,
        checks=checks,
        noise=noise,
        timings=timer.timings,
        stage_times=dict(timer.stages),
        warnings=rec.warnings,
        effects=checks.effects,
        segment=rec,
        pattern=prepared.pattern,
    )
