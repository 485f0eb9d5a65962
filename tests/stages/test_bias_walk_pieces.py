"""A bias walk estimated in pieces: the state and its blocks, the scales the truncated SVD judges
them by, what the result file carries, and how diagnose chooses the pieces by their BIC."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from licalib_cli.config import load_config
from licalib_cli.estimation import (
    CALIBRATION_SCALES,
    CalibrationState,
    FreeParameters,
    parameter_blocks,
    state_from_values,
    state_to_values,
)
from licalib_cli.models.imu import bias_drift_basis, drift_pieces, resample_drift
from licalib_cli.residuals import GYRO_BIAS_DRIFT
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots


def _state(t_ref_s: float = 10.0, **kwargs: Any) -> CalibrationState:
    knots = UniformKnots(0.0, 0.5, 48)
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (knots.num_control_points, 1))
    return CalibrationState(
        so3_spline=SO3Spline(knots, quats),
        r3_spline=R3Spline(knots, np.zeros((knots.num_control_points, 3))),
        gyro_bias=np.zeros(3),
        accel_bias=np.zeros(3),
        gravity_G=np.array([0.0, 0.0, -9.81]),
        R_imu_lidar=np.eye(3),
        t_imu_lidar=np.zeros(3),
        time_offset_s=0.0,
        t_ref_s=t_ref_s,
        **kwargs,
    )


def test_pieces_follow_the_segment_and_the_piece_length() -> None:
    assert drift_pieces(10.0, None) == 1
    assert drift_pieces(10.0, 5.0) == 4  # a 20 s segment
    assert drift_pieces(10.0, 7.0) == 3
    assert drift_pieces(1.0, 5.0) == 1  # never none


def test_going_to_pieces_keeps_the_bias_a_linear_drift_gave() -> None:
    d = np.array([1e-4, -2e-4, 3e-5])
    t = np.linspace(-1.0, 21.0, 50)
    four = resample_drift(d, 4)
    assert four.shape == (4, 3)
    np.testing.assert_allclose(
        bias_drift_basis(t, 10.0, 4) @ four, bias_drift_basis(t, 10.0, 1) @ d[None, :], atol=1e-15
    )
    # back to one piece: the mean drift; the same count: unchanged
    np.testing.assert_allclose(resample_drift(four * [[1], [2], [3], [4]], 1), 2.5 * d)
    np.testing.assert_array_equal(resample_drift(four, 4), four)


def test_the_state_holds_one_drift_or_one_per_piece() -> None:
    assert _state(gyro_bias_drift=np.zeros((1, 3))).gyro_bias_drift.shape == (3,)
    assert _state(gyro_bias_drift=np.ones((4, 3))).gyro_bias_drift.shape == (4, 3)
    for bad in (np.zeros(4), np.zeros((2, 2)), np.zeros(0)):
        with pytest.raises(ValueError, match="gyro_bias_drift must have shape"):
            _state(gyro_bias_drift=bad)


def test_the_blocks_of_a_walk_in_pieces() -> None:
    state = _state(gyro_bias_drift=np.array([2e-5, 0.0, -1e-5]))
    free = FreeParameters(gyro_bias_drift=True, bias_walk_piece_s=5.0)
    (block,) = [b for b in parameter_blocks(state, free) if b.name == GYRO_BIAS_DRIFT]
    assert block.num_elements == 4
    assert block.coord_names[:4] == (
        f"{GYRO_BIAS_DRIFT}.x_1",
        f"{GYRO_BIAS_DRIFT}.y_1",
        f"{GYRO_BIAS_DRIFT}.z_1",
        f"{GYRO_BIAS_DRIFT}.x_2",
    )
    np.testing.assert_allclose(block.value, np.tile([2e-5, 0.0, -1e-5], (4, 1)))
    # each piece judged on the footing of one drift: K^1.5 times its scale
    np.testing.assert_allclose(block.scale, 8.0 * CALIBRATION_SCALES[GYRO_BIAS_DRIFT][0])
    # without a piece length the state's own pieces stay as they are
    (linear,) = [
        b
        for b in parameter_blocks(state, FreeParameters(gyro_bias_drift=True))
        if b.name == GYRO_BIAS_DRIFT
    ]
    assert linear.coord_names == tuple(f"{GYRO_BIAS_DRIFT}.{a}" for a in "xyz")
    np.testing.assert_allclose(linear.scale, CALIBRATION_SCALES[GYRO_BIAS_DRIFT][0])
    # the solved pieces go back into the state
    values = {GYRO_BIAS_DRIFT: np.arange(12.0).reshape(4, 3)}
    back = state_from_values(state, values)
    np.testing.assert_array_equal(back.gyro_bias_drift, values[GYRO_BIAS_DRIFT])
    np.testing.assert_array_equal(state_to_values(back)[GYRO_BIAS_DRIFT], back.gyro_bias_drift)


def test_the_result_carries_every_piece_and_its_sigma() -> None:
    from licalib_cli.pipeline.assemble import extra_terms
    from licalib_cli.pipeline.intrinsic_sigmas import intrinsics_uncertainty
    from licalib_cli.results import CalibrationResult

    cfg = load_config(None, {"model.imu": ["gyro_bias_walk"], "model.bias_walk_piece_s": 10.0})
    drift = np.array([[1e-5, 2e-5, 3e-5], [-4e-5, 5e-5, -6e-5]])
    terms = extra_terms(_state(gyro_bias_drift=drift), cfg)
    assert terms is not None
    assert terms.bias_walk_pieces == 2
    assert terms.gyro_bias_walk == pytest.approx(tuple(drift.reshape(-1)))
    names = [f"{GYRO_BIAS_DRIFT}.{a}_{k}" for k in (1, 2) for a in "xyz"]
    report = SimpleNamespace(
        calibration_names=["ext.translation.x", *names],
        std=np.array([1e-3, *np.arange(1.0, 7.0) * 1e-6]),
        truncated_weight=np.zeros(7),
    )
    sigmas = intrinsics_uncertainty(report, cfg, 1.0, 16)  # type: ignore[arg-type]
    assert sigmas is not None
    assert sigmas.values["gyro_bias_walk"] == pytest.approx(tuple(np.arange(1.0, 7.0) * 1e-6))
    # the section reads back as written (schema v1, a tuple of any length)
    result = CalibrationResult(extra_terms=terms)
    again = CalibrationResult.from_dict(result.to_dict())
    assert again.extra_terms == terms
    linear = extra_terms(_state(gyro_bias_drift=drift[0]), cfg)
    assert linear is not None and linear.bias_walk_pieces is None


def _step(delta_bic: float, t_ref_s: float = 10.0, kept: bool | None = None) -> Any:
    from licalib_cli.pipeline.diagnose import DiagnosisStep, Gap

    gap = Gap("gyro", 0.5, 0.5, 0.0)
    return DiagnosisStep(
        effect="gyro_bias_walk",
        statistic=90.0,
        dof=3,
        p_value=1e-18,
        delta_bic=delta_bic,
        kept=delta_bic < 0.0 if kept is None else kept,
        estimate={},
        gap_before=gap,
        gap_after=gap,
        moved_translation_m=0.0,
        moved_rotation_deg=0.0,
        moved_time_offset_s=0.0,
        after=SimpleNamespace(state=SimpleNamespace(t_ref_s=t_ref_s)),  # type: ignore[arg-type]
    )


def test_diagnose_keeps_finer_pieces_while_they_lower_the_bic() -> None:
    from licalib_cli.pipeline.walk_pieces import finer_walk

    cfg = load_config(None, {"model.imu": ["gyro_bias_walk"]})
    bic = {2: -205.8, 4: -239.6, 8: -192.4}  # the 20 s walk of the benchmark
    tried: list[float] = []

    def try_with(c: Any) -> Any:
        tried.append(c.model.bias_walk_piece_s)
        return _step(bic[round(20.0 / c.model.bias_walk_piece_s)])

    step, out = finer_walk(_step(-75.6), try_with, cfg)
    assert tried == [10.0, 5.0, 2.5]
    assert step.pieces == 4 and step.delta_bic == pytest.approx(-239.6)
    assert step.linear_delta_bic == pytest.approx(-75.6)
    assert out.model.bias_walk_piece_s == pytest.approx(5.0)
    # a walk refitted at its expected size keeps saying so in pieces
    sized = replace(_step(-75.6), expected_size=5e-4, held_delta_bic=28.2, sized_delta_bic=-75.6)
    step, _ = finer_walk(sized, try_with, cfg)
    assert step.pieces == 4 and step.expected_size == pytest.approx(5e-4)
    assert (step.held_delta_bic, step.sized_delta_bic) == pytest.approx((28.2, -75.6))
    # no gain from pieces: the linear drift stays, its config unchanged
    step, out = finer_walk(_step(-75.6), lambda c: _step(-60.0), cfg)
    assert step.pieces == 1 and out is cfg
    # pieces of under MIN_WALK_PIECE_S are not tried (a 3 s segment: only halves)
    short: list[float] = []

    def try_short(c: Any) -> Any:
        short.append(c.model.bias_walk_piece_s)
        return _step(-100.0 * len(short))

    finer_walk(_step(-75.6, t_ref_s=1.5), try_short, cfg)
    assert short == [1.5]


def test_a_final_model_without_a_walk_has_no_piece_length() -> None:
    from licalib_cli.pipeline.effect_models import final_config
    from licalib_cli.pipeline.walk_pieces import with_walk_pieces

    cfg = with_walk_pieces(load_config(None), 5.0)
    assert final_config(cfg, ("gyro_bias_walk",)).model.bias_walk_piece_s == 5.0
    assert final_config(cfg, ("gyro_scale",)).model.bias_walk_piece_s is None
    assert cfg.model.bias_walk_piece_s == 5.0  # the input is not changed
