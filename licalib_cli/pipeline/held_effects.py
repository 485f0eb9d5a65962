"""Effects in the model that the truncated SVD held: said, with what to do about it.

An effect a user (or ``diagnose``) puts in the model, a bias walk, a clock drift or an error of
the per-point times, is there to capture something the base model lacks. When the recording
determines it worse than the size it is expected to have (its characteristic scale, or
``model.expected_size``), the truncated SVD holds it near zero and the fit is the base model's:
on a 10 s OS1-64 shake whose gyro bias walked at a hundred times the MTi-100's rate, the walk
was configured, held, and the checks then found the gyro residuals depending on time, "the gyro
model lacks an effect", with nothing saying that the effect meant to capture it had been held.
This stage says so, and how to estimate it when it is larger than expected.
"""

from __future__ import annotations

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline.settings import calibration_block, expected_size
from licalib_cli.solver.lm import SolverReport

__all__ = ["EFFECT_BLOCKS", "HELD_WEIGHT", "held_effect_text", "held_effects"]

EFFECT_BLOCKS: dict[str, str] = {
    "gyro_bias_walk": "rad/s^2",
    "accel_bias_walk": "m/s^3",
    "clock_drift": "s/s",
    "point_time": "of the sweep time",
}
"""The ``model:`` effects (beyond the sensors' intrinsics) and the unit of their size."""

HELD_WEIGHT = 0.5
"""A coordinate counts as held when at least this share of it (scaled) lies in truncated
directions."""


def held_effects(report: SolverReport, cfg: CalibConfig) -> list[tuple[str, float, int, int]]:
    """The model's effects with coordinates the fit held.

    Returns:
        ``(block, expected size, coordinates held, coordinates)`` per effect of ``cfg.model``
        (:data:`EFFECT_BLOCKS`) with a held coordinate, in the model's order.
    """
    out = []
    weight = dict(zip(report.calibration_names, report.truncated_weight, strict=True))
    for block in (*cfg.model.imu, *cfg.model.lidar):
        if block not in EFFECT_BLOCKS:
            continue
        prefix = calibration_block(block)
        mine = [w for n, w in weight.items() if n == prefix or n.startswith(f"{prefix}.")]
        held = sum(w >= HELD_WEIGHT for w in mine)
        if held:
            out.append((str(block), expected_size(cfg, block), int(held), len(mine)))
    return out


def held_effect_text(block: str, size: float, held: int, coordinates: int) -> str:
    """One sentence on a held effect (:func:`held_effects`)."""
    which = "it" if held == coordinates else f"{held} of its {coordinates} numbers"
    return (
        f"{block} is in the model, but this recording determines {which} worse than the size "
        f"it is expected to have ({size:.3g} {EFFECT_BLOCKS[block]} per number, "
        f"model.expected_size), so the truncated SVD held {which} near zero: the fit is that of "
        f"a model without {which}. If the effect is larger than that (the residual checks find "
        f"a pattern over time), licalib diagnose measures its size from its score test and "
        f"refits it expecting that size (it sets model.expected_size)."
    )
