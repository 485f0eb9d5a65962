"""The windows of ``calibrate --segments`` refitted with what one of them shows beyond doubt
(``licalib_cli.pipeline.segments_evident``): the decisions, on stand-in fits (the end-to-end run
on a simulated bag is ``test_joint_evident_e2e.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from held_effects import scored_effect

from licalib_cli.config import load_config
from licalib_cli.geometry import so3
from licalib_cli.pipeline import segments_evident
from licalib_cli.pipeline.effect_refit import REFIT_STATISTIC_PER_DOF
from licalib_cli.pipeline.scan_pattern import SPINNING, ScanPattern

STRONG = 3.0 * REFIT_STATISTIC_PER_DOF


@dataclass(frozen=True)
class _Initial:
    state: object = None


@dataclass
class _Window:
    """A stand-in for a window's calibration: its estimate, status and what its checks show."""

    tz: float
    status: str = "ok"
    effects: tuple = ()
    segment: object = "segment"
    noise: object = "noise"
    initial: _Initial = _Initial()
    pattern: ScanPattern = SPINNING
    config: object = None  # the window fit's resolved config: the one given

    @property
    def state(self) -> SimpleNamespace:
        return SimpleNamespace(
            t_imu_lidar=np.array([0.1, 0.2, self.tz]),
            R_imu_lidar=so3.exp(np.zeros(3)),
            time_offset_s=0.0,
        )

    @property
    def checks(self) -> SimpleNamespace:
        return SimpleNamespace(effects=self.effects, exit_status=self.status)


def _install(
    monkeypatch: pytest.MonkeyPatch,
    refits: dict,
    bic: float = -50.0,
    without: dict[str, float | dict[float, float]] | None = None,
) -> list[tuple[float, tuple[str, ...]]]:
    """Refits answered by window start (or by (start, IMU blocks)); ``without``: per effect,
    a window's BIC with it minus without it on the refit's data (or per window start; -100 for
    the others, and the sum for several left out together); returns what was asked (start, IMU
    and LiDAR blocks)."""
    asked: list[tuple[float, tuple[str, ...]]] = []
    without = without or {}

    def delta(name: str, window_start: float) -> float:
        d = without.get(name, -100.0)
        return d[window_start] if isinstance(d, dict) else d

    def bic_deltas(refit, refit_cfg, names, start, model_without):  # type: ignore[no-untyped-def]
        assert model_without(()).model == refit_cfg.model  # the refit's own model
        assert refit_cfg.bag.start_s == model_without(names[:1]).bag.start_s
        return {n: delta(n, refit_cfg.bag.start_s) for n in names}

    def joint_delta(refit, refit_cfg, out, start, model_without):  # type: ignore[no-untyped-def]
        return sum(delta(n, refit_cfg.bag.start_s) for n in out)

    monkeypatch.setattr(segments_evident, "bic_deltas", bic_deltas)
    monkeypatch.setattr(segments_evident, "joint_delta", joint_delta)

    def fit_and_check(prepared, start, cfg, progress, timer, *, warm):  # type: ignore[no-untyped-def]
        assert warm
        asked.append((cfg.bag.start_s, (*cfg.model.imu, *cfg.model.lidar)))
        key = (cfg.bag.start_s, tuple(cfg.model.imu))
        return refits[key] if key in refits else refits[cfg.bag.start_s]

    monkeypatch.setattr(segments_evident, "fit_and_check", fit_and_check)
    monkeypatch.setattr(segments_evident, "bic_change", lambda *args: bic)
    return asked


def _add(windows: list[_Window]) -> segments_evident.WindowsEvident | None:
    spans = [(5.0 * k, 5.0 * (k + 1)) for k in range(len(windows))]
    return segments_evident.add_evident_to_windows(
        Path("bag"),
        windows,  # type: ignore[arg-type]
        spans,
        load_config(None),
        None,  # type: ignore[arg-type]
    )


def test_a_window_that_did_not_converge_counts_and_every_window_is_refitted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    offsets = scored_effect("lidar_range_offset", STRONG, rank=15, shift_z_mm=0.0)
    windows = [_Window(0.30), _Window(0.20, "not converged", (offsets,))]
    asked = _install(monkeypatch, {0.0: _Window(0.301), 5.0: _Window(0.302)})
    out = _add(windows)
    assert asked == [(0.0, ("range_offset",)), (5.0, ("range_offset",))]  # one group
    assert out is not None and out.cfg.model.lidar == ["range_offset"]
    assert [r.tz for r in out.runs] == [0.301, 0.302]
    (added,) = out.added
    assert added.effect == "lidar_range_offset" and added.delta_bic == pytest.approx(-100.0)
    assert added.moved_translation_m == pytest.approx(0.102)


