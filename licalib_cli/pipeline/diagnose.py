"""Model selection stage (``licalib diagnose``, ``calibrate --model auto``, method.md section 10).

1. Fit the base model: extrinsic, time offset, trajectory, biases and gravity. A base model
   that loses its map (beams that disagree by centimetres blur it) has the beams' intrinsics
   freed, and those the data need kept, before anything is scored
   (:mod:`~licalib_cli.pipeline.beams_in_base`).
2. Score every candidate effect the model lacks against the residuals (a Lagrange-multiplier
   test with the trajectory and the estimated parameters profiled out through the solver's Schur
   complement, :mod:`licalib_cli.consistency.score`), the strongest first.
3. Add the strongest significant candidate to the model, refit from the current estimate, and
   keep it only if the Bayesian information criterion improves: ``BIC = sum r^2 + k ln n`` over
   the same measurements and map (the model without the effect is re-solved on the new fit's
   map, so that both see the same data). ``n`` is the number of residuals of the sensor the
   effect belongs to: an IMU scale is determined by some 10^4 IMU residuals, not by the 10^5
   LiDAR points that dominate the total (with the total, an IMU effect with three parameters
   needed a cost decrease of 38 where its score test was significant from 26).
   A close rival (a candidate that explains most of its score when freed with it, of either
   sensor: :func:`~.rivals.rivals_of`) is refitted as well and compared with it on the same
   data (:func:`~.rivals.rival_delta_bic`); a pair that neither score test separates is reported
   as not told apart (:func:`~.rivals.not_told_apart`). A rival that lost to an effect kept is
   offered once more while the data still show it (:class:`~.rivals.CandidatePool`).
   A per-beam effect whose free numbers do not pay (each pays ``ln n``) is refitted once more
   as one random effect across beams: its numbers drawn from ``N(0, s^2)`` with the spread
   ``s`` that best explains its score (:mod:`licalib_cli.consistency.spread`, set in
   ``model.lidar_spread``), its BIC the refit's sum of squares (the prior's term included)
   plus ``ln det(1 + s^2 I)`` and ``ln n`` for ``s`` (:func:`spread_worth_trying`).
   A bias walk, tested and first refitted as one linear drift, is refitted once that pays as a
   bias linear over each of 2, 4 and 8 equal pieces of the segment, each kept while the BIC
   falls further (:mod:`licalib_cli.pipeline.walk_pieces`, ``model.bias_walk_piece_s``).
   An effect the truncated SVD held at its characteristic scale although its score test shows
   it far above is refitted expecting that size (:mod:`licalib_cli.pipeline.effect_size`,
   ``model.expected_size``).
4. Repeat until no candidate is significant, or ``max_effects`` were added.
5. Check backwards: an effect added early may explain nothing that the effects added after it
   do not (an accelerometer misalignment picked first on a bag whose gyro is rotated: once the
   gyro rotation is in, the misalignment gains a sum of squares of 0.9 for its three
   parameters). Each kept effect but the last is taken out on the final fit's data (reset to
   its starting value, the rest re-solved); when the BIC is lower without it, it is dropped,
   the model refitted without it, and the check repeated (:func:`~.backward.drop_redundant`).
6. For every candidate not added, say how large it would have to be for this bag to show it
   (:class:`NotShown`): "not found" is then a statement about the data, not about the sensor.

Each step records the effect, its test, its estimate with 1-sigma, the gap of its sensor before
and after (chi-square per sample above what a model that explains the data leaves, the residual
RMS, and for LiDAR effects the mean map entropy) and how far the extrinsic moved.

What "a model that explains the data leaves" is comes from a twin recording of each fit
(:mod:`licalib_cli.pipeline.twin`): the fitted model's own prediction of every measurement with
noise of the fitted levels, fitted and checked the same way. Its chi-square per sample is the
reference of the gap (the IMU's is below 1 because the trajectory spline absorbs some noise, the
LiDAR's because the planes are fitted to the same points); without a twin (its fit failed) the
reference is the analytic ``1 - knots / IMU samples`` (IMU) and 1 (LiDAR).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

from licalib_cli.config import CalibConfig, LidarSpreadSection
from licalib_cli.consistency.distributions import chi2_isf, chi2_sf
from licalib_cli.consistency.power import (
    DETECTION_POWER,
    DISPLAY_UNITS,
    detectable_rms,
    display_size,
)
from licalib_cli.consistency.score import EffectScore
from licalib_cli.consistency.spread import SharedSpread, shared_spread
from licalib_cli.errors import MapLost
from licalib_cli.estimation import intrinsic_coordinates
from licalib_cli.pipeline import (
    CalibrationRun,
    Prepared,
    Timer,
    fit_and_check,
    noise_spread,
    prepare,
)
from licalib_cli.pipeline.backward import deltas_without, drop_redundant
from licalib_cli.pipeline.beams_in_base import BeamsInBase, base_with_beams
from licalib_cli.pipeline.diagnosis_step import (
    CANDIDATES,
    GAP_NOISE_SIGMAS,
    LIDAR_SUFFIX,
    DiagnosisStep,
    Gap,
)
from licalib_cli.pipeline.effect_models import (
    bic_terms,
    final_config,
    of_effect,
    sensor_samples,
    with_effects,
    with_spread,
    without_effect,
)
from licalib_cli.pipeline.effect_size import sized_refit, with_sizes_of
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE
from licalib_cli.pipeline.held_effects import HELD_WEIGHT
from licalib_cli.pipeline.knot_spacing import with_knot_spacing
from licalib_cli.pipeline.lost_map import beams_held, collapsed_map
from licalib_cli.pipeline.rivals import CandidatePool, compare_rivals, pick_rival, rivals_of
from licalib_cli.pipeline.round import extrinsic_of
from licalib_cli.pipeline.scan_pattern import with_scan_pattern
from licalib_cli.pipeline.settings import LIDAR_COLUMNS, lm_params
from licalib_cli.pipeline.twin import TWIN_ITERATIONS, Twin, twin_checks
from licalib_cli.pipeline.walk_pieces import WALKS, finer_walk
from licalib_cli.progress import NullProgress, Progress

__all__ = [
    "CANDIDATES",
    "DETECTION_POWER",
    "DISPLAY_UNITS",
    "GAP_NOISE_SIGMAS",
    "PER_BEAM_CANDIDATES",
    "Diagnosis",
    "DiagnosisStep",
    "Gap",
    "NotShown",
    "detectable_rms",
    "diagnose",
    "share_of",
    "spread_worth_trying",
    "twin_of",
    "wants_share",
]

logger = logging.getLogger(__name__)

PER_BEAM_CANDIDATES = frozenset(
    name
    for name, (sensor, block, _) in CANDIDATES.items()
    if sensor == "lidar" and block in LIDAR_COLUMNS
)
"""The candidates that are a LiDAR beam's intrinsics (not tried on a non-repetitive scanner)."""


