"""Effects of one evident refit that the others explain, left out before the refit is kept.

:mod:`licalib_cli.pipeline.evident` refits with every effect the checks show beyond doubt at
once, and the refit's BIC weighs them only together. Shown by a fit whose rounds had not
settled, the tests see more than the effects in the data: on a 20 s figure-8 whose LiDAR had
only per-beam range offsets (``bench_consistency.py --first-seed 18980 --scenarios figure8
--lever-arm-prior 0.01 --duration 20 --seeds 18996``) the base fit crawled 42 mm in its final
round, and its checks showed seven effects beyond doubt, among them a gyro scale (965 on 3
degrees of freedom) and an accelerometer misalignment (196 on 1) that the refit with all seven
put at 2e-5 and 4e-4. Each effect of a refit with several is therefore taken out on the
refit's data, as ``diagnose`` checks backwards (:func:`licalib_cli.pipeline.backward.
bic_deltas`): its
parameters back at the values of the fit without it, the rest re-solved a few iterations. Those
whose BIC is lower without them explain nothing the others do not. They are left out together
when the BIC is lower without them all too, else the one the BIC needs least alone (two effects
that stand in for each other are each redundant given the other, not both), and never all of
them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import CalibrationState
from licalib_cli.pipeline import CalibrationRun
from licalib_cli.pipeline.backward import bic_deltas, log_samples
from licalib_cli.pipeline.effect_models import bic_terms, without_effect

__all__ = ["joint_delta", "left_out", "redundant", "without_all"]

logger = logging.getLogger(__name__)


def without_all(
    state: CalibrationState, effects: Sequence[str], start: CalibrationState
) -> CalibrationState:
    """``state`` with every one of ``effects`` back at its value in ``start``."""
    for e in effects:
        state = without_effect(state, e, start)
    return state


def redundant(
    refit: CalibrationRun,
    refit_cfg: CalibConfig,
    names: Sequence[str],
    start: CalibrationState,
    model_without: Callable[[Sequence[str]], CalibConfig],
) -> tuple[tuple[str, ...], dict[str, float]]:
    """The effects of ``names`` (all estimated by ``refit``, model ``refit_cfg``) to leave out
    (module docstring), and each one's BIC with it minus without it on the refit's data.

    Args:
        refit: the refit with every effect of ``names``.
        refit_cfg: its configuration.
        names: the effects the refit added.
        start: the estimate of the fit without them (where a left-out effect's parameters go
            back to).
        model_without: the configuration that estimates all of ``names`` but those given.

    Returns:
        The effects to leave out (empty when each pays with the others in, or fewer than two
        were added) and the BIC differences (positive: the others explain what it did).
    """
    if len(names) < 2:
        return (), {}
    deltas = bic_deltas(refit, refit_cfg, names, start, model_without)
    out = left_out(
        names, deltas, lambda out: joint_delta(refit, refit_cfg, out, start, model_without)
    )
    return out, deltas


def joint_delta(
    refit: CalibrationRun,
    refit_cfg: CalibConfig,
    out: Sequence[str],
    start: CalibrationState,
    model_without: Callable[[Sequence[str]], CalibConfig],
) -> float:
    """The BIC of ``refit`` minus that of its model without all of ``out`` together, on the
    refit's data (the penalty at the largest of their sensors' sample counts)."""
    ((ss, k),) = bic_terms(
        refit, refit_cfg, [(without_all(refit.state, out, start), model_without(out))]
    )
    return float(ss + k * max(log_samples(refit, e) for e in out))


def left_out(
    names: Sequence[str], deltas: Mapping[str, float], joint: Callable[[list[str]], float]
) -> tuple[str, ...]:
    """The effects to leave out given each one's BIC difference ``deltas`` (with it minus
    without it) and ``joint`` (the same for a set of them together): those with a positive
    difference, together when ``joint`` is positive for them all, else the largest alone; never
    every one of ``names``."""
    out = [e for e in names if deltas[e] > 0.0]
    if len(out) == len(names):  # the one the BIC needs most stays
        out.remove(min(out, key=lambda e: deltas[e]))
    if len(out) > 1:
        together = joint(out)
        logger.info("%s together: BIC %+.1f against without them.", ", ".join(out), together)
        if not together > 0.0:
            out = [max(out, key=lambda e: deltas[e])]
    return tuple(out)
