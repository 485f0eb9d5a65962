"""A significant effect that does not pay its BIC penalty: how well the bag determines it, how
much more data would add it, and a per-beam effect tried as one spread across beams."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from diagnosis_steps import diagnosis_step

from licalib_cli.commands.diagnose import diagnosis_dict, unpaid_sentence
from licalib_cli.pipeline.diagnosis_step import (
    DiagnosisStep,
    Gap,
    data_to_pay,
    unpaid_effect,
)


def _per_beam_gain(rng: np.random.Generator, beta: np.ndarray, n: int) -> float:
    """The drop in the sum of squares (unit noise) when ``beta`` is fitted: each sample sees
    one beam, ``y = beta[beam] x + noise`` (a per-beam effect, as a per-beam range scale)."""
    k = beta.size
    beam = rng.integers(0, k, size=n)
    x = rng.normal(size=n)
    y = beta[beam] * x + rng.normal(size=n)
    xy = np.bincount(beam, weights=x * y, minlength=k)
    xx = np.bincount(beam, weights=x * x, minlength=k)
    return float(np.sum(xy**2 / xx))


def test_the_data_factor_is_where_the_bic_starts_to_pay() -> None:
    """16 per-beam numbers of 1.4 sigmas each on 2000 samples: significant together, not worth
    their penalty; at the factor the BIC change averages zero, a quarter of it never pays, four
    times it nearly always does, and the factor estimated from one draw is close to the true."""
    rng = np.random.default_rng(30)
    k, n = 16, 2000
    beta = np.full(k, 1.4 / math.sqrt(n / k)) * rng.choice([-1.0, 1.0], size=k)
    noncentrality = float(np.sum(beta**2) * n / k)
    m = data_to_pay(k + noncentrality, k, k, math.log(n))
    assert 3.0 < m < 10.0

    def bic_changes(factor: float, runs: int = 300) -> np.ndarray:
        size = round(factor * n)
        return np.array([k * math.log(size) - _per_beam_gain(rng, beta, size) for _ in range(runs)])

    at = bic_changes(m)
    assert abs(at.mean()) < 3.0 * at.std() / math.sqrt(at.size)
    assert np.mean(bic_changes(m / 4) < 0.0) < 0.2
    assert np.mean(bic_changes(4 * m) < 0.0) > 0.8
    base = bic_changes(1.0, 100)
    assert np.mean(base < 0.0) < 0.1  # the bag itself: not worth it
    estimated = [data_to_pay(k * math.log(n) - d, k, k, math.log(n)) for d in base]
    assert 0.6 * m < float(np.median(estimated)) < 1.6 * m


def test_data_to_pay_edges() -> None:
    assert data_to_pay(100.0, 3, 3, 8.0) == 1.0  # already pays
    assert data_to_pay(2.0, 3, 3, 8.0) == math.inf  # nothing beyond noise
    assert data_to_pay(3.0 + 1e-9, 3, 3, 8.0) == math.inf  # a million times would not do
    m = data_to_pay(40.0, 9, 9, 8.7)
    assert 9 + m * 31 == pytest.approx(9 * (8.7 + math.log(m)))


def _step(**kw: object) -> DiagnosisStep:
    return diagnosis_step(**kw)


def test_a_significant_effect_that_did_not_pay_is_explained() -> None:
    step = _step()
    u = step.unpaid
    assert u is not None
    assert u.coordinates == 64 and u.gain == pytest.approx(64 * 12.0 - 600.0)
    assert u.sigmas_each == pytest.approx(math.sqrt((168.0 - 64.0) / 64.0))
    assert u.sigmas_to_pay == pytest.approx(math.sqrt(11.0))
    assert 1.0 < u.data_factor < math.inf
    text = unpaid_sentence(step)
    assert text is not None
    assert text.startswith("lidar_range_scale shows in this bag (score 192 on 64, p = 9e-15)")
    assert "each of its 64 numbers is about 1.3 of its sigma from nominal on average" in text
    assert f"It would pay with about {u.data_factor:.1f} times the information" in text
    assert "surfels.max_points" in text  # a LiDAR effect: a round's points are capped
    assert "the extrinsic moved 0.80 mm / 0.0040 deg / 0.020 ms" in text
    one = _step(
        effect="imu_clock_drift",
        dof=1,
        statistic=30.0,
        delta_bic=2.0,
        bic_log_n=9.0,
        estimate={"ext.clock_drift": (1e-5, 2e-6)},
    )
    imu = replace(one, gap_before=Gap("gyro", 0.9, 0.88, 0.003))
    text = unpaid_sentence(imu) or ""
    assert "its number is about" in text and "more samples that see it" in text
    assert "surfels.max_points" not in text
    apart = unpaid_sentence(replace(step, not_told_apart=("lidar_range_offset",))) or ""
    assert "(score 192 on 64, p = 9e-15; this bag does not tell it from lidar_range_offset)" in (
        apart
    )


def test_nothing_is_explained_for_an_effect_that_paid_was_dropped_or_was_not_significant() -> None:
    step = _step()
    assert replace(step, kept=True, delta_bic=-20.0).unpaid is None
    assert replace(step, delta_bic=-5.0).unpaid is None  # a rival that paid and lost
    assert replace(step, dropped_for=("lidar_range_offset",)).unpaid is None
    assert replace(step, rival_named="lidar_range_offset").unpaid is None  # its rival explains it
    assert replace(step, final_p_value=0.3).unpaid is None  # an effect added later explains it
    assert replace(step, final_p_value=1e-9).unpaid is not None  # still shows on the final fit
    assert replace(step, p_value=0.2).unpaid is None
    assert replace(step, bic_log_n=float("nan")).unpaid is None
    assert unpaid_sentence(replace(step, kept=True, delta_bic=-20.0)) is None
    assert unpaid_effect(600.0, 0, 64, 12.0, 1e-9) is None


def _steps_dict(monkeypatch: pytest.MonkeyPatch, *steps: DiagnosisStep) -> list[dict]:
    """``diagnosis_dict``'s steps of a diagnosis made of ``steps``."""
    from types import SimpleNamespace

    import licalib_cli.commands.diagnose as cmd

    diag = SimpleNamespace(
        steps=steps,
        not_shown=(),
        effects_found=(),
        base=SimpleNamespace(verdict=SimpleNamespace(status="warn")),
        final=SimpleNamespace(
            verdict=SimpleNamespace(status="pass"),
            result=SimpleNamespace(to_dict=lambda: {}),
        ),
        base_twin=None,
        final_twin=None,
        beams_in_base=None,
    )
    monkeypatch.setattr(cmd, "_residuals", lambda run, twin: {})
    return list(diagnosis_dict(diag)["steps"])