@dataclass(frozen=True)
class NotShown:
    """A candidate the data do not show, and how large it would have to be to show.

    Attributes:
        effect: its name (:data:`CANDIDATES`).
        statistic: its score statistic on the final fit (tested with the effects added freed).
        dof: degrees of freedom (directions of the effect the bag determines; 0: none).
        p_value: the test's p-value.
        detectable_rms: RMS per coordinate, in solver units, from which an effect along any
            direction the bag determines is named at least :data:`DETECTION_POWER` of the time
            (its weakest direction; ``inf``: the bag determines no direction of it). Below it,
            an effect may hide in this bag.
        detectable_rms_best: the same along the best-determined direction: well below it, no
            effect of the kind shows in this bag.
    """

    effect: str
    statistic: float
    dof: int
    p_value: float
    detectable_rms: float
    detectable_rms_best: float = float("inf")

    @property
    def detectable(self) -> tuple[float, str]:
        """``detectable_rms`` in the unit of :data:`DISPLAY_UNITS`."""
        return display_size(self.effect, self.detectable_rms)

    @property
    def detectable_best(self) -> tuple[float, str]:
        """``detectable_rms_best`` in the unit of :data:`DISPLAY_UNITS`."""
        return display_size(self.effect, self.detectable_rms_best)


def _not_shown(
    run: CalibrationRun, allowed: tuple[str, ...], found: tuple[str, ...]
) -> tuple[NotShown, ...]:
    """Every allowed candidate not added nor tried, with the size this bag would need to show
    it (``found``: the effects added and those tried)."""
    out = []
    seen = set()
    for e in run.effects:
        name = e.score.name
        if name not in allowed or name in found or name in seen:
            continue
        seen.add(name)
        rank = int(e.score.rank)
        threshold = chi2_isf(EFFECT_P_VALUE, max(rank, 1))
        weakest, best = detectable_rms(threshold, e.score.estimate.size, e.score.information)
        out.append(
            NotShown(
                effect=name,
                statistic=float(e.score.statistic),
                dof=rank,
                p_value=float(e.score.p_value),
                detectable_rms=weakest,
                detectable_rms_best=best,
            )
        )
    for name in allowed:  # candidates with no free coordinate in this bag (e.g. no beam kept)
        if name not in found and name not in seen:
            out.append(NotShown(name, 0.0, 0, 1.0, float("inf"), float("inf")))
    return tuple(out)


