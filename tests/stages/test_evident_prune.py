"""Effects of one evident refit that the others explain (``licalib_cli.pipeline.evident_prune``).

Each effect is taken out on the refit's data; those whose BIC is lower without them are left
out together when the BIC is lower without them all too, else the one needed least alone, and
never every one. The sums of squares here are stand-ins: the rule is what is tested.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from licalib_cli.pipeline import backward, evident_prune

LOG_N = math.log(100)


def _install(
    monkeypatch: pytest.MonkeyPatch, ss_without: dict[tuple[str, ...], float]
) -> list[tuple[str, ...]]:
    """The refit's sum of squares minus that of the model without each set of effects (one
    parameter each) -> their BIC difference is that plus ``ln 100`` per effect."""
    asked: list[tuple[str, ...]] = []

    def bic_terms(refit, refit_cfg, others):  # type: ignore[no-untyped-def]
        out = []
        for state, without in others:
            assert state == ("state without", without)  # the effects back where they started
            asked.append(without)
            out.append((ss_without[without], len(without)))
        return out

    # each effect alone is taken out by the backward check's bic_deltas, several together here
    for module in (backward, evident_prune):
        monkeypatch.setattr(module, "bic_terms", bic_terms)
    monkeypatch.setattr(backward, "sensor_samples", lambda run, sensor: 100)
    monkeypatch.setattr(
        backward, "without_effect", lambda state, effect, start: ("state without", (effect,))
    )
    monkeypatch.setattr(
        evident_prune,
        "without_all",
        lambda state, effects, start: ("state without", tuple(effects)),
    )
    return asked


def _redundant(names: tuple[str, ...]) -> tuple[tuple[str, ...], dict[str, float]]:
    return evident_prune.redundant(
        SimpleNamespace(state="refit"),  # type: ignore[arg-type]
        None,  # type: ignore[arg-type]
        names,
        None,  # type: ignore[arg-type]
        lambda drop: tuple(drop),  # type: ignore[arg-type,return-value]
    )


def test_one_effect_is_never_taken_out(monkeypatch: pytest.MonkeyPatch) -> None:
    asked = _install(monkeypatch, {})
    assert _redundant(("gyro_scale",)) == ((), {})
    assert asked == []


def test_the_effects_the_others_explain_are_left_out_together(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a range offset the data need; a gyro scale and an accelerometer misalignment that a fit
    # which had not settled showed
    ss = {
        ("lidar_range_offset",): -150000.0,
        ("gyro_scale",): 25.7,
        ("accel_misalignment",): 24.9,
        ("gyro_scale", "accel_misalignment"): 50.0,
    }
    asked = _install(monkeypatch, ss)
    out, deltas = _redundant(("lidar_range_offset", "gyro_scale", "accel_misalignment"))
    assert out == ("gyro_scale", "accel_misalignment")
    assert deltas["gyro_scale"] == pytest.approx(25.7 + LOG_N)
    assert deltas["lidar_range_offset"] == pytest.approx(-150000.0 + LOG_N)
    assert asked[-1] == ("gyro_scale", "accel_misalignment")


def test_two_that_stand_in_for_each_other_are_not_both_left_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # each is redundant given the other, but without both the fit is much worse: only the one
    # the BIC needs least goes
    ss = {
        ("lidar_range_offset",): -1000.0,
        ("lidar_range_scale",): 3.0,
        ("lidar_elevation",): 1.0,
        ("lidar_range_scale", "lidar_elevation"): -900.0,
    }
    _install(monkeypatch, ss)
    out, _ = _redundant(("lidar_range_offset", "lidar_range_scale", "lidar_elevation"))
    assert out == ("lidar_range_scale",)


def test_the_effect_the_bic_needs_most_stays_when_every_one_is_redundant(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ss = {("gyro_scale",): 2.0, ("accel_scale",): 9.0}
    asked = _install(monkeypatch, ss)
    out, deltas = _redundant(("gyro_scale", "accel_scale"))
    assert out == ("accel_scale",) and set(deltas) == {"gyro_scale", "accel_scale"}
    # a single effect left out needs no joint test
    assert len(asked) == 2


def test_nothing_is_left_out_when_each_pays_with_the_others_in(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _install(monkeypatch, {("gyro_scale",): -40.0, ("accel_scale",): -9.0})
    out, deltas = _redundant(("gyro_scale", "accel_scale"))
    assert out == () and deltas["accel_scale"] == pytest.approx(-9.0 + LOG_N)