def test_the_diagnosis_file_carries_it(monkeypatch: pytest.MonkeyPatch) -> None:
    paid = _step(kept=True, delta_bic=-30.0)
    first, second = _steps_dict(monkeypatch, paid, _step())
    assert first["unpaid"] is None and first["spread"] is None
    assert second["unpaid"]["coordinates"] == 64
    assert second["unpaid"]["bic_penalty_per_coordinate"] == 12.0
    assert 1.0 < second["unpaid"]["data_factor"] < 1e6


def _score_of(statistic_per_dof: float, k: int = 64) -> object:
    """A per-beam group's score (unit information) whose statistic is ``statistic_per_dof`` per
    degree of freedom, spread evenly."""
    from licalib_cli.consistency.score import EffectScore

    g = np.full(k, math.sqrt(statistic_per_dof))
    return EffectScore(
        name="lidar_range_scale",
        statistic=float(g @ g),
        rank=k,
        p_value=1e-14,
        estimate=g,
        sigma=np.ones(k),
        shift=np.zeros(7),
        shift_sigma=np.zeros(7),
        gradient=g,
        profiled_information=np.eye(k),
    )


def test_a_per_beam_effect_that_did_not_pay_is_tried_as_one_spread() -> None:
    from licalib_cli.pipeline.diagnose import spread_worth_trying

    step = _step()
    spread = spread_worth_trying(step, _score_of(3.0))  # type: ignore[arg-type]
    assert spread is not None
    # unit information, c = 3 on every beam: L(t) = 32 (3 t / (1 + t) - ln(1 + t)), max at t = 2
    assert spread.sigma == pytest.approx(math.sqrt(2.0), rel=1e-4)
    assert spread.delta_bic(12.0) == pytest.approx(-64 * (2.0 - math.log(3.0)) + 12.0, rel=1e-6)
    # not when the numbers paid, an IMU effect, not significant, or one spread would not pay
    assert spread_worth_trying(replace(step, kept=True), _score_of(3.0)) is None  # type: ignore[arg-type]
    assert spread_worth_trying(replace(step, effect="gyro_scale"), _score_of(3.0)) is None  # type: ignore[arg-type]
    assert spread_worth_trying(replace(step, p_value=1e-3), _score_of(3.0)) is None  # type: ignore[arg-type]
    assert spread_worth_trying(step, _score_of(1.1)) is None  # type: ignore[arg-type]


