"""An effect's expected size (``model.expected_size``): the characteristic scale the truncated
SVD judges a block by, and diagnose's refit of an effect its score test shows far above the
scale it was held at."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from licalib_cli.config import CalibConfig, load_config
from licalib_cli.consistency.score import EffectScore
from licalib_cli.errors import ConfigError
from licalib_cli.estimation import CALIBRATION_SCALES, parameter_blocks
from licalib_cli.pipeline.diagnose import DiagnosisStep
from licalib_cli.pipeline.effect_models import final_config
from licalib_cli.pipeline.effect_size import (
    round_up,
    size_worth_trying,
    sized_refit,
    with_expected_size,
)
from licalib_cli.pipeline.segments_model import union_config
from licalib_cli.pipeline.settings import expected_size, free_parameters
from licalib_cli.residuals import GYRO_BIAS_DRIFT, GYRO_SCALE
from tests.stages.test_bias_walk_pieces import _state
from tests.stages.test_bias_walk_pieces import _step as walk_step

# 4218's first 10 s: the score test's one-step drift and its sigmas (rad/s^2)
WALK_ESTIMATE = np.array([1.09e-4, 1.73e-4, -2.86e-4])
WALK_SIGMA = np.array([2.21e-5, 2.11e-5, 2.23e-5])


def _score(estimate: Any = WALK_ESTIMATE, sigma: Any = WALK_SIGMA) -> EffectScore:
    e = np.asarray(estimate, dtype=np.float64)
    return EffectScore(
        name="gyro_bias_walk",
        statistic=255.7,
        rank=e.size,
        p_value=4e-55,
        estimate=e,
        sigma=np.asarray(sigma, dtype=np.float64),
        shift=np.zeros(7),
        shift_sigma=np.ones(7),
    )


def test_sizes_round_up_to_one_two_or_five_times_a_power_of_ten() -> None:
    assert [round_up(x) for x in (1.83e-4, 2e-4, 2.01e-4, 4.9e-3, 7.0, 0.1)] == pytest.approx(
        [2e-4, 2e-4, 5e-4, 5e-3, 10.0, 0.1]
    )


def test_the_expected_size_sets_the_scale_the_truncated_svd_judges_a_block_by() -> None:
    cfg = load_config(None, {"model.imu": ["gyro_bias_walk", "gyro_scale"]})
    assert expected_size(cfg, "gyro_bias_walk") == CALIBRATION_SCALES[GYRO_BIAS_DRIFT][0]
    sized = with_expected_size(cfg, "gyro_bias_walk", 2e-4)
    assert expected_size(sized, "gyro_bias_walk") == 2e-4
    assert cfg.model.expected_size == {}  # the input is not changed
    free = free_parameters(sized, intrinsics=True)
    assert free.expected_size == ((GYRO_BIAS_DRIFT, 2e-4),)
    scales = {b.name: b.scale for b in parameter_blocks(_state(), free)}
    assert np.allclose(scales[GYRO_BIAS_DRIFT], 2e-4)
    assert np.allclose(scales[GYRO_SCALE], CALIBRATION_SCALES[GYRO_SCALE])  # others unchanged
    # in four pieces of 5 s each piece's scale is 4^1.5 times the one drift's, as before
    pieces = free_parameters(
        sized.model_copy(
            update={"model": sized.model.model_copy(update={"bias_walk_piece_s": 5.0})}
        ),
        intrinsics=True,
    )
    scales = {b.name: b.scale for b in parameter_blocks(_state(), pieces)}
    assert scales[GYRO_BIAS_DRIFT].shape == (12,)
    assert np.allclose(scales[GYRO_BIAS_DRIFT], 8.0 * 2e-4)
    # the rounds without intrinsics free nothing of it
    assert free_parameters(sized, intrinsics=False).expected_size == ()


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("model:\n  expected_size:\n    gyro_bias_walk: 0\n", "greater than 0"),
        (
            "model:\n  expected_size:\n    range_offset: 0.001\n",
            "setting 'model.expected_size.range_offset' in.*'clock_drift' or 'point_time'",
        ),
        ("model:\n  expected_size:\n    gyro_scale: big\n", "valid number"),
    ],
)
def test_a_bad_expected_size_is_refused_in_one_sentence(
    tmp_path: Path, text: str, fragment: str
) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=fragment) as info:
        load_config(path)
    assert "\n" not in str(info.value)
    assert path.read_text() == text


def test_a_walk_held_at_its_scale_is_sized_from_its_score_test() -> None:
    cfg = load_config(None)
    assert size_worth_trying(_score(), "gyro_bias_walk", True, True, cfg) == pytest.approx(5e-4)
    # not when nothing was held, the test is not significant, or for per-beam intrinsics
    assert size_worth_trying(_score(), "gyro_bias_walk", False, True, cfg) is None
    assert size_worth_trying(_score(), "gyro_bias_walk", True, False, cfg) is None
    assert size_worth_trying(_score(), "range_offset", True, True, cfg) is None
    # not from coordinates within SIZE_SIGMAS of zero (an estimate the test does not show)
    assert size_worth_trying(_score([5e-5, 6e-5, 0.0]), "gyro_bias_walk", True, True, cfg) is None
    # the largest coordinate beyond them sets it (here y: 2e-4)
    mixed = _score([5e-5, 1.73e-4, 0.0])
    assert size_worth_trying(mixed, "gyro_bias_walk", True, True, cfg) == pytest.approx(2e-4)
    # not when the size would not exceed the scale it was held at
    held_at = with_expected_size(cfg, "gyro_bias_walk", 5e-4)
    assert size_worth_trying(_score(), "gyro_bias_walk", True, True, held_at) is None
    # the largest coordinate the test shows sets the size; undetermined ones do not
    wide = _score([1e-2, 0.0, 0.0], [3e-3, np.inf, np.inf])
    assert size_worth_trying(wide, "gyro_bias_walk", True, True, cfg) == pytest.approx(0.01)
    blurred = _score([1.2e-3, 0.0, 0.0], [3.0e-4, 2e-3, np.inf])
    assert size_worth_trying(blurred, "gyro_bias_walk", True, True, cfg) == pytest.approx(2e-3)


def _step(delta_bic: float, held: tuple[str, ...] = (), **kw: Any) -> DiagnosisStep:
    """4218's walk step (at the built-in scale when ``held``)."""
    return replace(walk_step(delta_bic), statistic=255.7, p_value=4e-55, held=held, **kw)


