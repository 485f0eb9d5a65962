"""Effects a window shows beyond doubt, estimated in every window (``calibrate --segments``).

The joint problem of several segments estimates one model, so its windows are first calibrated
with exactly the configured one (:mod:`~licalib_cli.pipeline.segment_runs`). An effect any of
them shows beyond doubt (a score test of at least
:data:`~licalib_cli.pipeline.effect_refit.REFIT_STATISTIC_PER_DOF` per degree of freedom, picked
by its forward selection; a window whose rounds did not converge counts too, such an effect
often being why) is a property of the sensors, not of a window: as for one segment
(:mod:`~licalib_cli.pipeline.evident`), every window is then refitted from its own estimate with
all such effects estimated, and the refits are kept when together they pay their BIC (the sum
of the windows' changes), every one converged and none failed where its fit without them did
not; else those of the strongest effect's sensor are tried. Of several effects kept, those the
others explain (their BIC summed over the windows is lower without them, on the refits' data:
:mod:`~licalib_cli.pipeline.evident_prune`) are left out by one more refit of the windows, kept
on the same terms. An effect kept with a close rival, one that could stand in for it in the
window that showed it most (:func:`~licalib_cli.pipeline.evident.rival_in`), is weighed as for
one segment: every window is refitted with the rival in its place, and the two are compared on
the same data in every window (:func:`~licalib_cli.pipeline.rivals.weigh_refits`, summed); the
rival is estimated instead when it fit better, and the two are reported as not told apart when
no window separates them (:func:`~licalib_cli.pipeline.rivals.refits_alike` in each). The joint
calibration then estimates that model.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.errors import LicalibError
from licalib_cli.pipeline import CalibrationRun, Prepared, fit_and_check
from licalib_cli.pipeline.backward import bic_deltas
from licalib_cli.pipeline.effect_refit import unmistakable_ones
from licalib_cli.pipeline.evident import (
    addable,
    bic_change,
    estimating,
    refit_groups,
    rival_in,
    statistic_of,
    with_rival,
)
from licalib_cli.pipeline.evident_prune import joint_delta, left_out
from licalib_cli.pipeline.fitcheck import EffectEvidence
from licalib_cli.pipeline.rivals import weigh_refits
from licalib_cli.pipeline.round import extrinsic_of
from licalib_cli.pipeline.scan_pattern import with_scan_pattern
from licalib_cli.pipeline.segments import _with_range
from licalib_cli.pipeline.timing import Timer
from licalib_cli.progress import Progress
from licalib_cli.sections import AddedEffect

__all__ = ["WindowsEvident", "add_evident_to_windows"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class WindowsEvident:
    """The windows refitted with the effects added.

    Attributes:
        runs: each window's calibration of the model with them, in the windows' order.
        cfg: that model's configuration (the bag's range as given).
        added: the effects added: each with the largest score per degree of freedom a window
            showed, the windows' summed BIC change and the largest move of a window's extrinsic;
            empty when the refits were not kept.
    """

    runs: tuple[CalibrationRun, ...]
    cfg: CalibConfig
    added: tuple[AddedEffect, ...]


def add_evident_to_windows(
    bag: Path,
    runs: Sequence[CalibrationRun],
    windows: Sequence[tuple[float, float]],
    cfg: CalibConfig,
    progress: Progress,
) -> WindowsEvident | None:
    """Refit every window with the effects any of them shows beyond doubt (module docstring);
    None when none does. When the refits with all of them are not kept, those of the strongest's
    sensor are tried (as for one segment, :func:`~licalib_cli.pipeline.evident.add_evident`).
    When neither is kept the windows' fits stand: ``runs`` and ``cfg`` as given, nothing
    added."""
    strongest: dict[str, EffectEvidence] = {}  # per effect, the window's largest per dof
    for run in runs:
        for e in addable(run.checks.effects, cfg):
            name = e.score.name
            if name not in strongest or _per_dof(e) > _per_dof(strongest[name]):
                strongest[name] = e
    if not strongest:
        return None
    for group in refit_groups(unmistakable_ones(list(strongest.values())), alone=False):
        names = [e.score.name for e in group]
        kept = _refit_windows(bag, runs, windows, cfg, names, progress)
        if kept is None:
            continue
        out = _redundant(runs, kept[0], windows, cfg, names)
        if out:
            rest = [n for n in names if n not in out]
            again = _refit_windows(bag, runs, windows, cfg, rest, progress)
            if again is not None:
                logger.info(
                    "%s left out: with %s estimated, %s explained nothing more.",
                    ", ".join(out),
                    ", ".join(rest),
                    "it" if len(out) == 1 else "they",
                )
                kept, group = again, [e for e in group if e.score.name in rest]
        pair = _rival_pair(runs, group, cfg)
        weighed = (
            None
            if pair is None
            else _weigh_rival(bag, runs, windows, cfg, (group, kept), pair, progress)
        )
        if weighed is not None:
            group, kept = weighed.group, weighed.kept
        new_runs, new_cfg, delta_bic, largest = kept
        added = tuple(
            AddedEffect(
                effect=e.score.name,
                statistic=statistic_of(e),
                dof=int(e.score.rank),
                delta_bic=delta_bic,
                moved_translation_m=float(np.linalg.norm(largest[:3])),
                moved_rotation_deg=float(np.degrees(np.linalg.norm(largest[3:6]))),
                moved_time_offset_s=float(largest[6]),
            )
            for e in group
        )
        if weighed is not None:
            added = tuple(
                with_rival(a, weighed.winner, weighed.loser, weighed.delta_bic, weighed.alike)
                for a in added
            )
        return WindowsEvident(tuple(new_runs), new_cfg, added)
    return WindowsEvident(tuple(runs), cfg, ())


def _redundant(
    runs: Sequence[CalibrationRun],
    refits: Sequence[CalibrationRun],
    windows: Sequence[tuple[float, float]],
    cfg: CalibConfig,
    names: Sequence[str],
) -> tuple[str, ...]:
    """The effects of ``names`` the others explain in the windows' ``refits`` (each
    effect's BIC difference summed over the windows; :func:`~licalib_cli.pipeline.
    evident_prune.left_out`); empty for fewer than two, or when a re-solve failed."""
    if len(names) < 2:
        return ()

    def model(run: CalibrationRun, a: float, b: float, drop: Sequence[str]) -> CalibConfig:
        return _window_model(estimating(cfg, [n for n in names if n not in drop]), run, a, b)

    parts = [
        (refit, model(run, a, b, ()), run.state, lambda d, r=run, a=a, b=b: model(r, a, b, d))
        for run, refit, (a, b) in zip(runs, refits, windows, strict=True)
    ]
    try:
        deltas = {n: 0.0 for n in names}
        for refit, refit_cfg, start, without in parts:
            for n, d in bic_deltas(refit, refit_cfg, names, start, without).items():
                deltas[n] += d
        return left_out(
            names,
            deltas,
            lambda out: sum(joint_delta(r, c, out, s, w) for r, c, s, w in parts),
        )
    except LicalibError as exc:
        logger.warning("Taking the effects out one by one failed (%s); all are kept.", exc)
        return ()


_Refits = tuple[list[CalibrationRun], CalibConfig, float, np.ndarray]
"""The windows refitted with a model (:func:`_refit_windows`): the refits, the model's
configuration, the summed BIC change and the largest move of a window's extrinsic."""


@dataclass(frozen=True)
class _Weighed:
    """The windows' refits kept after a leading effect was weighed against its close rival.

    Attributes:
        group: the effects of the refits kept (the rival in the leader's place when it won).
        kept: those refits.
        winner: the effect of the two estimated.
        loser: the other.
        delta_bic: the winner's BIC minus the loser's on the same data, summed over the
            windows (at most 0).
        alike: no window tells the two apart.
    """

    group: list[EffectEvidence]
    kept: _Refits
    winner: str
    loser: str
    delta_bic: float
    alike: bool


def _rival_pair(
    runs: Sequence[CalibrationRun], group: Sequence[EffectEvidence], cfg: CalibConfig
) -> tuple[EffectEvidence, EffectEvidence] | None:
    """The first effect of ``group`` with a close rival in the window that showed it most (the
    window whose checks hold its evidence), and that rival (:func:`~licalib_cli.pipeline.
    evident.rival_in`, the group's other effects excluded); None when none has one."""
    names = {e.score.name for e in group}
    for e in group:
        own = next((r for r in runs if any(x is e for x in r.checks.effects)), None)
        if own is None:
            continue
        options = [x for x in own.checks.effects if x.score.name not in names]
        pair = rival_in([e], options, cfg)
        if pair is not None:
            return pair
    return None


def _weigh_rival(
    bag: Path,
    runs: Sequence[CalibrationRun],
    windows: Sequence[tuple[float, float]],
    cfg: CalibConfig,
    ours: tuple[list[EffectEvidence], _Refits],
    pair: tuple[EffectEvidence, EffectEvidence],
    progress: Progress,
) -> _Weighed | None:
    """The windows' refits ``ours`` against refits with ``pair``'s rival in place of its
    leader, compared on the same data in every window and summed; None when the rival's refits
    were not kept (one failed, did not converge, or together they did not pay) or a
    comparison failed (``ours`` stands)."""
    group, kept = ours
    leader, rival = pair
    a, b = leader.score.name, rival.score.name
    logger.info(
        "%s could stand in for %s (freed with it, it explains %.0f %% of its score in the "
        "segment that showed it most); refitting every segment with %s in its place.",
        b,
        a,
        100.0 * leader.explained_by.get(b, 0.0),
        b,
    )
    other = [rival if e is leader else e for e in group]
    theirs = _refit_windows(bag, runs, windows, cfg, [e.score.name for e in other], progress)
    if theirs is None:
        logger.info("%s does not stand in for %s here; %s stays.", b, a, a)
        return None
    b_minus_a, alike = 0.0, True
    try:
        for run, x, y, (s, t) in zip(runs, kept[0], theirs[0], windows, strict=True):
            ours_k = (a, x, _window_model(kept[1], run, s, t))
            theirs_k = (b, y, _window_model(theirs[1], run, s, t))
            delta, alike_here = weigh_refits(run, ours_k, theirs_k)
            b_minus_a, alike = b_minus_a + delta, alike and alike_here
    except LicalibError as exc:
        logger.warning("Comparing %s with %s failed (%s); %s stays.", a, b, exc, a)
        return None
    logger.info(
        "%s against %s on the same data, summed over the segments: BIC %+.1f%s.",
        b,
        a,
        b_minus_a,
        "; no segment tells them apart" if alike else "",
    )
    if b_minus_a < 0.0:
        return _Weighed(other, theirs, b, a, b_minus_a, alike)
    return _Weighed(list(group), kept, a, b, -b_minus_a, alike)


def _window_model(model: CalibConfig, run: CalibrationRun, a: float, b: float) -> CalibConfig:
    """``model`` for the window ``a``-``b`` s of ``run``: its range and scan pattern."""
    return _with_range(with_scan_pattern(model, run.pattern), a, b - a)


def _per_dof(e: EffectEvidence) -> float:
    return float(e.score.statistic) / int(e.score.rank)


def _refit_windows(
    bag: Path,
    runs: Sequence[CalibrationRun],
    windows: Sequence[tuple[float, float]],
    cfg: CalibConfig,
    names: Sequence[str],
    progress: Progress,
) -> _Refits | None:
    """Every window refitted from its estimate with ``names`` estimated too: the refits, their
    configuration, the summed BIC change and the largest move of a window's extrinsic; None
    when a refit failed, did not converge or failed the verdict where the window's fit did not,
    or when together they do not pay."""
    new_cfg = estimating(cfg, names)
    logger.info(
        "Shown beyond doubt by a segment: %s; refitting every segment with %s estimated.",
        ", ".join(names),
        "it" if len(names) == 1 else "them",
    )
    timer = Timer()
    new_runs, delta_bic, moves = [], 0.0, []
    for run, (a, b) in zip(runs, windows, strict=True):
        assert run.segment is not None
        window_cfg = _window_model(new_cfg, run, a, b)
        prepared = Prepared(bag, run.segment, run.noise, run.initial, run.pattern, window_cfg)
        try:
            new = fit_and_check(
                prepared,
                replace(run.initial, state=run.state),
                window_cfg,
                progress,
                timer,
                warm=True,
            )
            change = bic_change(new, window_cfg, run, _with_range(cfg, a, b - a), names)
        except LicalibError as exc:
            logger.warning("The refit of segment %.0f-%.0f s failed (%s).", a, b, exc)
            return None
        lost = new.checks.exit_status == "fail" and run.checks.exit_status == "ok"
        if new.checks.exit_status == "not converged" or lost:
            logger.info(
                "Segment %.0f-%.0f s %s with %s estimated.",
                a,
                b,
                "did not converge" if not lost else "failed",
                ", ".join(names),
            )
            return None
        delta_bic += change
        moves.append(extrinsic_of(run.state).moved_to(extrinsic_of(new.state)))
        new_runs.append(new)
    if not delta_bic < 0.0:
        logger.info("Estimating %s does not pay (BIC %+.1f).", ", ".join(names), delta_bic)
        return None
    largest = max(moves, key=lambda m: float(np.linalg.norm(m[:3])))
    logger.info(
        "%s estimated in every segment (BIC %+.1f); a segment's extrinsic moved up to %.2f mm.",
        ", ".join(names),
        delta_bic,
        1e3 * float(np.linalg.norm(largest[:3])),
    )
    return new_runs, new_cfg, delta_bic, largest