def test_the_final_config_keeps_the_spreads_of_the_effects_kept() -> None:
    from licalib_cli.config import CalibConfig
    from licalib_cli.pipeline.effect_models import final_config, with_spread

    cfg = with_spread(CalibConfig(), "lidar_range_scale", 1.2e-4)
    cfg = with_spread(cfg, "lidar_elevation", math.radians(0.01))
    out = final_config(cfg, ("gyro_scale", "lidar_range_scale"))
    assert out.model.imu == ["gyro_scale"] and out.model.lidar == ["range_scale"]
    assert out.model.lidar_spread.range_scale == pytest.approx(1.2e-4)
    assert out.model.lidar_spread.elevation_deg is None  # not kept: its spread is not the model's
    assert final_config(cfg, ()).model.lidar_spread.configured(["range_scale"]) == {}


def test_the_spread_is_said_and_written() -> None:
    from licalib_cli.commands.diagnose import _spread_dict, spread_sentence

    kept = _step(kept=True, delta_bic=370.0, spread=1.09e-4, spread_delta_bic=-230.0)
    text = spread_sentence(kept) or ""
    assert text.startswith("lidar_range_scale was added as one spread across beams")
    assert "as 64 free numbers it did not pay (BIC +370)" in text
    assert "a spread of 109 ppm" in text and "(BIC -230, one parameter)" in text
    assert _spread_dict(kept) == {"value": 109.0, "unit": "ppm", "delta_bic": -230.0, "kept": True}
    assert kept.unpaid is None
    failed = _step(spread=5e-5, spread_delta_bic=14.0)
    assert spread_sentence(failed) == (
        "As one spread across beams (50 ppm) lidar_range_scale did not pay either (BIC +14)."
    )
    assert failed.unpaid is not None  # the free numbers' explanation still holds
    assert spread_sentence(_step()) is None and _spread_dict(_step()) is None


def _elevation_step(n: int = 300_000) -> DiagnosisStep:
    """1437's per-beam elevation step: added first, it closed 15 % of the LiDAR gap."""
    return _step(
        effect="lidar_elevation",
        kept=True,
        gap_before=Gap("lidar", 1.303, 1.0, 0.02, twin_chi2_per_sample=0.973, samples=n),
        gap_after=Gap("lidar", 1.252, 1.0, 0.02, twin_chi2_per_sample=0.973, samples=n),
    )