HELD = ("imu.gyro_bias_drift.x", "imu.gyro_bias_drift.y", "imu.gyro_bias_drift.z")


def test_diagnose_refits_a_held_walk_expecting_its_size_and_the_bic_decides() -> None:
    cfg = load_config(None)
    tried: list[CalibConfig] = []

    def pays(c: CalibConfig) -> DiagnosisStep:
        tried.append(c)
        return _step(-220.8)

    held = _step(28.2, HELD, not_told_apart=("accel_bias_walk",))
    step, out = sized_refit(held, _score(), pays, cfg)
    assert [c.model.expected_size for c in tried] == [{"gyro_bias_walk": 5e-4}]
    assert step.kept and step.delta_bic == pytest.approx(-220.8)
    assert step.expected_size == pytest.approx(5e-4)
    assert step.held_delta_bic == pytest.approx(28.2)
    assert step.sized_delta_bic == pytest.approx(-220.8)
    assert step.not_told_apart == ("accel_bias_walk",)  # the pick's comparison stays
    assert out.model.expected_size == {"gyro_bias_walk": 5e-4}
    # a sized refit that does not pay leaves the step and the config as they were
    step, out = sized_refit(held, _score(), lambda c: _step(12.0), cfg)
    assert not step.kept and step.delta_bic == pytest.approx(28.2) and out is cfg
    assert step.sized_delta_bic == pytest.approx(12.0) and step.held == HELD
    # nothing held, or already kept: no refit at all
    for plain in (_step(28.2), _step(-50.0, HELD)):
        tried.clear()
        step, out = sized_refit(plain, _score(), pays, cfg)
        assert step is plain and out is cfg and not tried


