"""Each window of a multi-segment calibration calibrated alone: a window whose own motion cannot
give an initial guess starts from the best window's estimate instead of sinking the run."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from licalib_cli.config import CalibConfig, load_config
from licalib_cli.errors import DataError, ExcitationError
from licalib_cli.pipeline import segment_runs
from licalib_cli.pipeline.segment_runs import calibrate_windows, started_from_result
from licalib_cli.progress import NullProgress
from licalib_cli.results import CalibrationResult, Extrinsic, matrix_from_rpy_deg
from licalib_cli.sections import Uncertainty

WINDOWS = ((0.0, 10.0), (10.0, 20.0), (20.0, 30.0))
SIZED: list[bool] = []  # whether each window's checks sized the rivals, in call order


def _run(t_std: float, rpy: tuple[float, float, float] = (1.0, 2.0, 3.0)) -> Any:
    result = CalibrationResult(
        extrinsic=Extrinsic(matrix_from_rpy_deg(rpy), np.array([0.1, -0.2, 0.3]), 0.004),
        uncertainty=Uncertainty((t_std,) * 3, (0.01,) * 3, 1e-5),
    )
    return SimpleNamespace(result=result)


def _fake(monkeypatch: pytest.MonkeyPatch, outcome: dict[float, Any]) -> list[CalibConfig]:
    """``calibrate`` replaced: by the window's start, a run, or an error to raise (an error
    given as a pair ``(error, run)`` is raised only without an initial rotation)."""
    calls: list[CalibConfig] = []
    SIZED.clear()

    def calibrate(bag: Path, cfg: CalibConfig, progress: object, *, rivals: bool) -> Any:
        assert not cfg.model.add_evident_effects  # every window estimates the given model
        SIZED.append(rivals)
        calls.append(cfg)
        what = outcome[cfg.bag.start_s]
        if isinstance(what, tuple):
            err, run = what
            if cfg.initialization.rotation_rpy_deg is None:
                raise err
            return run
        if isinstance(what, Exception):
            raise what
        return what

    monkeypatch.setattr(segment_runs, "calibrate", calibrate)
    return calls


def test_a_window_that_cannot_start_alone_starts_from_the_best_windows_estimate(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    weak = ExcitationError("Rotation excitation is too weak.")
    best, other, late = _run(0.001, (5.0, 6.0, 7.0)), _run(0.004), _run(0.002)
    calls = _fake(monkeypatch, {0.0: (weak, late), 10.0: other, 20.0: best})
    out = calibrate_windows(Path("x.bag"), load_config(None), WINDOWS, NullProgress(), chosen=False)
    assert out.windows == WINDOWS  # time order kept
    assert out.runs == (late, other, best)
    assert out.started_from == {0: 2}  # the first window started from the third's estimate
    retry = calls[-1].initialization
    assert retry.rotation_rpy_deg == pytest.approx([5.0, 6.0, 7.0])
    assert retry.translation_m == pytest.approx([0.1, -0.2, 0.3])
    assert retry.time_offset_s == pytest.approx(0.004)
    assert set(out.timings) == {"segment 0-10 s", "segment 10-20 s", "segment 20-30 s"}


def test_the_windows_size_the_rivals_only_when_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    # effects added to the windows are weighed against their rivals, which the checks size
    for rivals in (False, True):
        _fake(monkeypatch, {0.0: _run(0.001), 10.0: _run(0.002), 20.0: _run(0.003)})
        cfg = load_config(None)
        calibrate_windows(Path("x.bag"), cfg, WINDOWS, NullProgress(), chosen=False, rivals=rivals)
        assert SIZED == [rivals] * 3


def test_without_a_window_that_starts_alone_the_given_windows_fail_as_before(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    weak = ExcitationError("Rotation excitation is too weak.")
    _fake(monkeypatch, {0.0: weak, 10.0: weak, 20.0: weak})
    with pytest.raises(ExcitationError, match="too weak"):
        calibrate_windows(Path("x.bag"), load_config(None), WINDOWS, NullProgress(), chosen=False)
    with pytest.raises(ExcitationError, match="None of the selected segments"):
        calibrate_windows(Path("x.bag"), load_config(None), WINDOWS, NullProgress(), chosen=True)


def test_other_errors_stop_given_windows_and_leave_chosen_ones_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    bad = DataError("The clouds are empty.")
    weak = ExcitationError("Rotation excitation is too weak.")
    good = _run(0.002)
    _fake(monkeypatch, {0.0: good, 10.0: bad, 20.0: weak})  # the weak one fails again too
    with pytest.raises(DataError):
        calibrate_windows(Path("x.bag"), load_config(None), WINDOWS, NullProgress(), chosen=False)
    out = calibrate_windows(Path("x.bag"), load_config(None), WINDOWS, NullProgress(), chosen=True)
    assert out.windows == (WINDOWS[0],) and out.started_from == {}


def test_the_start_from_a_result_keeps_the_rest_of_the_config() -> None:
    cfg = load_config(None, {"imu.topic": "/imu"})
    out = started_from_result(cfg, _run(0.001, (10.0, -20.0, 30.0)).result)
    assert out.imu.topic == "/imu"
    assert out.initialization.rotation_rpy_deg == pytest.approx([10.0, -20.0, 30.0])
    assert cfg.initialization.rotation_rpy_deg is None  # the input is not changed


def test_a_window_diagnosed_for_model_auto_starts_from_the_other_windows_estimate(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from licalib_cli.pipeline import segments_model

    weak = ExcitationError("Rotation excitation is too weak.")
    starts: list[Any] = []

    def diagnose(bag: Path, cfg: CalibConfig, progress: object = None) -> Any:
        starts.append(cfg.initialization.rotation_rpy_deg)
        if cfg.bag.start_s == 10.0 and cfg.initialization.rotation_rpy_deg is None:
            raise weak
        found = ("lidar_elevation",) if cfg.bag.start_s == 10.0 else ()
        return SimpleNamespace(final=_run(0.002, (4.0, 5.0, 6.0)), effects_found=found, config=cfg)

    monkeypatch.setattr(segments_model, "diagnose", diagnose)
    cfg = load_config(None)
    out = segments_model.model_for_segments(Path("x.bag"), cfg, WINDOWS[:2])
    assert starts == [None, None, pytest.approx([4.0, 5.0, 6.0])]
    assert out.effects == ("lidar_elevation",)
    # the joint model carries the effects, not the start the weak window was given
    assert out.config.initialization.rotation_rpy_deg is None
    assert len(out.diagnoses) == 2