def test_a_share_is_the_gap_an_effect_closes_with_the_others_in(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """1437's elevation: added before the gyro rotation it closed 15 % of a LiDAR gap that was
    mostly the rotation's; with the rotation in, taking it out reopens a gap it closes whole."""
    from licalib_cli.commands.diagnose import _gap_text

    n = 300_000
    step = _elevation_step(n)
    assert step.shrink == pytest.approx(1.0 - 0.279 / 0.330, abs=1e-3)
    assert math.isnan(step.share)  # no other effect in the final model
    (alone,) = _steps_dict(monkeypatch, step)
    assert alone["share_gap_before"] is None and alone["share_shrink"] is None
    assert _gap_text(step) == "lidar: +0.330 -> +0.279"
    shared = replace(
        step,
        share_before=Gap("lidar", 1.04, 1.0, 0.01, twin_chi2_per_sample=0.973, samples=n),
        share_after=Gap("lidar", 0.97, 1.0, 0.01, twin_chi2_per_sample=0.973, samples=n),
    )
    assert shared.share == pytest.approx(1.0)  # its excess below the twin's: all closed
    assert shared.share_after is not None and shared.share_before is not None
    half = replace(shared, share_after=replace(shared.share_after, chi2_per_sample=1.0065))
    assert half.share == pytest.approx(0.5, abs=1e-3)
    # a gap within three of its noise sigmas cannot be seen to close
    within = replace(shared, share_before=replace(shared.share_before, chi2_per_sample=0.9745))
    assert math.isnan(within.share)
    assert _gap_text(shared) == (
        "lidar: +0.330 -> +0.279; with the other effects in +0.067 -> -0.003"
    )
    (row,) = _steps_dict(monkeypatch, shared)
    assert row["share_shrink"] == pytest.approx(1.0)
    assert row["share_gap_before"]["excess"] == pytest.approx(0.067)
    assert row["gap_shrink"] == pytest.approx(0.155, abs=1e-3)


def test_a_share_is_measured_for_a_step_that_closed_less_than_half_among_several() -> None:
    from licalib_cli.pipeline.diagnose import wants_share

    low = _elevation_step()
    pair = ("lidar_elevation", "gyro_rotation")
    assert wants_share(low, pair)
    assert not wants_share(low, ("lidar_elevation",))  # alone: its step measured the same
    assert not wants_share(low, ("gyro_rotation", "gyro_scale"))  # dropped from the model
    assert not wants_share(replace(low, kept=False), pair)
    closed = replace(low, gap_after=replace(low.gap_after, chi2_per_sample=0.98))
    assert not wants_share(closed, pair)  # its own step closed it
    quiet = replace(low, gap_before=replace(low.gap_before, chi2_per_sample=0.975))
    assert math.isnan(quiet.shrink) and not wants_share(quiet, pair)  # no gap to share


def test_a_rival_named_in_place_of_the_leader_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bag 1837's step: the gyro rotation, refitted as the rival of the accelerometer
    misalignment (it explained 0.83 of its score), named in its place."""
    from licalib_cli.commands.diagnose import rival_sentence

    picked = _step(
        effect="gyro_rotation",
        kept=True,
        delta_bic=-157982.0,
        rival_delta_bic=-32006.0,
        rival_of="accel_misalignment",
        rival_share=0.83,
    )
    text = rival_sentence(picked) or ""
    assert text.startswith("gyro_rotation was named in place of accel_misalignment")
    assert "explains 83 % of its score" in text
    assert text.endswith("on the same data its BIC is 32006.0 lower.")
    # the pick by paying where the leader does not
    paying = replace(picked, rival_delta_bic=4.0, delta_bic=-20.0)
    assert (rival_sentence(paying) or "").endswith(
        "it pays its BIC (-20.0) where accel_misalignment does not."
    )
    # the leader, a rival not kept, a pair not told apart: nothing to say
    assert rival_sentence(_step(kept=True, delta_bic=-30.0)) is None
    assert rival_sentence(replace(picked, kept=False)) is None
    assert rival_sentence(replace(picked, not_told_apart=("accel_misalignment",))) is None
    row, leader = _steps_dict(monkeypatch, picked, _step(kept=True, delta_bic=-30.0))
    assert row["rival_of"] == "accel_misalignment" and row["rival_share"] == pytest.approx(0.83)
    assert leader["rival_of"] is None and leader["rival_share"] is None


def test_a_rival_tried_again_with_its_winner_in_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """The paper's case on a 15 s VLP-16 sinusoid: the vertical offsets lost to the elevations
    as their rival, and with the elevations in their score test was still 1767.6 on 15."""
    from licalib_cli.commands.diagnose import retried_sentence

    lost = _step(effect="lidar_vertical_offset", rival_of="lidar_elevation", delta_bic=-47955.4)
    lost = replace(lost, rival_named="lidar_elevation")
    again = _step(
        effect="lidar_vertical_offset",
        statistic=1767.6,
        dof=15,
        kept=True,
        delta_bic=-758.6,
        retried_after="lidar_elevation",
    )
    text = retried_sentence(again) or ""
    assert text.startswith(
        "lidar_vertical_offset lost to lidar_elevation as its rival, and was tried again with "
        "lidar_elevation in: its score test was still 1767.6 on 15 degrees of freedom"
    )
    assert text.endswith("it paid too (BIC -758.6): both are in the model.")
    unpaid = retried_sentence(replace(again, kept=False, delta_bic=12.0)) or ""
    assert unpaid.endswith("it did not pay (BIC +12.0).")
    assert retried_sentence(lost) is None
    first, second = _steps_dict(monkeypatch, lost, again)
    assert first["retried_after"] is None and first["rival_named"] == "lidar_elevation"
    assert second["retried_after"] == "lidar_elevation" and second["kept"]


def test_the_steps_table_keeps_every_effect_name_whole_at_80_columns() -> None:
    """A range scale and a range offset both read "lidar_ra..." when the table cut the names
    to fit an 80-column console; folded, each name is whole once the cell's lines are joined."""
    from rich.console import Console

    from licalib_cli.commands.diagnose import steps_table

    names = ["lidar_range_scale", "lidar_range_offset", "lidar_horizontal_offset"]
    rows = [_step(effect=n, statistic=78694.0, dof=16, delta_bic=-212068.0) for n in names]
    out = Console(width=80, record=True, color_system=None)
    out.print(steps_table(rows))
    text = out.export_text()
    assert "…" not in text
    first_cells = [line.split("│")[1].strip() for line in text.splitlines() if line.startswith("│")]
    joined = "".join(first_cells)
    for n in names:
        assert n in joined
    assert joined.index(names[0]) < joined.index(names[1]) < joined.index(names[2])
