"""Effects the data show beyond doubt, estimated: how ``calibrate`` chooses its model.

The checks test every effect the model holds fixed (:func:`~licalib_cli.pipeline.fitcheck.
effect_evidence`). One whose score per degree of freedom is at least
:data:`~licalib_cli.pipeline.effect_refit.REFIT_STATISTIC_PER_DOF` (each of its directions about
ten of its sigmas from zero, probability below 1e-20 on data without it) is no longer a question
of model selection: holding it fixed biases the extrinsic, and the checks can only widen the
sigmas and warn. This stage refits the segment from the final estimate with every such effect
estimated too (as ``diagnose`` tries an effect) and keeps the refit when it pays its BIC on the
refit's data, converges and does not fail where the fit without them did not (else it tries
those of the strongest's sensor, then the strongest alone); then again on the refit's checks,
up to :data:`MAX_PASSES` refits. A LiDAR with errors in several of its per-beam intrinsics
shows them all at once, and adding one per refit took three refits (70-110 s on 10 s bags) to
add three of them. Each effect added is named in the result (``model.added``) and the
verdict's notes, with how far its refit moved the extrinsic.

A refit kept with several effects is checked backwards: those the others explain (shown only
by a fit that had not settled) are left out by one more refit
(:mod:`licalib_cli.pipeline.evident_prune`). Then an effect of the refit with a close rival,
one that could stand in for it (:func:`rival_in`), is refitted with the rival in its place and
the better on the same data kept, as ``diagnose`` weighs rivals; ``model.added`` names the
rival and whether the recording tells the two apart.

A fit whose rounds did not converge is tried too: an effect the model lacks (per-beam intrinsics
of a LiDAR, a gyro-to-IMU rotation) blurs the map and pulls the rounds one way and another, and
estimating it is often what lets them settle (an HDL-32 sinusoid with the simulator's intrinsic
errors failed as not converged 95 mm off; with the four effects it showed beyond doubt it
converged 4 mm off). Its refit is kept only when it converges, and a note says the fit without
the effects had not.

Effects the data show only below that bar stay with the checks (sigmas widened by their shift,
a warning naming them) and with ``diagnose`` / ``calibrate --model auto``, which compare the
model against twin recordings and weigh rivals. ``model.add_evident_effects: false`` (``calibrate
--model config``) keeps exactly the configured model.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import LicalibError
from licalib_cli.estimation import CalibrationState
from licalib_cli.pipeline import CalibrationRun, Prepared, fit_and_check
from licalib_cli.pipeline.checks import Finding
from licalib_cli.pipeline.diagnosis_step import CANDIDATES
from licalib_cli.pipeline.effect_models import bic_terms, sensor_samples, with_effect
from licalib_cli.pipeline.effect_refit import REFIT_STATISTIC_PER_DOF, unmistakable_ones
from licalib_cli.pipeline.evident_prune import redundant, without_all
from licalib_cli.pipeline.fitcheck import EffectEvidence
from licalib_cli.pipeline.rivals import rivals_of, weigh_refits
from licalib_cli.pipeline.round import extrinsic_of
from licalib_cli.pipeline.timing import Timer
from licalib_cli.pipeline.unchecked_priors import listed
from licalib_cli.progress import Progress
from licalib_cli.sections import AddedEffect

__all__ = [
    "MAX_PASSES",
    "Evident",
    "add_evident",
    "addable",
    "added_note",
    "bic_change",
    "estimating",
    "refit_groups",
    "rival_in",
    "stands_in",
    "statistic_of",
    "with_added",
    "with_rival",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

MAX_PASSES = 2
"""At most this many refits add effects (each costs a fit and its checks)."""


@dataclass(frozen=True)
class Evident:
    """The outcome of :func:`add_evident`.

    Attributes:
        run: the calibration of the model arrived at (``run`` itself when nothing was added).
        cfg: that model's configuration.
        added: the effects added, in order (those of one refit share its BIC change and move).
        declined: the strongest effect refitted but not added (the refit did not pay its BIC or
            did not converge, or it failed where the fit without it did not) and that refit's
            estimate, which measures how far it moves the extrinsic; None when every refit was
            kept or none was tried.
        notes: why an effect shown beyond doubt was not added, when the user would otherwise
            be told to estimate it (its refit's verdict failed); and that the rounds converged
            only with the effects added.
    """

    run: CalibrationRun
    cfg: CalibConfig
    added: tuple[AddedEffect, ...] = ()
    declined: tuple[str, CalibrationState] | None = None
    notes: tuple[str, ...] = ()


def added_note(added: Sequence[AddedEffect]) -> str:
    """The verdict's note on the effects one refit added."""
    a = added[0]
    tests = " and ".join(
        f"{' or '.join((e.effect, *e.not_told_apart))} (score test {e.statistic:.0f} on "
        f"{e.dof} degrees of freedom)"
        for e in added
    )
    them = "it was" if len(added) == 1 else "they were"
    return (
        f"The data showed {tests} beyond doubt; {them} estimated (BIC {a.delta_bic:+.0f}), which "
        f"moved the extrinsic by {1e3 * a.moved_translation_m:.2f} mm / "
        f"{a.moved_rotation_deg:.4f} deg / {1e3 * abs(a.moved_time_offset_s):.3f} ms. The "
        "resolved config estimates "
        f"{'it' if len(added) == 1 else 'them'}; calibrate --model config keeps to the config's "
        "model."
    )


def add_evident(
    prepared: Prepared,
    run: CalibrationRun,
    cfg: CalibConfig,
    progress: Progress,
    timer: Timer,
) -> Evident:
    """Estimate the effects ``run``'s checks show beyond doubt.

    Every such effect of the checks' forward selection is added in one refit (when that is not
    kept, those of the strongest's sensor are tried, then the strongest alone:
    :func:`refit_groups`); then the same on the refit's checks, up to :data:`MAX_PASSES` refits
    kept.

    Args:
        prepared: the segment, noise and initial guess.
        run: the calibration of ``cfg``'s model.
        cfg: the configuration.
        progress: progress sink.
        timer: stage timer (the refits' rounds and checks add to its stages).

    Returns:
        The model arrived at, its calibration and what was added (module docstring).
    """
    added: list[AddedEffect] = []
    stuck = run.checks.exit_status == "not converged"
    declined: tuple[str, CalibrationState] | None = None
    notes: tuple[str, ...] = ()
    stage_notes: list[str] = []
    passes = 0
    while passes < MAX_PASSES:
        strong = addable(run.checks.effects, cfg)
        if not strong:
            break
        kept = outcome = None
        for group in refit_groups(strong):
            outcome = _refit(prepared, run, cfg, group, progress, timer)
            if outcome is None:  # the refit failed: the effects stay held
                break
            new, new_cfg, delta_bic = outcome
            # an effect that takes away what the data determine (a gyro rotation beside the
            # extrinsic rotation on a shake that hardly tilted) is not added: the fit without it
            # stands, its shift in the sigmas
            lost = new.checks.exit_status == "fail" and run.checks.exit_status == "ok"
            if _keeps(new, delta_bic):
                kept = (group, new, new_cfg, delta_bic)
                break
            last = (group[0].score.name, new.state)
        if kept is None:
            if outcome is not None:
                declined = last
                notes = (_failed_note(group, new),) if lost else ()
            break
        # effects the others explain are left out (shown only by a fit that had not settled)
        kept, left_out = _pruned(prepared, run, cfg, kept, progress, timer)
        if left_out:
            stage_notes.append(left_out)
        # a close rival of the refit's effects is refitted in its place, the better kept
        pair = rival_in(kept[0], run.checks.effects, cfg)
        weighed = (
            None if pair is None else _weigh_rival(prepared, run, cfg, kept, pair, progress, timer)
        )
        if weighed is not None:
            kept = weighed.kept
            stage_notes.append(weighed.note)
        group, new, new_cfg, delta_bic = kept
        move = extrinsic_of(run.state).moved_to(extrinsic_of(new.state))
        ours = [
            AddedEffect(
                effect=e.score.name,
                statistic=statistic_of(e),
                dof=int(e.score.rank),
                delta_bic=delta_bic,
                moved_translation_m=float(np.linalg.norm(move[:3])),
                moved_rotation_deg=float(np.degrees(np.linalg.norm(move[3:6]))),
                moved_time_offset_s=float(move[6]),
                refit=passes + 1,
            )
            for e in group
        ]
        added += ours if weighed is None else [weighed.on(a) for a in ours]
        logger.info(
            "%s estimated (BIC %+.1f): the extrinsic moved %.2f mm / %.4f deg / %.3f ms.",
            ", ".join(e.score.name for e in group),
            delta_bic,
            1e3 * float(np.linalg.norm(move[:3])),
            float(np.degrees(np.linalg.norm(move[3:6]))),
            1e3 * float(move[6]),
        )
        run, cfg = new, new_cfg
        passes += 1
    notes = (*stage_notes, *notes)
    if stuck and added:
        notes = (_settled_note(added), *notes)
    return Evident(run, cfg, tuple(added), declined, notes)


def _keeps(refit: CalibrationRun, delta_bic: float) -> bool:
    """Whether a refit may be kept: its rounds converged, its verdict did not fail and it paid
    its BIC."""
    return refit.checks.exit_status not in ("not converged", "fail") and delta_bic < 0.0


def _pruned(
    prepared: Prepared,
    run: CalibrationRun,
    cfg: CalibConfig,
    kept: tuple[list[EffectEvidence], CalibrationRun, CalibConfig, float],
    progress: Progress,
    timer: Timer,
) -> tuple[tuple[list[EffectEvidence], CalibrationRun, CalibConfig, float], str]:
    """``kept`` refitted without the effects the others explain
    (:func:`~licalib_cli.pipeline.evident_prune.redundant`) when that refit pays its BIC and
    converges, with the note that says so; ``kept`` itself and no note otherwise."""
    group, new, new_cfg, _ = kept
    names = [e.score.name for e in group]
    try:
        out, deltas = redundant(
            new,
            new_cfg,
            names,
            run.state,
            lambda drop: estimating(cfg, [n for n in names if n not in drop]),
        )
    except LicalibError as exc:
        logger.warning("Taking the effects out one by one failed (%s); all are kept.", exc)
        return kept, ""
    if not out:
        return kept, ""
    rest = [e for e in group if e.score.name not in out]
    outcome = _refit(
        prepared, run, cfg, rest, progress, timer, state=without_all(new.state, out, run.state)
    )
    if outcome is None:
        return kept, ""
    r_new, r_cfg, r_delta = outcome
    if not _keeps(r_new, r_delta):
        logger.info("The refit without %s did not pay or settle; all are kept.", ", ".join(out))
        return kept, ""
    one = len(out) == 1
    note = (
        f"The fit before this refit also showed {listed(out)}, but with "
        f"{listed([e.score.name for e in rest])} estimated "
        f"{'it' if one else 'they'} explained nothing more (BIC "
        + ", ".join(f"{deltas[e]:+.0f}" for e in out)
        + f" with {'it' if one else 'each'} than without); "
        f"{'it was' if one else 'they were'} left out."
    )
    return (rest, r_new, r_cfg, r_delta), note


@dataclass(frozen=True)
class _Weighed:
    """A refit's leading effect weighed against its close rival (:func:`_weigh_rival`).

    Attributes:
        kept: the refit to keep (group, run, configuration, BIC change against the fit without
            them): the rival's when it fit the same data better.
        winner: the effect of the two estimated.
        loser: the other.
        delta_bic: the winner's BIC minus the loser's on the same data (at most 0).
        alike: the recording does not tell the two apart.
        note: what the verdict's notes say about it.
    """

    kept: tuple[list[EffectEvidence], CalibrationRun, CalibConfig, float]
    winner: str
    loser: str
    delta_bic: float
    alike: bool
    note: str

    def on(self, added: AddedEffect) -> AddedEffect:
        """``added`` naming the rival when it is the winner."""
        return with_rival(added, self.winner, self.loser, self.delta_bic, self.alike)


def with_rival(
    added: AddedEffect, winner: str, loser: str, delta_bic: float, alike: bool
) -> AddedEffect:
    """``added`` naming ``loser`` as its rival when it is ``winner``, the close rival's
    comparison on the same data (``delta_bic``, at most 0) and whether the recording tells the
    two apart; ``added`` itself for another effect."""
    if added.effect != winner:
        return added
    return replace(
        added,
        rival=loser,
        rival_delta_bic=delta_bic,
        not_told_apart=(loser,) if alike else (),
    )


def statistic_of(e: EffectEvidence) -> float:
    """``e``'s score test as the checks' forward selection added it, or on its own when it was
    not added (a rival in a refit's place: its test with the leader freed says nothing of
    it)."""
    return float(e.score.statistic if e.selected else e.statistic_alone)


def rival_in(
    group: Sequence[EffectEvidence], effects: Sequence[EffectEvidence], cfg: CalibConfig
) -> tuple[EffectEvidence, EffectEvidence] | None:
    """The first effect of ``group`` (strongest first) with a close rival among ``effects``
    that ``cfg`` does not estimate and the group does not hold, and that rival; None when none
    has one.

    A rival is one ``diagnose`` would refit beside it (:func:`~licalib_cli.pipeline.rivals.
    rivals_of`: freed with it, it explains most of its score) that could stand in for it
    (:func:`stands_in`). Turning about one axis ``u``, a gyro measures only ``M u`` of its 3x3
    error ``M``: with the IMU mounted obliquely on a car that drove figure-8s, a per-axis gyro
    scale explained 99.9 % of a gyro-to-IMU rotation's score (6496 against 6494 on 3 degrees of
    freedom), both refits paid (BIC -5964 and -5982), and the strongest alone would have named
    the scale.
    """
    names = {e.score.name for e in group}
    options = [
        e
        for e in effects
        if e.score.name not in names
        and e.score.rank > 0
        and e.score.name in CANDIDATES
        and with_effect(cfg, e.score.name) is not cfg
    ]
    for e in group:
        rivals = [r for r in rivals_of(e, options) if stands_in(e, r)]
        if rivals:
            return e, rivals[0]
    return None


def stands_in(leader: EffectEvidence, rival: EffectEvidence) -> bool:
    """Whether ``rival`` could stand in for ``leader``: what is left of the leader's score with
    the rival freed (``(1 - share) x`` its score, :attr:`~licalib_cli.pipeline.fitcheck.
    EffectEvidence.explained_by`) is below :data:`~licalib_cli.pipeline.effect_refit.
    REFIT_STATISTIC_PER_DOF` per degree of freedom. Were the rival the effect in the data, that
    rest would be noise; one left beyond doubt says the rival cannot explain what the leader
    does, and its refit is not needed to tell. On three single-effect bags (10 s, VLP-16 and
    OS1-64) a per-beam range scale left 8 % of a range offset's score (106620 on 64 degrees of
    freedom), a vertical offset 14 % of an elevation's (100131 on 63), an azimuth 7 % of a
    horizontal offset's (61469 on 15); each rival's refit, 9-13 s more a run, fit the same data
    worse by a BIC of 17285, 17672 and 3409. The gyro scale above left 0.1 %."""
    share = leader.explained_by.get(rival.score.name, 0.0)
    left = (1.0 - share) * float(leader.statistic_alone)
    return bool(left < REFIT_STATISTIC_PER_DOF * max(leader.score.rank, 1))


def _weigh_rival(
    prepared: Prepared,
    run: CalibrationRun,
    cfg: CalibConfig,
    kept: tuple[list[EffectEvidence], CalibrationRun, CalibConfig, float],
    pair: tuple[EffectEvidence, EffectEvidence],
    progress: Progress,
    timer: Timer,
) -> _Weighed | None:
    """The refit ``kept`` against one with ``pair``'s rival in place of its leader, compared on
    the same data (:func:`~licalib_cli.pipeline.rivals.weigh_refits`) as ``diagnose`` compares
    rivals; None when the rival's refit failed, did not converge or did not pay (``kept``
    stands)."""
    group, new, new_cfg, _ = kept
    leader, rival = pair
    a, b = leader.score.name, rival.score.name
    logger.info(
        "%s could stand in for %s (freed with it, it explains %.0f %% of its score; on their "
        "own, scores %.0f and %.0f on %d and %d degrees of freedom); refitting with %s in its "
        "place.",
        b,
        a,
        100.0 * leader.explained_by.get(b, 0.0),
        rival.statistic_alone,
        leader.statistic_alone,
        rival.score.rank,
        leader.score.rank,
        b,
    )
    other = [rival if e is leader else e for e in group]
    outcome = _refit(prepared, run, cfg, other, progress, timer)
    if outcome is None:
        return None
    r_new, r_cfg, r_delta = outcome
    if not _keeps(r_new, r_delta):
        logger.info("%s does not stand in for %s here; %s stays.", b, a, a)
        return None
    b_minus_a, alike = weigh_refits(run, (a, new, new_cfg), (b, r_new, r_cfg))
    if b_minus_a < 0.0:
        winner, loser, won, lost = b, a, (other, r_new, r_cfg, r_delta), new
    else:
        winner, loser, won, lost = a, b, kept, r_new
    diff = extrinsic_of(won[1].state).moved_to(extrinsic_of(lost.state))
    delta = -abs(b_minus_a)
    note = _rival_note(winner, loser, delta, alike, diff)
    return _Weighed(won, winner, loser, delta, alike, note)


def _rival_note(winner: str, loser: str, delta_bic: float, alike: bool, diff: F64) -> str:
    """The verdict's note on an effect estimated in place of, or against, its close rival."""
    apart = (
        f"{1e3 * float(np.linalg.norm(diff[:3])):.2f} mm / "
        f"{float(np.degrees(np.linalg.norm(diff[3:6]))):.4f} deg / "
        f"{1e3 * abs(float(diff[6])):.3f} ms"
    )
    if alike:
        return (
            f"This recording does not tell {winner} from {loser}: with either estimated, the "
            f"other's score test is no longer significant. Both were refitted; {winner} fit "
            f"the same data better (BIC {delta_bic:+.0f}) and is estimated, and the two refits' "
            f"extrinsics differ by {apart}. Its numbers stand for an effect either one explains, "
            f"not for {winner} alone; a motion that excites more axes tells them apart, and "
            "licalib diagnose shows both."
        )
    return (
        f"{loser} could stand in for {winner}; refitted in its place, it fit the same data "
        f"worse (BIC {-delta_bic:+.0f}), and the data tell the two apart."
    )


def refit_groups(
    strong: Sequence[EffectEvidence], *, alone: bool = True
) -> list[list[EffectEvidence]]:
    """The groups of ``strong`` (strongest first) to refit with, in turn, until one is kept:
    all of them; those of the strongest's sensor (an IMU effect that the recording cannot tell
    from the extrinsic rotation, such as a gyro-to-IMU rotation on a shake that hardly tilted,
    would otherwise keep a LiDAR's per-beam errors out with it); with ``alone``, the strongest
    alone. Each group once."""
    own = [e for e in strong if e.sensor == strong[0].sensor]
    tries = [list(strong), own, list(strong[:1])] if alone else [list(strong), own]
    names = [[e.score.name for e in g] for g in tries]
    return [g for k, g in enumerate(tries) if names[k] not in names[:k]]


def addable(effects: Sequence[EffectEvidence], cfg: CalibConfig) -> list[EffectEvidence]:
    """The effects shown beyond doubt (:func:`~licalib_cli.pipeline.effect_refit.
    unmistakable_ones`, the strongest per degree of freedom first) whose blocks ``cfg`` does
    not estimate yet (an estimated one shows only where the truncated SVD held it)."""
    return [e for e in unmistakable_ones(effects) if with_effect(cfg, e.score.name) is not cfg]


def _refit(
    prepared: Prepared,
    run: CalibrationRun,
    cfg: CalibConfig,
    group: Sequence[EffectEvidence],
    progress: Progress,
    timer: Timer,
    state: CalibrationState | None = None,
) -> tuple[CalibrationRun, CalibConfig, float] | None:
    """``run`` refitted from its estimate (or ``state``) with ``group`` estimated too: the
    refit, its configuration and its BIC change on its data (the penalty at the largest
    sensor's sample count among the group's); None when the refit failed."""
    names = [e.score.name for e in group]
    logger.info(
        "Shown beyond doubt: %s; refitting with %s estimated.",
        ", ".join(
            f"{e.score.name} (score {statistic_of(e):.0f} on {e.score.rank} degrees of freedom)"
            for e in group
        ),
        "it" if len(group) == 1 else "them",
    )
    new_cfg = estimating(cfg, names)
    start = replace(prepared.guess, state=run.state if state is None else state)
    try:
        new = fit_and_check(prepared, start, new_cfg, progress, timer, warm=True, rivals=True)
        delta_bic = bic_change(new, new_cfg, run, cfg, names)
    except LicalibError as exc:
        logger.warning("The refit with %s failed (%s); held fixed.", ", ".join(names), exc)
        return None
    reasons = new.checks.verdict.reasons
    logger.info(
        "Estimating %s: BIC %+.1f%s.",
        ", ".join(names),
        delta_bic,
        {
            "not converged": ", the rounds did not converge",
            "fail": f", the verdict failed ({reasons[0] if reasons else 'no reason given'})",
        }.get(new.checks.exit_status, ""),
    )
    return new, new_cfg, delta_bic


def estimating(cfg: CalibConfig, effects: Sequence[str]) -> CalibConfig:
    """``cfg`` whose ``model:`` section estimates ``effects`` too."""
    for name in effects:
        cfg = with_effect(cfg, name)
    return cfg


def bic_change(
    new: CalibrationRun,
    new_cfg: CalibConfig,
    run: CalibrationRun,
    cfg: CalibConfig,
    effects: Sequence[str],
) -> float:
    """The BIC change from ``run`` (model ``cfg``) to ``new`` (``new_cfg``, estimating
    ``effects`` too) on ``new``'s data: the drop in the sum of squares plus ``ln n`` per
    parameter added, ``n`` the largest sample count of the effects' sensors."""
    ((ss, k),) = bic_terms(new, new_cfg, [(run.state, cfg)])
    samples = max(sensor_samples(run, CANDIDATES[name][2]) for name in effects)
    return float(ss + k * math.log(max(samples, 2)))


def _failed_note(group: Sequence[EffectEvidence], refit: CalibrationRun) -> str:
    """Why the effects of ``group`` stay held: estimating them made the verdict fail."""
    names = ", ".join(e.score.name for e in group)
    reasons = refit.checks.verdict.reasons
    why = reasons[0].split(": ")[0].rstrip(".") if reasons else "The verdict failed"
    why = why[:1].lower() + why[1:]
    return (
        f"The data show {names} beyond doubt, but estimating "
        f"{'it' if len(group) == 1 else 'them'} failed the calibration ({why}); "
        f"{'it stays' if len(group) == 1 else 'they stay'} held fixed, "
        "the shift in the sigmas."
    )


def _settled_note(added: Sequence[AddedEffect]) -> str:
    """Why the effects ``added`` to a fit whose rounds did not converge matter."""
    names = ", ".join(a.effect for a in added)
    them = "it" if len(added) == 1 else "them"
    return (
        f"Without {names} the rounds did not converge (the model lacked what the data show, "
        f"which pulled the estimate one way and another); with {them} estimated they converged."
    )


def with_added(
    run: CalibrationRun, added: tuple[AddedEffect, ...], notes: tuple[str, ...] = ()
) -> CalibrationRun:
    """``run`` whose result names ``added`` and whose findings note each, and ``notes`` (after
    the last stage that assembles the result again)."""
    result = run.result
    if added:
        assert result.model is not None
        result = replace(result, model=replace(result.model, added=added))
    refits = sorted({a.refit for a in added})
    found = tuple(Finding("note", added_note([a for a in added if a.refit == k])) for k in refits)
    found += tuple(Finding("note", n) for n in notes)
    checks = replace(run.checks, findings=(*found, *run.checks.findings))
    return replace(run, result=result, checks=checks)
