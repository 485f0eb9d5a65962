"""The backward check of the forward selection (:mod:`licalib_cli.pipeline.diagnose`, step 5).

An effect added early may explain nothing that the effects added after it do not: each kept
effect but the last is taken out on the final fit's data (reset to its starting value, the rest
re-solved), and when the BIC is lower without it, it is dropped.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import CalibrationState
from licalib_cli.pipeline import CalibrationRun
from licalib_cli.pipeline.diagnosis_step import CANDIDATES
from licalib_cli.pipeline.effect_models import (
    bic_terms,
    sensor_samples,
    with_effects,
    without_effect,
)

__all__ = ["bic_deltas", "deltas_without", "drop_redundant", "log_samples"]

logger = logging.getLogger(__name__)


def deltas_without(
    run: CalibrationRun,
    kept: tuple[str, ...],
    effects: tuple[str, ...],
    start: CalibrationState,
    cfg: CalibConfig,
    spread_log_det: Mapping[str, float] | None = None,
) -> dict[str, float]:
    """Per effect of ``effects``: the BIC of ``run``'s model (the effects ``kept``) minus that of
    the model without it, both on ``run``'s final data (:func:`bic_deltas`, the models those of
    ``cfg`` with exactly the effects listed)."""
    return bic_deltas(
        run,
        with_effects(cfg, kept),
        effects,
        start,
        lambda drop: with_effects(cfg, tuple(x for x in kept if x not in drop)),
        spread_log_det,
    )


def bic_deltas(
    refit: CalibrationRun,
    refit_cfg: CalibConfig,
    effects: Sequence[str],
    start: CalibrationState,
    model_without: Callable[[Sequence[str]], CalibConfig],
    spread_log_det: Mapping[str, float] | None = None,
) -> dict[str, float]:
    """Per effect of ``effects``: the BIC of ``refit`` (model ``refit_cfg``) minus that of the
    model without it (``model_without((effect,))``), both on the refit's final data; the latter
    re-solved from the refit's estimate with the effect back at its value in ``start``.
    Positive: the others explain what it did. An effect kept as one spread across beams
    (``spread_log_det``: its ``ln det(1 + s^2 I)``) costs that and ``ln n`` instead of ``ln n``
    per coordinate."""
    spread_log_det = spread_log_det or {}
    others = [(without_effect(refit.state, e, start), model_without((e,))) for e in effects]
    terms = bic_terms(refit, refit_cfg, others)
    deltas = {}
    for e, (ss, k) in zip(effects, terms, strict=True):
        log_n = log_samples(refit, e)
        penalty = log_n + spread_log_det[e] if e in spread_log_det else k * log_n
        deltas[e] = ss + penalty
    for effect, delta in deltas.items():
        logger.info("%s with the others in: BIC %+.1f against without it.", effect, delta)
    return deltas


def log_samples(run: CalibrationRun, effect: str) -> float:
    """``ln n`` of an effect's BIC penalty: ``n`` the residuals of its sensor in ``run``."""
    return math.log(max(sensor_samples(run, CANDIDATES[effect][2]), 2))


def drop_redundant(
    kept: tuple[str, ...],
    deltas_without: Callable[[tuple[str, ...], tuple[str, ...]], dict[str, float]],
    refit_without: Callable[[tuple[str, ...], str], None],
) -> list[tuple[str, tuple[str, ...], float]]:
    """The backward check of the forward selection (module docstring, step 5).

    Every kept effect but the last added (which paid with all the others in) is taken out in
    turn: ``deltas_without(kept, effects)`` gives, per effect of ``effects``, the BIC with it
    minus without it. The one whose
    removal lowers the BIC most is dropped (``refit_without(kept, effect)`` refits the model
    without it) and the check repeats on the effects left, until no removal pays.

    Returns:
        Per effect dropped, in order: its name, the effects added after it that remain (what
        explains it), and its BIC change.
    """
    dropped: list[tuple[str, tuple[str, ...], float]] = []
    while len(kept) >= 2:
        deltas = deltas_without(kept, kept[:-1])
        effect = max(deltas, key=lambda e: deltas[e])
        if not deltas[effect] > 0.0:
            break
        refit_without(kept, effect)
        later = kept[kept.index(effect) + 1 :]
        kept = tuple(e for e in kept if e != effect)
        dropped.append((effect, later, deltas[effect]))
    return dropped