@dataclass(frozen=True)
class Diagnosis:
    """What ``diagnose`` found.

    Attributes:
        base: the fit of the base model.
        steps: every candidate tried, in order.
        final: the fit with the effects kept.
        effects_found: the effects kept, in the order added.
        base_twin: the twin recordings of the base fit (None if none could be fitted).
        final_twin: those of the final fit.
        not_shown: the candidates not added, each with the size this bag would need to show it.
        config: the configuration of the final fit: the ``model:`` section lists the effects
            kept (and the spread of those kept as one spread across beams); calibrating with it
            estimates that model.
        beams_in_base: the beams' intrinsics that joined a base model which lost its map
            (:mod:`~licalib_cli.pipeline.beams_in_base`; None when the base model held it).
            Those kept lead :attr:`effects_found`, and ``base`` is the fit with them.
    """

    base: CalibrationRun
    steps: tuple[DiagnosisStep, ...]
    final: CalibrationRun
    effects_found: tuple[str, ...]
    base_twin: Twin | None = None
    final_twin: Twin | None = None
    not_shown: tuple[NotShown, ...] = ()
    config: CalibConfig | None = None
    beams_in_base: BeamsInBase | None = None


def _expected_chi2(sensor: str, knot_spacing_s: float, imu_rate_hz: float) -> float:
    if sensor == "lidar":
        return 1.0
    knots_per_s = 1.0 / knot_spacing_s
    return max(0.0, 1.0 - knots_per_s / max(imu_rate_hz, 1e-9))


def _gap(run: CalibrationRun, sensor: str, imu_rate_hz: float, twin: Twin | None) -> Gap:
    consistency = run.result.consistency
    assert consistency is not None
    s = next(c for c in consistency.sensors if c.sensor == sensor)
    t = twin.sensor(sensor) if twin is not None else None
    nan = float("nan")
    return Gap(
        sensor=sensor,
        chi2_per_sample=s.chi2_per_sample,
        expected=_expected_chi2(sensor, run.state.knots.dt_s, imu_rate_hz),
        rms=s.rms,
        map_entropy=run.rounds[-1].map_entropy if sensor == "lidar" else nan,
        twin_chi2_per_sample=t.chi2_per_sample if t is not None else nan,
        twin_spread=t.chi2_spread if t is not None else nan,
        twin_rms=t.rms if t is not None else nan,
        samples=int(s.samples),
    )


def twin_of(run: CalibrationRun, cfg: CalibConfig) -> Twin | None:
    """The twin recordings of a fit (:mod:`licalib_cli.pipeline.twin`)."""
    return twin_checks(
        run.state,
        run.fit.inputs,
        run.noise,
        lm_params(cfg, max_iterations=TWIN_ITERATIONS),
    )


