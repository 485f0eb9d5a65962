"""The model of a calibration over several segments chosen from the data
(``calibrate --segments ... --model auto``).

Every window is diagnosed on its own (:func:`~licalib_cli.pipeline.diagnose.diagnose`, exactly
as ``calibrate --start/--duration --model auto`` would); the joint calibration then estimates
every effect any window kept. The effects are properties of the sensors, not of a window: a
window that does not show one (too little excitation for it) loses nothing by estimating it
with the others, while one that shows it would be biased without it. An effect that one window
kept as one spread across beams (``model.lidar_spread``) keeps the spread of the first window
that kept it so.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from licalib_cli.config import CalibConfig, LidarSpreadSection
from licalib_cli.pipeline.diagnose import Diagnosis, diagnose
from licalib_cli.pipeline.effect_models import with_effects
from licalib_cli.pipeline.segment_runs import each_window, sigma_size
from licalib_cli.pipeline.segments import _with_range
from licalib_cli.progress import Progress

__all__ = ["SegmentsModel", "model_for_segments", "union_config"]


@dataclass(frozen=True)
class SegmentsModel:
    """The model the windows' diagnoses arrive at.

    Attributes:
        effects: every effect a window kept, in the order first kept.
        windows: the windows diagnosed, seconds after the bag start.
        diagnoses: each window's diagnosis, in the windows' order.
        config: the configuration whose ``model:`` section estimates ``effects``.
    """

    effects: tuple[str, ...]
    windows: tuple[tuple[float, float], ...]
    diagnoses: tuple[Diagnosis, ...]
    config: CalibConfig


def union_config(
    cfg: CalibConfig, diagnoses: Sequence[Diagnosis]
) -> tuple[tuple[str, ...], CalibConfig]:
    """The effects any of ``diagnoses`` kept, in the order first kept, and ``cfg`` estimating
    exactly them (the spreads across beams of the first diagnosis that kept each so; a bias walk
    in the shortest pieces any diagnosis chose; each block's largest expected size any
    diagnosis set)."""
    effects: list[str] = []
    for diag in diagnoses:
        effects.extend(e for e in diag.effects_found if e not in effects)
    out = with_effects(cfg, tuple(effects))
    spread = LidarSpreadSection()
    for block in out.model.lidar:
        for diag in diagnoses:
            sigma = diag.config.model.lidar_spread.sigma_of(block) if diag.config else None
            if sigma is not None:
                spread = spread.with_sigma(block, sigma)
                break
    pieces = [
        d.config.model.bias_walk_piece_s
        for d in diagnoses
        if d.config is not None and d.config.model.bias_walk_piece_s is not None
    ]
    sizes: dict[str, float] = {}
    for d in diagnoses:
        if d.config is not None:
            for sized, size in d.config.model.expected_size.items():
                sizes[sized] = max(size, sizes.get(sized, 0.0))
    model = out.model.model_copy(
        update={
            "lidar_spread": spread,
            "bias_walk_piece_s": min(pieces, default=None),
            "expected_size": sizes,
        }
    )
    return tuple(effects), out.model_copy(update={"model": model})


def model_for_segments(
    bag: Path,
    cfg: CalibConfig,
    windows: Sequence[tuple[float, float]],
    progress: Progress | None = None,
) -> SegmentsModel:
    """Diagnose every window of ``bag`` (seconds after its start) and join what they found. A
    window whose motion cannot give the initial guess is diagnosed from the estimate of the
    best-determined window that could (:func:`~licalib_cli.pipeline.segment_runs.each_window`).

    Raises:
        BagError, TopicError, DataError, TimestampError: unreadable input.
        ExcitationError, SolverError: a window cannot be calibrated.
    """

    def diagnose_one(a: float, b: float, window_cfg: CalibConfig) -> Diagnosis:
        return diagnose(bag, _with_range(window_cfg, a, b - a), progress=progress)

    done, _ = each_window(
        windows,
        cfg,
        diagnose_one,
        lambda d: d.final.result,
        lambda d: sigma_size(d.final),
        chosen=False,
    )
    diagnoses = tuple(done[i] for i in sorted(done))
    effects, config = union_config(cfg, diagnoses)
    return SegmentsModel(effects, tuple(windows), diagnoses, config)
