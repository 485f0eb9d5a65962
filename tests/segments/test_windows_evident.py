"""The windows of ``calibrate --segments`` refitted with what one of them shows beyond doubt
(``licalib_cli.pipeline.segments_evident``): the decisions, on stand-in fits (the end-to-end run
on a simulated bag is ``test_joint_evident_e2e.py``)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from held_effects import scored_effect

from licalib_cli.config import load_config
from licalib_cli.geometry import so3
from licalib_cli.pipeline import rivals, segments_evident
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


def _scale_and_rotation(share: float) -> tuple:
    """A gyro scale one window shows beyond doubt and a gyro-to-IMU rotation that explains
    ``share`` of its score when freed with it (figure-8s with the IMU mounted obliquely)."""
    scale = replace(
        scored_effect("gyro_scale", STRONG, shift_z_mm=0.0),
        statistic_alone=3 * STRONG,
        explained_by={"gyro_rotation": share},
    )
    rotation = replace(
        scored_effect("gyro_rotation", 2.0, selected=False, shift_z_mm=0.0),
        statistic_alone=2.7 * STRONG,
    )
    return scale, rotation


def _compare(
    monkeypatch: pytest.MonkeyPatch, rotation_minus_scale: float, alike: dict[float, bool]
) -> list:
    """The same-data comparison answered per window (by the scale refit's ``tz``)."""
    compared: list = []

    def same_data_bic(a, b, samples):  # type: ignore[no-untyped-def]
        assert a[2].bag.start_s == b[2].bag.start_s  # each window's data, its own range
        compared.append((a[0], b[0], a[2].bag.start_s, samples))
        return rotation_minus_scale

    monkeypatch.setattr(rivals, "same_data_bic", same_data_bic)
    monkeypatch.setattr(rivals, "refits_alike", lambda a, b: alike[a[1].tz])
    monkeypatch.setattr(rivals, "sensor_samples", lambda run, sensor: 4000)
    return compared


ROTATION_REFITS = {
    (0.0, ("gyro_scale",)): _Window(0.31),
    (5.0, ("gyro_scale",)): _Window(0.32),
    (0.0, ("gyro_rotation",)): _Window(0.311),
    (5.0, ("gyro_rotation",)): _Window(0.321),
}


def test_a_close_rival_is_refitted_in_every_window_and_the_better_summed_one_named(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    scale, rotation = _scale_and_rotation(0.999)
    windows = [_Window(0.30), _Window(0.30, effects=(scale, rotation))]
    asked = _install(monkeypatch, ROTATION_REFITS)
    compared = _compare(monkeypatch, -8.5, {0.31: True, 0.32: True})
    out = _add(windows)
    assert asked == [
        (0.0, ("gyro_scale",)),
        (5.0, ("gyro_scale",)),
        (0.0, ("gyro_rotation",)),
        (5.0, ("gyro_rotation",)),
    ]
    assert compared == [
        ("gyro_scale", "gyro_rotation", 0.0, 4000),
        ("gyro_scale", "gyro_rotation", 5.0, 4000),
    ]
    assert out is not None and out.cfg.model.imu == ["gyro_rotation"]
    assert [r.tz for r in out.runs] == [0.311, 0.321]
    (a,) = out.added
    assert (a.effect, a.rival, a.not_told_apart) == ("gyro_rotation", "gyro_scale", ("gyro_scale",))
    assert a.rival_delta_bic == pytest.approx(-17.0)  # summed over the two windows
    assert a.statistic == pytest.approx(2.7 * STRONG)  # its own test, not given the scale
    # one window that tells them apart is enough to say the data do
    _install(monkeypatch, ROTATION_REFITS)
    _compare(monkeypatch, -8.5, {0.31: True, 0.32: False})
    out = _add(windows)
    assert out is not None and out.added[0].not_told_apart == ()


def test_a_rival_that_fits_worse_in_sum_leaves_the_leader_with_the_rival_named(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    scale, rotation = _scale_and_rotation(0.999)
    windows = [_Window(0.30, effects=(scale, rotation)), _Window(0.30)]
    _install(monkeypatch, ROTATION_REFITS)
    _compare(monkeypatch, +20.0, {0.31: False, 0.32: False})
    out = _add(windows)
    assert out is not None and out.cfg.model.imu == ["gyro_scale"]
    assert [r.tz for r in out.runs] == [0.31, 0.32]
    (a,) = out.added
    assert (a.effect, a.rival, a.rival_delta_bic, a.not_told_apart) == (
        "gyro_scale",
        "gyro_rotation",
        -40.0,
        (),
    )


def test_a_rival_is_not_refitted_when_it_cannot_stand_in_or_its_refits_are_not_kept(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # freed with the scale, the rotation explains 60 %: the rest of the scale's score is beyond
    # doubt, so the rotation cannot be what the data show
    scale, rotation = _scale_and_rotation(0.6)
    asked = _install(monkeypatch, ROTATION_REFITS)
    compared = _compare(monkeypatch, -50.0, {0.31: True, 0.32: True})
    out = _add([_Window(0.30, effects=(scale, rotation)), _Window(0.30)])
    assert len(asked) == 2 and compared == []
    assert out is not None and out.added[0].rival == ""
    # the rival's refit of one window does not converge: the scale stays, unweighed
    scale, rotation = _scale_and_rotation(0.999)
    refits = {**ROTATION_REFITS, (5.0, ("gyro_rotation",)): _Window(0.35, "not converged")}
    asked = _install(monkeypatch, refits)
    compared = _compare(monkeypatch, -50.0, {0.31: True, 0.32: True})
    out = _add([_Window(0.30, effects=(scale, rotation)), _Window(0.30)])
    assert len(asked) == 4 and compared == []
    assert out is not None and out.cfg.model.imu == ["gyro_scale"]
    assert out.added[0].rival == "" and [r.tz for r in out.runs] == [0.31, 0.32]


def test_the_notes_name_the_rival_and_whether_the_segments_told_them_apart() -> None:
    from licalib_cli.commands.segments_render import added_notes
    from licalib_cli.sections import AddedEffect

    moved = {"moved_translation_m": 4e-5, "moved_rotation_deg": 0.002, "moved_time_offset_s": 0.0}
    added = AddedEffect("gyro_rotation", 810.0, 3, -5982.0, **moved)
    assert added_notes([added]) == [
        "a segment showed gyro_rotation (810 on 3 dof) beyond doubt; every segment estimated it "
        "(BIC -5982; a segment's extrinsic moved up to 0.04 mm). The resolved config estimates "
        "it; --model config keeps to the config's model."
    ]
    alike = replace(
        added, rival="gyro_scale", rival_delta_bic=-17.0, not_told_apart=("gyro_scale",)
    )
    assert added_notes([alike])[1] == (
        "no segment tells gyro_rotation from gyro_scale: with either estimated, the other's score "
        "test is no longer significant. Both were refitted in every segment; gyro_rotation fit "
        "the same data better (BIC -17 summed over the segments) and is estimated. Its numbers "
        "stand for an effect either one explains; a motion that excites more axes tells them "
        "apart, and licalib diagnose on a segment shows both."
    )
    apart = replace(alike, not_told_apart=())
    assert added_notes([apart])[1:] == [
        "gyro_scale could stand in for gyro_rotation; refitted in its place in every segment, it "
        "fit the same data worse (BIC +17 summed over the segments)."
    ]