def spread_worth_trying(step: DiagnosisStep, score: EffectScore) -> SharedSpread | None:
    """The spread across beams to refit a per-beam effect with, when its free numbers did not
    pay (``step``, the pick of its step) although its score test is significant, and the linear
    model says that one spread would pay (:mod:`licalib_cli.consistency.spread`); None
    otherwise."""
    if step.kept or step.effect not in LIDAR_SUFFIX or not step.p_value < EFFECT_P_VALUE:
        return None
    if not math.isfinite(step.bic_log_n):
        return None
    spread = shared_spread(score.gradient, score.profiled_information)
    if not (spread.sigma > 0.0 and spread.delta_bic(step.bic_log_n) < 0.0):
        return None
    return spread


def _estimate(run: CalibrationRun, effect: str) -> dict[str, tuple[float, float]]:
    values = intrinsic_coordinates(run.state)
    std = dict(zip(run.solver.calibration_names, run.solver.std, strict=True))
    return {
        name: (float(value), float(std[name]))
        for name, value in values.items()
        if of_effect(name, effect) and name in std
    }


def _held(run: CalibrationRun, effect: str) -> tuple[str, ...]:
    """The coordinates of ``effect`` that ``run``'s solver mostly held where they started: they
    lie in directions the data determine worse than their characteristic scale (truncated SVD;
    an intrinsic there keeps its nominal value and that scale as its sigma)."""
    report = run.solver
    return tuple(
        name
        for name, w in zip(report.calibration_names, report.truncated_weight, strict=True)
        if w >= HELD_WEIGHT and of_effect(name, effect)
    )


SHARE_BELOW = 0.5
"""A kept effect whose own step closed less than this fraction of its sensor's gap gets its
share on the final model (:func:`share_of`) when that model holds other effects too."""


def wants_share(step: DiagnosisStep, kept: tuple[str, ...]) -> bool:
    """Whether a step's effect gets its share on the final model of the effects ``kept``: it is
    one of several there and its own step closed less than :data:`SHARE_BELOW` of its
    sensor's gap (a gap within its noise has no shrink, and no share either)."""
    return len(kept) >= 2 and step.kept and step.effect in kept and step.shrink < SHARE_BELOW


def share_of(
    run: CalibrationRun,
    without: CalibrationRun,
    effect: str,
    imu_rate_hz: float,
    twin: Twin | None,
) -> tuple[Gap, Gap]:
    """The gap of ``effect``'s sensor on the final model without it (``without``: the final fit
    refitted from its estimate with the effect taken out, its map rebuilt) and with it (``run``,
    the final fit), both against the final fit's twin.

    An effect's own step measures its gap against what the model lacked when it was added; an
    effect added later that moves the same residuals (a gyro-to-IMU rotation bends the
    trajectory every LiDAR point is mapped with) leaves the earlier one's step little of the
    gap to close. This is what it closes with the others in.
    """
    sensor = CANDIDATES[effect][2]
    return _gap(without, sensor, imu_rate_hz, twin), _gap(run, sensor, imu_rate_hz, twin)


