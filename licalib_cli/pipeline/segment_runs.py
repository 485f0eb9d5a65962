"""Each window of a multi-segment calibration calibrated alone, the joint problem's start.

A window whose own motion cannot give the initial guess (a calm stretch of a walk turns the rig
about one axis only: the hand-eye rotation and the rotation search both refuse it) need not sink
the calibration: the windows share the extrinsic, and that is what calibrating several of them
together is for. Such a window is calibrated again once the others are done, starting from the
extrinsic and time offset of the best-determined window that started on its own (as a user would
give ``initialization.rotation_rpy_deg`` and ``translation_m``); its own fit then runs on its
own data from there. The result names the window it started from
(:attr:`~licalib_cli.sections.SegmentEstimate.started_from`).

Other errors stop the calibration as before when the windows were given; windows chosen by
``--segments auto`` that cannot be calibrated are left out with a warning.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, ExcitationError, LicalibError
from licalib_cli.pipeline import CalibrationRun, calibrate
from licalib_cli.pipeline.segments import _with_range
from licalib_cli.progress import Progress
from licalib_cli.results import CalibrationResult, rpy_deg_from_matrix

__all__ = [
    "WindowRuns",
    "calibrate_windows",
    "each_window",
    "sigma_size",
    "started_from_result",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")


@dataclass(frozen=True)
class WindowRuns:
    """The windows calibrated alone.

    Attributes:
        runs: each kept window's own calibration, in time order.
        windows: those windows, seconds after the bag start.
        started_from: index into ``runs`` -> the index of the run whose estimate it started
            from (it could not start on its own).
        timings: wall seconds per window (both tries of one that started from another).
    """

    runs: tuple[CalibrationRun, ...]
    windows: tuple[tuple[float, float], ...]
    started_from: dict[int, int]
    timings: dict[str, float]


def sigma_size(run: CalibrationRun) -> float:
    """How well a run determines the extrinsic (smaller is better): its translation sigmas in
    units of 1 cm and its rotation sigmas in units of 1 mrad, squared and summed."""
    unc = run.result.uncertainty
    if unc is None:
        return float("inf")
    t = np.asarray(unc.translation_std_m) / 0.01
    r = np.asarray(unc.rotation_std_deg) / np.degrees(1e-3)
    v = float(np.sum(t**2) + np.sum(r**2))
    return v if np.isfinite(v) else float("inf")


def started_from_result(cfg: CalibConfig, result: CalibrationResult) -> CalibConfig:
    """``cfg`` whose initial guess is ``result``'s extrinsic and time offset."""
    ext = result.extrinsic
    init = cfg.initialization.model_copy(
        update={
            "rotation_rpy_deg": [float(v) for v in rpy_deg_from_matrix(ext.rotation)],
            "translation_m": [float(v) for v in ext.translation],
            "time_offset_s": float(ext.time_offset_s),
        }
    )
    return cfg.model_copy(update={"initialization": init})


def each_window(
    windows: Sequence[tuple[float, float]],
    cfg: CalibConfig,
    run_one: Callable[[float, float, CalibConfig], T],
    result_of: Callable[[T], CalibrationResult],
    size_of: Callable[[T], float],
    *,
    chosen: bool,
) -> tuple[dict[int, T], dict[int, int]]:
    """``run_one(start, end, cfg)`` for every window, a weak one again from the estimate of the
    best one that started on its own (see the module's text).

    Args:
        windows: the windows, seconds after the bag start, in time order.
        cfg: the configuration.
        run_one: one window's work (a calibration, a diagnosis).
        result_of: the result of that work whose extrinsic a weak window starts from.
        size_of: how poorly that work determines the extrinsic (the smallest is the start).
        chosen: the windows were chosen by ``--segments auto`` (a window that fails is left
            out) rather than given (a window that fails stops the calibration).

    Returns:
        Window index -> its work, for every window kept; window index -> the index of the
        window it started from.

    Raises:
        LicalibError: a given window failed (a weak one: also after starting from another's
            estimate, or when no window started on its own).
    """
    done: dict[int, T] = {}
    weak: list[tuple[int, ExcitationError]] = []

    def give_up(i: int, err: LicalibError) -> None:
        a, b = windows[i]
        if not chosen or isinstance(err, ConfigError):
            raise err
        logger.warning("Segment %.1f-%.1f s left out: %s", a, b, err)

    for i, (a, b) in enumerate(windows):
        try:
            done[i] = run_one(a, b, cfg)
        except ExcitationError as err:
            weak.append((i, err))
        except LicalibError as err:
            give_up(i, err)
    started: dict[int, int] = {}
    for i, failure in weak:
        if not done:
            give_up(i, failure)
            continue
        source = min(done, key=lambda j: size_of(done[j]))
        (a, b), (sa, sb) = windows[i], windows[source]
        logger.warning(
            "Segment %.1f-%.1f s cannot start on its own (%s); it starts from the estimate of "
            "segment %.1f-%.1f s.",
            a,
            b,
            failure,
            sa,
            sb,
        )
        try:
            done[i] = run_one(a, b, started_from_result(cfg, result_of(done[source])))
        except LicalibError as again:
            give_up(i, again)
            continue
        started[i] = source
    return done, started


def calibrate_windows(
    bag: Path,
    cfg: CalibConfig,
    windows: Sequence[tuple[float, float]],
    progress: Progress,
    *,
    chosen: bool,
    rivals: bool = False,
) -> WindowRuns:
    """Calibrate each window alone (:func:`each_window`).

    Args:
        bag: the bag.
        cfg: the configuration (its range is replaced by each window's).
        windows: the windows, seconds after the bag start, in time order.
        progress: stage progress (kept open across the windows by the caller).
        chosen: as for :func:`each_window`.
        rivals: the windows' checks size which effects can stand in for each other (read when
            effects are added to the windows: :mod:`~licalib_cli.pipeline.segments_evident`).

    Raises:
        LicalibError: as :func:`each_window`; ``ExcitationError`` when no window could be
            calibrated.
    """
    timings: dict[str, float] = {}

    def run_alone(a: float, b: float, window_cfg: CalibConfig) -> CalibrationRun:
        clock = time.perf_counter()
        key = f"segment {a:.0f}-{b:.0f} s"
        try:
            # every window estimates the same model, as the joint problem shares it: an effect
            # one window shows beyond doubt widens its sigmas and is named, not added there
            return calibrate(
                bag, _exact_model(_with_range(window_cfg, a, b - a)), progress, rivals=rivals
            )
        finally:  # a window tried twice counts both tries
            timings[key] = timings.get(key, 0.0) + time.perf_counter() - clock

    done, started = each_window(
        windows, cfg, run_alone, lambda r: r.result, sigma_size, chosen=chosen
    )
    if not done:
        msg = "None of the selected segments could be calibrated on its own."
        raise ExcitationError(msg)
    order = sorted(done)
    position = {i: k for k, i in enumerate(order)}
    return WindowRuns(
        runs=tuple(done[i] for i in order),
        windows=tuple(windows[i] for i in order),
        started_from={position[i]: position[j] for i, j in started.items()},
        timings=timings,
    )


def _exact_model(cfg: CalibConfig) -> CalibConfig:
    """``cfg`` estimating exactly its ``model:`` blocks (no effect added on the data's word)."""
    return cfg.model_copy(
        update={"model": cfg.model.model_copy(update={"add_evident_effects": False})}
    )