def test_the_size_is_said_and_written(monkeypatch: pytest.MonkeyPatch) -> None:
    from licalib_cli.commands.diagnose import size_sentence
    from tests.core.test_diagnose_unpaid import _steps_dict

    kept = _step(-220.8, expected_size=2e-4, held_delta_bic=28.2, sized_delta_bic=-220.8)
    text = size_sentence(kept) or ""
    assert text.startswith("gyro_bias_walk was held at nominal by the truncated SVD")
    assert "(BIC +28)" in text and "expecting 0.0115 deg/s^2 per coordinate" in text
    assert text.endswith("it was estimated and pays (BIC -221).")
    failed = _step(28.2, HELD, expected_size=2e-4, held_delta_bic=28.2, sized_delta_bic=12.0)
    assert (size_sentence(failed) or "").endswith("did not pay either (BIC +12).")
    assert size_sentence(_step(28.2)) is None
    (row,) = _steps_dict(monkeypatch, kept)
    assert row["expected_size"] == pytest.approx(2e-4)
    assert row["held_delta_bic"] == pytest.approx(28.2)
    assert row["sized_delta_bic"] == pytest.approx(-220.8)


def test_only_the_sizes_of_the_effects_kept_stay_and_windows_take_the_largest() -> None:
    cfg = with_expected_size(load_config(None), "gyro_bias_walk", 2e-4)
    cfg = with_expected_size(cfg, "accel_scale", 0.02)
    assert final_config(cfg, ("gyro_bias_walk",)).model.expected_size == {"gyro_bias_walk": 2e-4}
    assert final_config(cfg, ()).model.expected_size == {}

    @dataclass(frozen=True)
    class Found:
        effects_found: tuple[str, ...]
        config: CalibConfig | None

    first = Found(("gyro_bias_walk",), final_config(cfg, ("gyro_bias_walk",)))
    bigger = with_expected_size(load_config(None), "gyro_bias_walk", 5e-4)
    second = Found(("gyro_bias_walk",), final_config(bigger, ("gyro_bias_walk",)))
    _, out = union_config(load_config(None), [first, Found((), None), second])  # type: ignore[list-item]
    assert out.model.expected_size == {"gyro_bias_walk": 5e-4}


def _report(weights: dict[str, float]) -> Any:
    from types import SimpleNamespace

    return SimpleNamespace(
        calibration_names=tuple(weights), truncated_weight=np.array(list(weights.values()))
    )


def test_an_effect_of_the_model_the_fit_held_is_said_with_what_to_do() -> None:
    from licalib_cli.pipeline.held_effects import held_effect_text, held_effects

    cfg = load_config(None, {"model.imu": ["gyro_scale", "gyro_bias_walk", "clock_drift"]})
    report = _report(
        {
            "imu.gyro_scale.x": 0.9,  # an intrinsic held is the observability section's
            "imu.gyro_bias_drift.x": 0.97,
            "imu.gyro_bias_drift.y": 0.99,
            "imu.gyro_bias_drift.z": 0.6,
            "ext.time_drift": 0.1,  # determined
        }
    )
    assert held_effects(report, cfg) == [("gyro_bias_walk", 1e-5, 3, 3)]
    text = held_effect_text("gyro_bias_walk", 1e-5, 3, 3)
    assert text.startswith("gyro_bias_walk is in the model, but this recording determines it")
    assert "(1e-05 rad/s^2 per number, model.expected_size)" in text
    assert "licalib diagnose measures its size" in text
    # a walk in pieces, part of it held, at a configured size
    sized = with_expected_size(cfg, "gyro_bias_walk", 5e-4)
    pieces = _report(
        {f"imu.gyro_bias_drift.{a}_{k}": w for k, w in ((1, 0.2), (2, 0.8)) for a in "xyz"}
    )
    assert held_effects(pieces, sized) == [("gyro_bias_walk", 5e-4, 3, 6)]
    assert "determines 3 of its 6 numbers worse" in held_effect_text("gyro_bias_walk", 5e-4, 3, 6)
    # nothing held, or no effect in the model: nothing said
    assert held_effects(_report({"imu.gyro_bias_drift.x": 0.3}), cfg) == []
    assert held_effects(report, load_config(None, {"model.imu": ["gyro_scale"]})) == []


def test_rivals_are_compared_each_at_the_size_it_was_refitted_at() -> None:
    from licalib_cli.pipeline.effect_size import with_sizes_of

    cfg = with_expected_size(load_config(None), "accel_scale", 0.02)
    walk = with_expected_size(cfg, "gyro_bias_walk", 5e-4)
    rotation = with_expected_size(cfg, "gyro_rotation", 0.05)
    both = with_sizes_of(cfg, [walk, cfg, rotation])
    assert both.model.expected_size == {
        "accel_scale": 0.02,
        "gyro_bias_walk": 5e-4,
        "gyro_rotation": 0.05,
    }
    assert with_sizes_of(cfg, []) is cfg