def _try_effect(
    evidence: object,
    run: CalibrationRun,
    run_twin: Twin | None,
    kept: tuple[str, ...],
    prepared: Prepared,
    cfg: CalibConfig,
    progress: Progress,
    timer: Timer,
    rate: float,
    spread: SharedSpread | None = None,
) -> DiagnosisStep:
    """Refit ``run`` with one more effect and judge it (BIC on the refit's data). With
    ``spread`` (``cfg`` then sets ``model.lidar_spread`` for the effect), the effect is one
    random effect across beams: its penalty is ``ln n + ln det(1 + s^2 I)`` instead of ``ln n``
    per coordinate (:mod:`licalib_cli.consistency.spread`)."""
    score = evidence.score  # type: ignore[attr-defined]
    name = score.name
    sensor = CANDIDATES[name][2]
    new_cfg = with_effects(cfg, (*kept, name))
    logger.info(
        "Diagnose: trying %s (score %.1f on %d degrees of freedom, p = %.2g).",
        name,
        score.statistic,
        score.rank,
        score.p_value,
    )
    start = replace(prepared.guess, state=run.state)
    new = fit_and_check(prepared, start, new_cfg, progress, timer, warm=True, rivals=True)
    samples = sensor_samples(run, sensor)
    log_n = math.log(max(samples, 2))
    ((ss, k),) = bic_terms(new, new_cfg, [(run.state, with_effects(cfg, kept))])
    delta_bic = ss + (k * log_n if spread is None else log_n + spread.log_det)
    moved = extrinsic_of(new.state).error_to(extrinsic_of(run.state))
    new_twin = twin_of(new, cfg)
    alone = float(getattr(evidence, "statistic_alone", score.statistic))
    statistic = alone if math.isfinite(alone) else float(score.statistic)
    step = DiagnosisStep(
        effect=name,
        statistic=statistic,
        dof=int(score.rank),
        p_value=float(chi2_sf(statistic, max(int(score.rank), 1))),
        delta_bic=float(delta_bic),
        kept=bool(delta_bic < 0.0),
        estimate=_estimate(new, name),
        held=_held(new, name),
        gap_before=_gap(run, sensor, rate, run_twin),
        gap_after=_gap(new, sensor, rate, new_twin),
        moved_translation_m=moved["translation_m"],
        moved_rotation_deg=moved["rotation_deg"],
        moved_time_offset_s=moved["time_offset_s"],
        before=run,
        after=new,
        after_twin=new_twin,
        bic_log_n=log_n,
    )
    logger.info(
        "Diagnose: %s%s %s (BIC %+.1f); %s gap %.3f -> %.3f; the extrinsic moved %.2f mm / "
        "%.4f deg / %.3f ms.",
        name,
        "" if spread is None else " as one spread across beams",
        "pays" if step.kept else "does not pay",
        delta_bic,
        sensor,
        step.gap_before.excess,
        step.gap_after.excess,
        1e3 * step.moved_translation_m,
        step.moved_rotation_deg,
        1e3 * step.moved_time_offset_s,
    )
    return step


def _refit_with(
    evidence: object,
    *,
    run: CalibrationRun,
    run_twin: Twin | None,
    kept: tuple[str, ...],
    prepared: Prepared,
    progress: Progress,
    timer: Timer,
    rate: float,
) -> Callable[[CalibConfig], DiagnosisStep]:
    """config -> ``evidence``'s effect refitted on ``run`` with that config
    (:func:`_try_effect`): how the sized refit and the walk's pieces try a configuration."""
    return partial(
        _try_effect,
        evidence,
        run,
        run_twin,
        kept,
        prepared,
        progress=progress,
        timer=timer,
        rate=rate,
    )