def test_the_windows_keep_the_configured_model_when_a_refit_does_not_converge_or_pay(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    offsets = scored_effect("lidar_range_offset", STRONG, rank=15, shift_z_mm=0.0)
    windows = [_Window(0.30, effects=(offsets,)), _Window(0.20, "not converged")]
    for refits, bic in (
        ({0.0: _Window(0.301), 5.0: _Window(0.25, "not converged")}, -50.0),
        ({0.0: _Window(0.301), 5.0: _Window(0.302)}, +10.0),
    ):
        _install(monkeypatch, refits, bic)
        out = _add(windows)
        assert out is not None and out.added == () and out.cfg.model.lidar == []
        assert list(out.runs) == windows
    weak = scored_effect("lidar_range_offset", 0.5 * REFIT_STATISTIC_PER_DOF, rank=15)
    asked = _install(monkeypatch, {})
    assert _add([_Window(0.30, effects=(weak,))]) is None and asked == []


def test_when_every_effect_together_fails_a_window_the_strongest_sensors_are_tried(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a gyro-to-IMU rotation that one window (a shake) cannot tell from the extrinsic rotation
    offsets = scored_effect("lidar_range_offset", 2 * STRONG, rank=15, shift_z_mm=0.0)
    rotation = scored_effect("gyro_rotation", STRONG, shift_z_mm=0.0)
    windows = [_Window(0.30, effects=(rotation,)), _Window(0.30, effects=(offsets,))]
    asked = _install(
        monkeypatch,
        {
            (0.0, ("gyro_rotation",)): _Window(0.31, "fail"),
            0.0: _Window(0.301),
            5.0: _Window(0.302),
        },
    )
    out = _add(windows)
    assert asked == [
        (0.0, ("gyro_rotation", "range_offset")),
        (0.0, ("range_offset",)),
        (5.0, ("range_offset",)),
    ]
    assert out is not None and [a.effect for a in out.added] == ["lidar_range_offset"]
    assert out.cfg.model.imu == [] and out.cfg.model.lidar == ["range_offset"]


def test_effects_the_others_explain_are_left_out_by_refitting_the_windows_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a window that had not settled showed a gyro scale beside the range offsets; with the
    # offsets in, it costs 8 of BIC in each window
    offsets = scored_effect("lidar_range_offset", 2 * STRONG, rank=15, shift_z_mm=0.0)
    scale = scored_effect("gyro_scale", STRONG, shift_z_mm=0.0)
    windows = [_Window(0.20, "not converged", (offsets, scale)), _Window(0.30)]
    refits = {
        (0.0, ("gyro_scale",)): _Window(0.31),
        (5.0, ("gyro_scale",)): _Window(0.32),
        0.0: _Window(0.301),
        5.0: _Window(0.302),
    }
    asked = _install(monkeypatch, refits, without={"gyro_scale": 8.0})
    out = _add(windows)
    assert asked == [
        (0.0, ("gyro_scale", "range_offset")),
        (5.0, ("gyro_scale", "range_offset")),
        (0.0, ("range_offset",)),
        (5.0, ("range_offset",)),
    ]
    assert out is not None and [a.effect for a in out.added] == ["lidar_range_offset"]
    assert out.cfg.model.imu == [] and [r.tz for r in out.runs] == [0.301, 0.302]
    # summed over the windows it pays (one window's -20 outweighs the other's +8): both stay
    asked = _install(monkeypatch, refits, without={"gyro_scale": {0.0: 8.0, 5.0: -20.0}})
    out = _add(windows)
    assert len(asked) == 2 and out is not None and len(out.added) == 2
    # the refit without it does not pay: the first refits stand, both named
    asked = _install(
        monkeypatch,
        {**refits, 5.0: _Window(0.25, "not converged")},
        without={"gyro_scale": 8.0},
    )
    out = _add(windows)
    assert len(asked) == 4 and out is not None
    assert [a.effect for a in out.added] == ["lidar_range_offset", "gyro_scale"]
    assert [r.tz for r in out.runs] == [0.31, 0.32]
