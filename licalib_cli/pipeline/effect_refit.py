"""How far an effect the data show beyond doubt moves the extrinsic, measured by a refit.

The checks predict each fixed effect's shift of the extrinsic from one Gauss-Newton step at the
final estimate (:func:`~licalib_cli.pipeline.fitcheck.effect_evidence`,
:mod:`licalib_cli.pipeline.effect_shift`). That step is the shift of a problem that is quadratic
around the estimate. An effect the data show beyond doubt is far outside that region: the final
map already absorbed part of it, and estimating it changes which points lie on which planes. On
a 20 s VLP-16 shake with per-beam horizontal offsets left out of the model and a 1.85 m lever
arm, the step said 7.5 mm while the estimate was 54.6 mm off; the sigmas it widened covered
the error at 3.8 of them only.

For the strongest effect the forward selection added whose score statistic per degree of freedom
is at least :data:`REFIT_STATISTIC_PER_DOF`, this stage refits the segment with that effect
estimated, from the final estimate (as ``diagnose`` tries an effect), and measures how far the
extrinsic moves. The effect's shift becomes, per coordinate, the larger of the step's and the
refit's, and the checks judge again with it: the sigmas cover the move, and the verdict says that
a refit moved the extrinsic by that much. The estimate stays the configured model's; adding the
effect to ``model:`` (or ``calibrate --model auto``) estimates it. A fit whose rounds did not
converge is not refitted: the refit would go on where its rounds stopped, and its move would be
theirs as much as the effect's (the verdict is a failure to converge anyway).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from licalib_cli.estimation import CalibrationState
from licalib_cli.pipeline.fitcheck import EffectEvidence
from licalib_cli.pipeline.round import extrinsic_of

__all__ = [
    "REFIT_STATISTIC_PER_DOF",
    "refit_shifts",
    "unmistakable",
    "unmistakable_ones",
    "with_move",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

REFIT_STATISTIC_PER_DOF = 100.0
"""An effect whose score statistic is at least this many times its degrees of freedom (each of
its directions about ten of its sigmas away from zero) gets its shift from a refit. On clean data
a statistic of 100 on one degree of freedom has a probability below 1e-20; the trust benchmark's
effects at the paper's sizes score from a few to a few thousand per degree of freedom."""


def unmistakable_ones(effects: Sequence[EffectEvidence]) -> list[EffectEvidence]:
    """The effects the forward selection added whose score per degree of freedom is at least
    :data:`REFIT_STATISTIC_PER_DOF`, the largest per degree of freedom first."""
    strong = [
        e
        for e in effects
        if e.selected
        and e.score.rank > 0
        and e.score.statistic >= REFIT_STATISTIC_PER_DOF * e.score.rank
    ]
    return sorted(strong, key=lambda e: -e.score.statistic / e.score.rank)


def unmistakable(effects: Sequence[EffectEvidence]) -> EffectEvidence | None:
    """The effect to refit with: the first of :func:`unmistakable_ones`; None when none is."""
    return next(iter(unmistakable_ones(effects)), None)


def with_move(e: EffectEvidence, move: F64) -> EffectEvidence:
    """``e`` whose shift is, per coordinate, the larger of its own and ``move`` (the refit's)."""
    move = np.asarray(move, dtype=np.float64)
    shift = np.where(np.abs(move) > np.abs(e.shift), move, e.shift)
    return replace(
        e,
        shift_translation_m=shift[:3].copy(),
        shift_rotation_rad=shift[3:6].copy(),
        shift_time_offset_s=float(shift[6]),
        refitted=True,
    )


def refit_shifts(
    effects: Sequence[EffectEvidence],
    state: CalibrationState,
    refit: Callable[[str], CalibrationState | None],
) -> tuple[EffectEvidence, ...] | None:
    """The effects with the unmistakable one's shift measured by a refit.

    Args:
        effects: the checks' score tests (selected ones first).
        state: the final estimate.
        refit: effect name -> the estimate of a refit with that effect estimated too (None when
            the refit failed).

    Returns:
        The effects in the same order, the refitted one replaced; None when no effect is
        unmistakable or its refit failed (the checks stand as they are).
    """
    top = unmistakable(effects)
    if top is None:
        return None
    name = top.score.name
    logger.info(
        "%s is unmistakable (score %.0f on %d degrees of freedom): refitting with it estimated "
        "to measure how far it moves the extrinsic.",
        name,
        top.score.statistic,
        top.score.rank,
    )
    after = refit(name)
    if after is None:
        return None
    move = extrinsic_of(state).moved_to(extrinsic_of(after))
    logger.info(
        "The refit with %s moved the extrinsic by %.2f mm / %.4f deg / %.3f ms (one step "
        "predicted %.2f mm / %.4f deg / %.3f ms).",
        name,
        1e3 * float(np.linalg.norm(move[:3])),
        float(np.degrees(np.linalg.norm(move[3:6]))),
        1e3 * abs(float(move[6])),
        1e3 * float(np.linalg.norm(top.shift[:3])),
        float(np.degrees(np.linalg.norm(top.shift[3:6]))),
        1e3 * abs(float(top.shift[6])),
    )
    return tuple(with_move(e, move) if e is top else e for e in effects)