def diagnose(
    bag: object,
    cfg: CalibConfig,
    candidates: tuple[str, ...] | None = None,
    max_effects: int | None = None,
    progress: Progress | None = None,
) -> Diagnosis:
    """Find the effects the data show, add them one by one, and show each gap shrink.

    Args:
        bag: the bag (see :func:`licalib_cli.pipeline.calibrate`).
        cfg: the configuration; its ``model:`` section is ignored (the base model is fitted
            first and effects are added as the data ask).
        candidates: the effects considered (default: all of :data:`CANDIDATES`).
        max_effects: add at most this many (default: no limit).
        progress: progress sink.

    Returns:
        The base fit, the steps and the final fit.
    """
    from pathlib import Path

    progress = progress or NullProgress()
    allowed = tuple(candidates) if candidates else tuple(CANDIDATES)
    timer = Timer()
    cfg = cfg.model_copy(
        update={"model": cfg.model.model_copy(update={"lidar_spread": LidarSpreadSection()})}
    )
    base_cfg = with_effects(cfg, ())
    prepared: Prepared = prepare(Path(str(bag)), base_cfg, progress, timer)
    base_cfg = prepared.cfg
    cfg = with_knot_spacing(with_scan_pattern(cfg, prepared.pattern), prepared.cfg.spline.spacing_s)
    if prepared.pattern.non_repetitive:
        # a non-repetitive scanner's lines have no intrinsics of their own
        per_beam = [c for c in allowed if c in PER_BEAM_CANDIDATES]
        allowed = tuple(c for c in allowed if c not in PER_BEAM_CANDIDATES)
        if per_beam:
            logger.info(
                "The LiDAR is a non-repetitive scanner: %s do not apply.", ", ".join(per_beam)
            )
    rate = (len(prepared.rec.imu) - 1) / max(
        float(prepared.rec.imu.t_ns[-1] - prepared.rec.imu.t_ns[0]) * 1e-9, 1e-9
    )
    # a base model that lost its map (an error, or a fit on what was left of it) frees the
    # beams of a spinning LiDAR it held at nominal
    in_base: BeamsInBase | None = None
    beams = tuple(c for c in allowed if c in PER_BEAM_CANDIDATES)
    lost: str | None = None
    try:
        run = fit_and_check(prepared, prepared.guess, base_cfg, progress, timer, rivals=True)
        lost = collapsed_map(run.rounds) if beams_held(base_cfg) else None
    except MapLost as err:
        if not err.beams_held or not beams:
            raise
        lost = str(err)
    if lost is not None and beams:
        run, in_base = base_with_beams(prepared, base_cfg, beams, lost, progress, timer)
    with timer.stage("twin", progress):
        run_twin = twin_of(run, cfg)
    base, base_twin = run, run_twin
    # the beams a lost map made join the base model are kept as found; the selection and its
    # check backwards work on the effects added to that
    fixed = in_base.kept if in_base is not None else ()
    kept: tuple[str, ...] = fixed
    pool = CandidatePool(allowed)
    spread_log_det: dict[str, float] = {}
    steps: list[DiagnosisStep] = []
    while max_effects is None or len(kept) < max_effects:
        options, significant = pool.offered(run.effects)
        if not significant:
            break
        # The forward selection's first pick (conditional tests) when it is allowed here, else
        # the most significant on its own; a close rival (a per-beam range scale against a
        # range offset in a room seen at similar ranges, a gyro rotation against an
        # accelerometer misalignment) is refitted too and the BIC on the same data decides.
        picked = [e for e in significant if e.selected]
        best = picked[0] if picked else min(significant, key=lambda e: e.score.p_value)
        logger.debug(
            "Diagnose: shares of %s's score explained by the others: %s",
            best.score.name,
            ", ".join(
                f"{k} {v:.2f}"
                for k, v in sorted(best.explained_by.items(), key=lambda kv: -kv[1])
                if v >= 0.05
            )
            or "none above 0.05",
        )
        rivals = rivals_of(best, options)
        for r in rivals:
            logger.info(
                "Diagnose: %s is refitted as a rival of %s: freed with it, it explains %.0f %% "
                "of its score.",
                r.score.name,
                best.score.name,
                100.0 * best.explained_by.get(r.score.name, 0.0),
            )
        # each trial refitted once more expecting the size its test shows when the truncated
        # SVD held it at its scale (effect_size), before the rivals are compared: a walk held
        # at its scale on a 10 s window otherwise lost to a gyro scale that paid
        refit_of = partial(
            _refit_with,
            run=run,
            run_twin=run_twin,
            kept=kept,
            prepared=prepared,
            progress=progress,
            timer=timer,
            rate=rate,
        )
        trials, trial_cfgs = [], {}
        for e in [best, *rivals]:
            lost_to = pool.refitting(e.score.name)
            if lost_to is not None:
                logger.info(
                    "Diagnose: %s lost to %s as its rival; with %s in, its score is still %.1f "
                    "on %d degrees of freedom (p = %.2g): it is tried again.",
                    e.score.name,
                    lost_to,
                    lost_to,
                    e.score.statistic,
                    e.score.rank,
                    e.score.p_value,
                )
            refit = refit_of(e)
            trial, trial_cfgs[e.score.name] = sized_refit(refit(cfg), e.score, refit, cfg)
            if e is not best:
                share = best.explained_by.get(e.score.name, float("nan"))
                trial = replace(trial, rival_of=best.score.name, rival_share=share)
            if lost_to is not None:
                trial = replace(trial, retried_after=lost_to)
            trials.append(trial)
        trials = compare_rivals(
            trials,
            kept,
            with_sizes_of(cfg, trial_cfgs.values()),
            sensor_samples(run, trials[0].gap_before.sensor),
        )
        step = trials[
            pick_rival([t.delta_bic for t in trials], [t.rival_delta_bic for t in trials])
        ]
        cfg = trial_cfgs[step.effect]
        for t in trials:
            if t is not step:
                steps.append(replace(t, kept=False, rival_named=step.effect))
        evidence = next(e for e in [best, *rivals] if e.score.name == step.effect)
        spread = spread_worth_trying(step, evidence.score)
        if spread is not None:
            spread_cfg = with_spread(cfg, step.effect, spread.sigma)
            used = spread_cfg.model.lidar_spread.sigma_of(CANDIDATES[step.effect][1])
            assert used is not None
            shared = _try_effect(
                evidence, run, run_twin, kept, prepared, spread_cfg, progress, timer, rate, spread
            )
            if shared.kept:
                step = replace(
                    shared,
                    delta_bic=step.delta_bic,
                    not_told_apart=step.not_told_apart,
                    rival_delta_bic=step.rival_delta_bic,
                    spread=used,
                    spread_delta_bic=shared.delta_bic,
                    retried_after=step.retried_after,
                )
                cfg = spread_cfg
                spread_log_det[step.effect] = spread.log_det
            else:
                step = replace(step, spread=used, spread_delta_bic=shared.delta_bic)
        if step.kept and step.effect in WALKS and cfg.model.bias_walk_piece_s is None:
            step, cfg = finer_walk(step, refit_of(evidence), cfg)
        losers = [t.effect for t in trials if t.effect != step.effect]
        pool.decided(losers, step.effect, step.kept)
        steps.append(step)
        if step.kept:
            kept = (*kept, step.effect)
            assert step.after is not None
            run, run_twin = step.after, step.after_twin

    def fit_without(effects: tuple[str, ...], effect: str) -> CalibrationRun:
        # the model of ``effects`` but ``effect``, refitted from the current fit's estimate
        rest = tuple(e for e in effects if e != effect)
        start = replace(prepared.guess, state=without_effect(run.state, effect, base.state))
        return fit_and_check(
            prepared, start, with_effects(cfg, rest), progress, timer, warm=True, rivals=True
        )

    def refit_without(effects: tuple[str, ...], effect: str) -> None:
        nonlocal run, run_twin
        rest = tuple(e for e in effects if e != effect)
        logger.info(
            "Diagnose: %s explains nothing %s does not; refit without it.", effect, ", ".join(rest)
        )
        run = fit_without(effects, effect)
        run_twin = twin_of(run, cfg)

    dropped = drop_redundant(
        kept[len(fixed) :],
        lambda effects, tested: deltas_without(
            run, (*fixed, *effects), tested, base.state, cfg, spread_log_det
        ),
        lambda effects, effect: refit_without((*fixed, *effects), effect),
    )
    for effect, later, delta in dropped:
        i = next(i for i, t in enumerate(steps) if t.effect == effect and t.kept)
        steps[i] = replace(steps[i], kept=False, dropped_for=later, drop_delta_bic=delta)
        kept = tuple(e for e in kept if e != effect)
    for i, t in enumerate(steps):
        if wants_share(t, kept):
            with timer.stage("share", progress):
                without = fit_without(kept, t.effect)
            before, after = share_of(run, without, t.effect, rate, run_twin)
            steps[i] = replace(t, share_before=before, share_after=after)
            logger.info(
                "Diagnose: %s closed %.0f %% of the %s gap when it was added; with the other "
                "effects in, the gap is %.3f without it and %.3f with it.",
                t.effect,
                100 * t.shrink,
                t.gap_before.sensor,
                before.excess,
                after.excess,
            )
    # a noisy LiDAR's sigmas floored by refits with more noise, as calibrate's
    run = noise_spread(prepared, run, final_config(cfg, kept), progress, timer)
    progress.close()
    final_p = {e.score.name: float(e.score.p_value) for e in run.effects}
    steps = [
        replace(t, final_p_value=final_p.get(t.effect, float("nan"))) if not t.kept else t
        for t in steps
    ]
    return Diagnosis(
        base=base,
        steps=tuple(steps),
        final=run,
        effects_found=kept,
        base_twin=base_twin,
        final_twin=run_twin,
        not_shown=_not_shown(run, allowed, (*kept, *sorted(pool.tried))),
        config=final_config(cfg, kept),
        beams_in_base=in_base,
    )
