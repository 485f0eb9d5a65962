"""The forward selection gives a rival that lost to an effect kept a second chance: the loop of
:func:`licalib_cli.pipeline.diagnose.diagnose` with every fit replaced by a scripted one."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from diagnosis_steps import diagnosis_step

import licalib_cli.pipeline.diagnose as dg
from licalib_cli.config import load_config
from licalib_cli.consistency import EffectScore
from licalib_cli.pipeline.diagnosis_step import DiagnosisStep
from licalib_cli.pipeline.rivals import CandidatePool
from licalib_cli.pipeline.scan_pattern import SPINNING, ScanPattern


def _evidence(
    name: str,
    statistic: float,
    p: float,
    explained_by: dict[str, float] | None = None,
    rank: int = 15,
) -> Any:
    """A candidate's evidence: its score test (``rank`` degrees of freedom) alone, and the
    shares of its score the others explain."""
    z = np.zeros(rank)
    return SimpleNamespace(
        score=EffectScore(name, statistic, rank, p, z, z, z, z),
        statistic_alone=statistic,
        explained_by=explained_by or {},
        selected=False,
    )


def _run(*effects: Any) -> Any:
    return SimpleNamespace(effects=list(effects), rounds=[])


def _step(effect: str, delta_bic: float, rival_bic: float, after: Any) -> DiagnosisStep:
    return diagnosis_step(
        effect=effect,
        dof=15,
        p_value=0.0,
        delta_bic=delta_bic,
        kept=delta_bic < 0.0,
        estimate={},
        rival_delta_bic=rival_bic,
        after=after,
    )


class _Imu:
    t_ns = np.array([0, 10_000_000_000])

    def __len__(self) -> int:
        return 2


def _diagnose(
    monkeypatch: pytest.MonkeyPatch,
    base: Any,
    refits: dict[str, Any],
    pattern: ScanPattern = SPINNING,
    allowed: list[tuple[str, ...]] | None = None,
) -> Any:
    """``diagnose`` on scripted fits: ``refits[name](run)`` is the step of refitting ``name``
    on ``run``; ``allowed`` receives the candidates the diagnosis reports on."""
    monkeypatch.setattr(
        dg,
        "prepare",
        lambda bag, cfg, *a, **k: SimpleNamespace(
            rec=SimpleNamespace(imu=_Imu()), guess=None, cfg=cfg, pattern=pattern
        ),
    )
    monkeypatch.setattr(dg, "fit_and_check", lambda *a, **k: base)
    monkeypatch.setattr(dg, "twin_of", lambda run, cfg: None)

    def refit_with(evidence: Any, *, run: Any, **_: Any) -> Any:
        return lambda cfg: refits[evidence.score.name](run)

    monkeypatch.setattr(dg, "_refit_with", refit_with)
    monkeypatch.setattr(dg, "sized_refit", lambda step, score, refit, cfg: (step, cfg))
    monkeypatch.setattr(dg, "with_sizes_of", lambda cfg, others: cfg)
    monkeypatch.setattr(dg, "compare_rivals", lambda trials, kept, cfg, samples: trials)
    monkeypatch.setattr(dg, "sensor_samples", lambda run, sensor: 1000)
    monkeypatch.setattr(dg, "drop_redundant", lambda kept, deltas, refit: [])
    seen = allowed if allowed is not None else []
    monkeypatch.setattr(dg, "_not_shown", lambda run, allowed, found: seen.append(allowed) or ())
    monkeypatch.setattr(dg, "noise_spread", lambda prepared, run, cfg, progress, timer: run)
    return dg.diagnose("bag.bag", load_config(None))


ELEVATION, OFFSET = "lidar_elevation", "lidar_vertical_offset"


def test_a_rival_the_fit_with_its_winner_still_shows_is_refitted_and_kept(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The paper's case: the elevations win against the vertical offsets (their rival, 0.93 of
    the elevations' score), and with the elevations in the offsets still show (1748 on 15)."""
    done = _run()
    with_elevation = _run(_evidence(OFFSET, 1748.3, 0.0, {}))
    base = _run(
        _evidence(ELEVATION, 49495.5, 0.0, {OFFSET: 0.93}),
        _evidence(OFFSET, 47613.0, 0.0, {ELEVATION: 0.9}),
    )
    refits = {
        ELEVATION: lambda run: _step(ELEVATION, -53206.7, -1143.5, with_elevation),
        OFFSET: lambda run: (
            _step(OFFSET, -47955.4, 1143.5, _run())
            if run is base
            else _step(OFFSET, -758.6, float("nan"), done)
        ),
    }
    diag = _diagnose(monkeypatch, base, refits)
    assert diag.effects_found == (ELEVATION, OFFSET)
    assert [(s.effect, s.kept, s.rival_named, s.retried_after) for s in diag.steps] == [
        (OFFSET, False, ELEVATION, ""),
        (ELEVATION, True, "", ""),
        (OFFSET, True, "", ELEVATION),
    ]
    assert diag.final is done


