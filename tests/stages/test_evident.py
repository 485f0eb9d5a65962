"""Effects the data show beyond doubt, estimated (``licalib_cli.pipeline.evident``).

The stage refits with every unmistakable effect estimated, keeps the refit when it pays its BIC
(else tries those of the strongest's sensor, then the strongest alone), and goes on from the
refit's checks; a refit that does not pay (or does not converge) ends the search and hands its
estimate to the shift measurement; a fit whose rounds did not converge is refitted too. The fits
here are stand-ins: the stage's own decisions are what is tested (the end-to-end run on a
simulated bag is in ``tests/integration/test_checks_e2e.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np
import pytest
from finished_runs import finished_run
from held_effects import scored_effect

from licalib_cli.config import load_config
from licalib_cli.errors import SolverError
from licalib_cli.filetypes import FileValueError
from licalib_cli.geometry import so3
from licalib_cli.pipeline import evident, rivals
from licalib_cli.pipeline.checks import Finding
from licalib_cli.pipeline.effect_refit import REFIT_STATISTIC_PER_DOF
from licalib_cli.pipeline.fitcheck import EffectEvidence
from licalib_cli.sections import AddedEffect, ModelInfo


def _evidence(name: str, per_dof: float, rank: int = 3) -> EffectEvidence:
    return scored_effect(name, per_dof, rank=rank, shift_z_mm=0.0)


def _state(tz: float) -> SimpleNamespace:
    return SimpleNamespace(
        t_imu_lidar=np.array([0.1, 0.2, tz]), R_imu_lidar=so3.exp(np.zeros(3)), time_offset_s=0.0
    )


@dataclass
class _Run:
    """A stand-in for a calibration run: its estimate and the effects its checks show."""

    tz: float
    effects: tuple[EffectEvidence, ...] = ()
    status: str = "ok"
    reasons: tuple[str, ...] = ()
    result: SimpleNamespace = field(
        default_factory=lambda: SimpleNamespace(model=ModelInfo(("gyro_scale",)))
    )

    @property
    def state(self) -> SimpleNamespace:
        return _state(self.tz)

    @property
    def checks(self) -> SimpleNamespace:
        return SimpleNamespace(
            effects=self.effects,
            exit_status=self.status,
            findings=(Finding("warn", "w"),),
            verdict=SimpleNamespace(reasons=self.reasons),
        )


class _Refits:
    """The refits the stage asks for, answered from a table: the model's blocks (IMU then
    LiDAR, as listed) -> (run, BIC)."""

    def __init__(
        self,
        table: dict[tuple[str, ...], tuple[_Run, float]],
        redundant: dict[tuple[str, ...], tuple[tuple[str, ...], dict[str, float]]] | None = None,
    ) -> None:
        self.table = table
        self.redundant = redundant or {}  # refit's blocks -> effects the others explain
        self.asked: list[tuple[str, ...]] = []
        self.starts: list[object] = []

    def install(self, monkeypatch: pytest.MonkeyPatch) -> None:
        def fit_and_check(prepared, start, cfg, progress, timer, *, warm, rivals):  # type: ignore[no-untyped-def]
            assert warm and rivals  # the refits' checks size the next one's rivals
            blocks = (*cfg.model.imu, *cfg.model.lidar)
            self.asked.append(blocks)
            self.starts.append(start.state)
            fit = self.table[blocks][0]
            if isinstance(fit, Exception):  # the refit itself fails
                raise fit
            return fit

        def bic_terms(new, new_cfg, others):  # type: ignore[no-untyped-def]
            blocks = (*new_cfg.model.imu, *new_cfg.model.lidar)
            return [(self.table[blocks][1], 0)]

        def redundant(refit, refit_cfg, names, start, model_without):  # type: ignore[no-untyped-def]
            blocks = (*refit_cfg.model.imu, *refit_cfg.model.lidar)
            return self.redundant.get(blocks, ((), {}))

        monkeypatch.setattr(evident, "fit_and_check", fit_and_check)
        monkeypatch.setattr(evident, "redundant", redundant)
        monkeypatch.setattr(evident, "without_all", lambda state, out, start: ("without", out))
        monkeypatch.setattr(evident, "bic_terms", bic_terms)
        monkeypatch.setattr(evident, "sensor_samples", lambda run, sensor: 1000)


@dataclass(frozen=True)
class _Guess:
    state: object = None


PREPARED = SimpleNamespace(guess=_Guess())
STRONG = 3.0 * REFIT_STATISTIC_PER_DOF


def _add(run: _Run, cfg_model: dict | None = None) -> evident.Evident:
    cfg = load_config(None, cfg_model or {})
    return evident.add_evident(PREPARED, run, cfg, None, None)  # type: ignore[arg-type]


def test_the_unmistakable_effects_are_added_together_and_the_search_goes_on(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    base = _Run(
        0.30,
        (
            _evidence("gyro_scale", 0.5 * REFIT_STATISTIC_PER_DOF),
            _evidence("lidar_elevation", 1.5 * REFIT_STATISTIC_PER_DOF, rank=15),
            _evidence("lidar_range_offset", STRONG, rank=16),
        ),
    )
    with_lidar = _Run(0.31, (_evidence("accel_misalignment", STRONG),))
    with_all = _Run(0.312, (_evidence("gyro_scale", 2.0),))
    refits = _Refits(
        {
            ("range_offset", "elevation"): (with_lidar, -500.0),
            ("accel_misalignment", "range_offset", "elevation"): (with_all, -40.0),
        }
    )
    refits.install(monkeypatch)
    out = _add(base)
    assert refits.asked == [
        ("range_offset", "elevation"),
        ("accel_misalignment", "range_offset", "elevation"),
    ]
    assert out.run is with_all and out.declined is None
    assert [(a.effect, a.refit) for a in out.added] == [
        ("lidar_range_offset", 1),
        ("lidar_elevation", 1),
        ("accel_misalignment", 2),
    ]
    assert out.cfg.model.lidar == ["range_offset", "elevation"]
    assert out.cfg.model.imu == ["accel_misalignment"]
    first = out.added[0]
    assert first.statistic == pytest.approx(16 * STRONG) and first.dof == 16
    assert first.delta_bic == pytest.approx(-500.0) == out.added[1].delta_bic
    assert first.moved_translation_m == pytest.approx(0.01)
    assert out.added[2].moved_translation_m == pytest.approx(0.002)


def test_when_the_group_does_not_pay_the_strongest_alone_is_tried(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    base = _Run(
        0.30, (_evidence("accel_scale", 2 * STRONG), _evidence("lidar_range_offset", STRONG, 16))
    )
    alone = _Run(0.32)
    refits = _Refits(
        {
            ("accel_scale", "range_offset"): (_Run(0.33), +5.0),
            ("accel_scale",): (alone, -60.0),
        }
    )
    refits.install(monkeypatch)
    out = _add(base)
    assert refits.asked == [("accel_scale", "range_offset"), ("accel_scale",)]
    assert out.run is alone and [a.effect for a in out.added] == ["accel_scale"]


def test_a_group_that_fails_is_followed_by_the_strongest_sensors_effects_together(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a gyro-to-IMU rotation on a shake that hardly tilted leaves the extrinsic rotation
    # undetermined: the per-beam errors shown with it are refitted without it
    base = _Run(
        0.30,
        (
            _evidence("lidar_range_offset", 4 * STRONG, rank=16),
            _evidence("gyro_rotation", 2 * STRONG),
            _evidence("lidar_elevation", STRONG, rank=15),
        ),
    )
    failed = _Run(0.31, status="fail", reasons=("The data determine only 1 of the 7 ...",))
    lidar = _Run(0.32)
    refits = _Refits(
        {
            ("gyro_rotation", "range_offset", "elevation"): (failed, -9e4),
            ("range_offset", "elevation"): (lidar, -8e4),
        }
    )
    refits.install(monkeypatch)
    out = _add(base)
    assert refits.asked == [
        ("gyro_rotation", "range_offset", "elevation"),
        ("range_offset", "elevation"),
    ]
    assert out.run is lidar
    assert [a.effect for a in out.added] == ["lidar_range_offset", "lidar_elevation"]
    # the strongest's sensor shows nothing else: its group is the strongest alone, tried once
    only = _Run(
        0.30, (_evidence("accel_scale", 2 * STRONG), _evidence("lidar_azimuth", STRONG, 15))
    )
    refits = _Refits(
        {("accel_scale", "azimuth"): (failed, -9e4), ("accel_scale",): (_Run(0.31), +3.0)}
    )
    refits.install(monkeypatch)
    out = _add(only)
    assert refits.asked == [("accel_scale", "azimuth"), ("accel_scale",)]
    assert out.added == () and out.declined is not None and out.declined[0] == "accel_scale"


def test_a_refit_that_does_not_pay_is_declined_and_its_estimate_kept_for_the_shift(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    base = _Run(0.30, (_evidence("lidar_range_offset", STRONG, rank=15),))
    refit = _Run(0.33)
    _Refits({("range_offset",): (refit, +12.0)}).install(monkeypatch)
    out = _add(base)
    assert out.run is base and out.added == () and out.cfg.model.lidar == []
    assert out.declined is not None and out.declined[0] == "lidar_range_offset"
    assert out.declined[1].t_imu_lidar[2] == pytest.approx(0.33)


def test_a_refit_that_does_not_converge_is_declined(monkeypatch: pytest.MonkeyPatch) -> None:
    base = _Run(0.30, (_evidence("accel_scale", STRONG),))
    _Refits({("accel_scale",): (_Run(0.31, status="not converged"), -900.0)}).install(monkeypatch)
    out = _add(base)
    assert out.run is base and out.added == () and out.declined is not None


def test_an_effect_whose_refit_fails_where_the_fit_without_it_did_not_stays_held(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a gyro rotation beside the extrinsic rotation on a shake that hardly tilted: estimated,
    # the extrinsic rotation is no longer determined
    base = _Run(0.30, (_evidence("gyro_rotation", STRONG),))
    reasons = ("The data determine only 1 of the 7 extrinsic coordinates: each of the others ...",)
    failed = _Run(0.301, status="fail", reasons=reasons)
    _Refits({("gyro_rotation",): (failed, -900.0)}).install(monkeypatch)
    out = _add(base)
    assert out.run is base and out.added == () and out.cfg.model.imu == []
    assert out.declined is not None and out.declined[0] == "gyro_rotation"
    assert out.notes == (
        "The data show gyro_rotation beyond doubt, but estimating it failed the calibration "
        "(the data determine only 1 of the 7 extrinsic coordinates); it stays held fixed, the "
        "shift in the sigmas.",
    )
    # a fit that failed already may take a refit that fails too: neither is kept, nothing said
    out = _add(replace(base, status="fail"))
    assert out.added == () and out.notes == ()


def test_nothing_is_tried_without_an_unmistakable_effect(monkeypatch: pytest.MonkeyPatch) -> None:
    refits = _Refits({})
    refits.install(monkeypatch)
    weak = _Run(0.30, (_evidence("gyro_scale", 0.9 * REFIT_STATISTIC_PER_DOF),))
    assert _add(weak).run is weak
    assert _add(weak, {"model.add_evident_effects": True}).added == ()
    assert refits.asked == []


def test_a_fit_that_did_not_converge_is_refitted_and_the_note_says_the_effects_let_it_settle(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # unmodelled per-beam intrinsics blur the map and keep the rounds moving
    stuck = _Run(
        0.20,
        (_evidence("lidar_range_offset", STRONG, 32), _evidence("gyro_rotation", STRONG)),
        status="not converged",
    )
    settled = _Run(0.30)
    _Refits({("gyro_rotation", "range_offset"): (settled, -4e5)}).install(monkeypatch)
    out = _add(stuck)
    assert out.run is settled
    assert [a.effect for a in out.added] == ["lidar_range_offset", "gyro_rotation"]
    assert out.added[0].moved_translation_m == pytest.approx(0.1)
    assert out.notes == (
        "Without lidar_range_offset, gyro_rotation the rounds did not converge (the model lacked "
        "what the data show, which pulled the estimate one way and another); with them estimated "
        "they converged.",
    )
    # the next refit fails outright: what was added stays, and so does the note
    onward = _Run(0.30, (_evidence("accel_scale", STRONG),))
    _Refits(
        {
            ("gyro_rotation", "range_offset"): (onward, -4e5),
            ("gyro_rotation", "accel_scale", "range_offset"): (SolverError("diverged"), 0.0),
        }
    ).install(monkeypatch)
    out = _add(stuck)
    assert out.run is onward and len(out.added) == 2 and out.declined is None
    assert out.notes[0].startswith("Without lidar_range_offset, gyro_rotation the rounds")
    # still stuck with them: neither is kept, the fit stays as it was and nothing is noted
    again = _Run(0.25, status="not converged")
    _Refits(
        {("gyro_rotation", "range_offset"): (again, -4e5), ("range_offset",): (again, -3e5)}
    ).install(monkeypatch)
    out = _add(stuck)
    assert out.run is stuck and out.added == () and out.notes == ()
    assert out.declined is not None and out.declined[0] == "lidar_range_offset"


def test_at_most_max_passes_refits_add_effects(monkeypatch: pytest.MonkeyPatch) -> None:
    chain = ["gyro_scale", "accel_scale", "gyro_misalignment"]
    runs = {
        name: _Run(0.30 + 0.01 * (k + 1), tuple(_evidence(n, STRONG) for n in chain[k + 1 : k + 2]))
        for k, name in enumerate(chain)
    }
    refits = _Refits({tuple(chain[: k + 1]): (runs[n], -100.0) for k, n in enumerate(chain)})
    refits.install(monkeypatch)
    base = _Run(0.30, (_evidence("gyro_scale", STRONG),))
    out = _add(base)
    assert len(refits.asked) == evident.MAX_PASSES == len(out.added)
    assert [a.effect for a in out.added] == chain[: evident.MAX_PASSES]


def test_effects_the_others_explain_are_left_out_by_a_second_refit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # a fit that had not settled showed a gyro scale beside the range offsets in the data
    base = _Run(
        0.20,
        (_evidence("lidar_range_offset", 4 * STRONG, rank=16), _evidence("gyro_scale", STRONG)),
    )
    both, offsets = _Run(0.29), _Run(0.30)
    refits = _Refits(
        {("gyro_scale", "range_offset"): (both, -9e5), ("range_offset",): (offsets, -8.9e5)},
        redundant={("gyro_scale", "range_offset"): (("gyro_scale",), {"gyro_scale": 30.3})},
    )
    refits.install(monkeypatch)
    out = _add(base)
    assert refits.asked == [("gyro_scale", "range_offset"), ("range_offset",)]
    # the second refit starts where the first ended, the effect left out back at nominal
    assert refits.starts[1] == ("without", ("gyro_scale",))
    assert out.run is offsets and [a.effect for a in out.added] == ["lidar_range_offset"]
    assert out.added[0].delta_bic == pytest.approx(-8.9e5)
    assert out.cfg.model.imu == [] and out.cfg.model.lidar == ["range_offset"]
    assert out.notes == (
        "The fit before this refit also showed gyro_scale, but with lidar_range_offset "
        "estimated it explained nothing more (BIC +30 with it than without); it was left out.",
    )
    # a second refit that does not pay keeps the first, all its effects named
    refits = _Refits(
        {("gyro_scale", "range_offset"): (both, -9e5), ("range_offset",): (offsets, +5.0)},
        redundant={("gyro_scale", "range_offset"): (("gyro_scale",), {"gyro_scale": 30.3})},
    )
    refits.install(monkeypatch)
    out = _add(base)
    assert out.run is both and len(out.added) == 2 and out.notes == ()


def _leader_and_rival(share: float, rival_per_dof: float) -> tuple[EffectEvidence, ...]:
    """A gyro scale shown beyond doubt, a gyro rotation that explains ``share`` of its score
    when freed with it (figure-8s of a car with the IMU mounted obliquely) and an accelerometer
    scale that explains 0.9 of it."""
    leader = replace(
        _evidence("gyro_scale", STRONG),
        statistic_alone=3 * STRONG,
        explained_by={"gyro_rotation": share, "accel_scale": 0.9},
    )
    rival = replace(
        _evidence("gyro_rotation", 2.0), selected=False, statistic_alone=3 * rival_per_dof
    )
    return (
        leader,
        rival,
        replace(_evidence("accel_scale", 2.0), selected=False, statistic_alone=3 * STRONG),
    )


def _same_data(monkeypatch: pytest.MonkeyPatch, rival_minus_leader: float, alike: bool) -> list:
    compared: list = []

    def same_data_bic(a, b, samples):  # type: ignore[no-untyped-def]
        compared.append((a[0], b[0], samples))
        return rival_minus_leader

    monkeypatch.setattr(rivals, "same_data_bic", same_data_bic)
    monkeypatch.setattr(rivals, "refits_alike", lambda a, b: alike)
    monkeypatch.setattr(rivals, "sensor_samples", lambda run, sensor: 1000)
    return compared


def test_a_close_rival_is_refitted_in_the_leaders_place_and_the_better_one_named(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    base = _Run(0.30, _leader_and_rival(0.999, 0.9 * STRONG))
    scale, rotation = _Run(0.31), _Run(0.312)
    refits = _Refits(
        {
            ("accel_scale", "gyro_scale"): (scale, -5964.0),
            ("accel_scale", "gyro_rotation"): (rotation, -5982.0),
        }
    )
    refits.install(monkeypatch)
    compared = _same_data(monkeypatch, -17.0, alike=True)
    out = _add(base, {"model.imu": ["accel_scale"]})
    assert refits.asked == [("accel_scale", "gyro_scale"), ("accel_scale", "gyro_rotation")]
    assert compared == [("gyro_scale", "gyro_rotation", 1000)]
    assert out.run is rotation and out.cfg.model.imu == ["accel_scale", "gyro_rotation"]
    (a,) = out.added
    assert (a.effect, a.rival, a.not_told_apart) == ("gyro_rotation", "gyro_scale", ("gyro_scale",))
    # the rival's own test, not the one conditional on the leader freed
    assert a.statistic == pytest.approx(2.7 * STRONG) and a.delta_bic == pytest.approx(-5982.0)
    assert a.rival_delta_bic == pytest.approx(-17.0)
    assert out.notes == (
        "This recording does not tell gyro_rotation from gyro_scale: with either estimated, the "
        "other's score test is no longer significant. Both were refitted; gyro_rotation fit the "
        "same data better (BIC -17) and is estimated, and the two refits' extrinsics differ by "
        "2.00 mm / 0.0000 deg / 0.000 ms. Its numbers stand for an effect either one explains, "
        "not for gyro_rotation alone; a motion that excites more axes tells them apart, and "
        "licalib diagnose shows both.",
    )
    note = evident.added_note(out.added)
    assert note.startswith(
        "The data showed gyro_rotation or gyro_scale (score test 810 on 3 degrees of freedom) "
        "beyond doubt; it was estimated (BIC -5982)"
    )


def test_a_rival_that_fits_worse_leaves_the_leader_and_the_data_tell_them_apart(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    base = _Run(0.30, _leader_and_rival(0.8, 0.5 * STRONG)[:2])
    scale = _Run(0.31)
    _Refits({("gyro_scale",): (scale, -900.0), ("gyro_rotation",): (_Run(0.33), -850.0)}).install(
        monkeypatch
    )
    _same_data(monkeypatch, +40.0, alike=False)
    out = _add(base)
    assert out.run is scale
    (a,) = out.added
    assert (a.effect, a.rival, a.rival_delta_bic, a.not_told_apart) == (
        "gyro_scale",
        "gyro_rotation",
        -40.0,
        (),
    )
    assert a.statistic == pytest.approx(STRONG * 3)
    assert out.notes == (
        "gyro_rotation could stand in for gyro_scale; refitted in its place, it fit the same "
        "data worse (BIC +40), and the data tell the two apart.",
    )


def test_a_rival_whose_refit_does_not_pay_or_converge_leaves_the_leader_unweighed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    base = _Run(0.30, _leader_and_rival(0.999, STRONG)[:2])
    scale = _Run(0.31)
    for rival_refit in [(_Run(0.33), +3.0), (_Run(0.33, status="not converged"), -900.0)]:
        _Refits({("gyro_scale",): (scale, -900.0), ("gyro_rotation",): rival_refit}).install(
            monkeypatch
        )
        compared = _same_data(monkeypatch, -50.0, alike=True)
        out = _add(base)
        assert out.run is scale and compared == [] and out.notes == ()
        assert out.added[0].rival == "" and out.added[0].not_told_apart == ()


def test_only_a_candidate_that_explains_most_of_the_score_and_is_strong_enough_is_a_rival() -> None:
    cfg = load_config(None, {})
    leader, rival, accel = _leader_and_rival(0.999, STRONG)
    # the one that explains most of the score
    assert evident.rival_in([leader], [leader, rival, accel], cfg) == (leader, rival)
    leader, rival, accel = _leader_and_rival(0.8, STRONG)
    assert evident.rival_in([leader], [leader, rival, accel], cfg) == (leader, accel)
    # not one the model estimates already
    estimated = load_config(None, {"model.imu": ["accel_scale"]})
    assert evident.rival_in([leader], [leader, rival, accel], estimated) == (leader, rival)
    # one that leaves beyond doubt part of the score cannot stand in for it: not refitted
    # (60 % of 900 explained leaves 360 on 3 degrees of freedom)
    leader, rival, _ = _leader_and_rival(0.6, STRONG)
    assert evident.rival_in([leader], [leader, rival], estimated) is None
    assert not evident.stands_in(leader, rival)
    leader, rival, _ = _leader_and_rival(0.7, STRONG)
    assert evident.stands_in(leader, rival)
    # one that explains little of the score, or is weak on its own, is none
    leader, rival, _ = _leader_and_rival(0.2, STRONG)
    assert evident.rival_in([leader], [leader, rival], estimated) is None
    leader, rival, _ = _leader_and_rival(0.999, 0.2 * STRONG)
    assert evident.rival_in([leader], [leader, rival], estimated) is None
    # an effect the refit holds already is no rival of another in it
    leader, rival, _ = _leader_and_rival(0.999, STRONG)
    assert evident.rival_in([leader, rival], [leader, rival], estimated) is None


def test_the_result_names_what_was_added_and_the_findings_note_it() -> None:
    added = (
        AddedEffect("lidar_range_offset", 35716.5, 16, -909137.0, 0.0132, 0.0291, 7.7e-5),
        AddedEffect("lidar_elevation", 2400.0, 15, -909137.0, 0.0132, 0.0291, 7.7e-5),
        AddedEffect("accel_scale", 900.0, 3, -80.0, 0.0021, 0.001, -1e-6, refit=2),
    )
    run = finished_run(ModelInfo((), ("range_offset",)), Finding("warn", "w"))
    out = evident.with_added(run, added)  # type: ignore[arg-type]
    assert out.result.model.added == added
    first, second, kept = out.checks.findings
    assert first.severity == second.severity == "note" and kept.text == "w"
    assert first.text.startswith(
        "The data showed lidar_range_offset (score test 35716 on 16 degrees of freedom) and "
        "lidar_elevation (score test 2400 on 15 degrees of freedom) beyond doubt; they were "
        "estimated (BIC -909137), which moved the extrinsic by 13.20 mm / 0.0291 deg / 0.077 ms."
    )
    assert second.text.startswith(
        "The data showed accel_scale (score test 900 on 3 degrees of freedom) beyond doubt; it "
        "was estimated (BIC -80), which moved the extrinsic by 2.10 mm"
    )
    d = ModelInfo((), ("range_offset",), added=added).to_dict()
    assert d["added"][0]["effect"] == "lidar_range_offset"
    assert ModelInfo.from_dict(d).added == added
    # a rival's names round-trip; a file written before them reads as without a rival
    rival = (
        replace(
            added[2],
            rival="accel_misalignment",
            rival_delta_bic=-3.5,
            not_told_apart=("accel_misalignment",),
        ),
    )
    d = ModelInfo(("accel_scale",), added=rival).to_dict()
    assert d["added"][0]["not_told_apart"] == ["accel_misalignment"]
    assert ModelInfo.from_dict(d).added == rival
    # a hand-edited file with a rival of the wrong type is named, not taken
    bad = {**d, "added": [{**d["added"][0], "not_told_apart": 5}]}
    with pytest.raises(
        FileValueError, match=r"model\.added\.0\.not_told_apart. is 5, not a list of strings"
    ):
        ModelInfo.from_dict(bad, "model")
    for key in ("rival", "rival_delta_bic", "not_told_apart"):
        del d["added"][0][key]
    assert ModelInfo.from_dict(d).added == added[2:]