def test_a_rival_that_only_echoed_its_winner_is_not_refitted_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With the elevations in, the offsets' test is that of noise: no second refit; nor when
    the winner was not kept."""
    with_elevation = _run(_evidence(OFFSET, 14.0, 0.45, {}))
    base = _run(
        _evidence(ELEVATION, 49495.5, 0.0, {OFFSET: 0.93}),
        _evidence(OFFSET, 47613.0, 0.0, {ELEVATION: 0.9}),
    )
    calls: list[str] = []

    def refit(name: str, delta: float, rival_bic: float) -> Any:
        def run_it(run: Any) -> DiagnosisStep:
            calls.append(name)
            return _step(name, delta, rival_bic, with_elevation)

        return run_it

    refits = {ELEVATION: refit(ELEVATION, -53206.7, -1.0), OFFSET: refit(OFFSET, -47955.4, 1.0)}
    diag = _diagnose(monkeypatch, base, refits)
    assert diag.effects_found == (ELEVATION,) and calls == [ELEVATION, OFFSET]

    calls.clear()
    unpaid = {ELEVATION: refit(ELEVATION, 30.0, -1.0), OFFSET: refit(OFFSET, 40.0, 1.0)}
    diag = _diagnose(monkeypatch, base, unpaid)
    assert diag.effects_found == () and calls == [ELEVATION, OFFSET]
    assert [s.kept for s in diag.steps] == [False, False]


def test_a_rival_that_lost_to_an_effect_kept_is_offered_once_more() -> None:
    """On the paper's case (every intrinsic off) the elevations won against the vertical
    offsets; with the elevations in, the offsets' test was still 1748 on 15 degrees of freedom.
    A candidate tried before is not offered again, unless it is a rival that lost to an effect
    kept: it stays on offer while significant given the winner, once; one the data do not
    determine (rank 0) or not allowed is never offered."""

    def names(found: list[Any]) -> list[str]:
        return [e.score.name for e in found]

    pool = CandidatePool(("lidar_elevation", "lidar_vertical_offset", "gyro_scale", "accel_scale"))
    base = [
        _evidence("lidar_elevation", 49495.5, 0.0),
        _evidence("lidar_vertical_offset", 47613.0, 0.0),
        _evidence("gyro_scale", 3.1, 0.38, rank=3),
        _evidence("accel_scale", 347.4, 1e-70, rank=3),
        _evidence("lidar_point_time", 1e4, 0.0, rank=1),  # not allowed
        _evidence("lidar_azimuth", 0.0, 1.0, rank=0),  # not determined
    ]
    options, significant = pool.offered(base)
    assert names(options) == [
        "lidar_elevation",
        "lidar_vertical_offset",
        "gyro_scale",
        "accel_scale",
    ]
    assert names(significant) == ["lidar_elevation", "lidar_vertical_offset", "accel_scale"]
    assert pool.refitting("lidar_elevation") is None
    assert pool.refitting("lidar_vertical_offset") is None
    pool.decided(["lidar_vertical_offset"], "lidar_elevation", kept=True)
    # with the elevations in: the offsets still show, and are offered
    with_elevation = [
        _evidence("lidar_vertical_offset", 1748.3, 0.0),
        _evidence("gyro_scale", 3.1, 0.38, rank=3),
        _evidence("accel_scale", 340.0, 1e-70, rank=3),
    ]
    options, significant = pool.offered(with_elevation)
    assert names(significant) == ["lidar_vertical_offset", "accel_scale"]
    # the accelerometer scale is tried first: the offsets keep their chance while they show
    assert pool.refitting("accel_scale") is None
    pool.decided([], "accel_scale", kept=True)
    options, significant = pool.offered(with_elevation[:2])
    assert names(significant) == ["lidar_vertical_offset"]
    assert pool.refitting("lidar_vertical_offset") == "lidar_elevation"
    # tried twice: never again, even when it lost once more to an effect kept
    pool.decided(["lidar_vertical_offset"], "gyro_scale", kept=True)
    assert pool.offered(with_elevation)[0] == [with_elevation[1]]

    # a rival that only echoed its winner is not significant given it, and leaves the pool
    echo = CandidatePool(("lidar_elevation", "lidar_vertical_offset"))
    echo.refitting("lidar_elevation")
    echo.refitting("lidar_vertical_offset")
    echo.decided(["lidar_vertical_offset"], "lidar_elevation", kept=True)
    assert echo.offered([_evidence("lidar_vertical_offset", 20.0, 0.2)])[1] == []
    assert echo.offered([_evidence("lidar_vertical_offset", 1748.3, 0.0)])[0] == []
    # a rival that lost to an effect not kept (neither paid) gets no second chance
    unpaid = CandidatePool(("lidar_elevation", "lidar_vertical_offset"))
    unpaid.refitting("lidar_elevation")
    unpaid.refitting("lidar_vertical_offset")
    unpaid.decided(["lidar_vertical_offset"], "lidar_elevation", kept=False)
    assert unpaid.offered([_evidence("lidar_vertical_offset", 1748.3, 0.0)])[0] == []


def test_a_non_repetitive_scanner_is_not_diagnosed_for_per_beam_intrinsics(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A Livox's lines have no intrinsics: the per-beam candidates are neither tried nor
    reported as effects the bag does not show."""
    base = _run(_evidence(ELEVATION, 49495.5, 0.0, {}))
    allowed: list[tuple[str, ...]] = []
    lines = ScanPattern("non_repetitive", 20.0, "data")
    diag = _diagnose(monkeypatch, base, {}, pattern=lines, allowed=allowed)
    assert diag.effects_found == () and diag.steps == ()
    (reported,) = allowed
    assert "lidar_point_time" in reported and "gyro_scale" in reported
    assert not set(reported) & dg.PER_BEAM_CANDIDATES
    assert dg.PER_BEAM_CANDIDATES == {
        "lidar_range_offset",
        "lidar_range_scale",
        "lidar_elevation",
        "lidar_azimuth",
        "lidar_vertical_offset",
        "lidar_horizontal_offset",
    }
