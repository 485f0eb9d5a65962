"""End to end: ``licalib diagnose`` on small simulated bags with a hidden effect, and on a clean
one."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from light_config import LIGHT_VLP16, VLP16

from licalib_cli.cli import main
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.pipeline.diagnose import CANDIDATES
from licalib_cli.results import CalibrationResult
from licalib_cli.simulation import SimulationSpec, simulate
from licalib_cli.truth import Truth

CONFIG = LIGHT_VLP16  # configs/vlp16.yaml with a lighter final round
VLP16_ELEVATION = np.radians(np.arange(-15.0, 16.0, 2.0))

pytestmark = pytest.mark.slow


def _bag(tmp_path: Path, imu: ImuIntrinsics | None = None, **effects: Any) -> Path:
    """An 8 s sinusoid with the IMU intrinsics ``imu`` (default: none) and the simulator's
    named ``effects`` (``SimulationSpec`` keywords, which may also change its length, seed,
    rates, LiDAR ...; a LiDAR other than the VLP-16 has no intrinsic errors)."""
    fields: dict[str, Any] = {
        "scenario": "sinusoid",
        "lidar": "vlp16",
        "duration_s": 8.0,
        "seed": 41,
        "time_offset_s": 0.004,
        "azimuth_resolution_deg": 0.4,
        **effects,
    }
    if fields["lidar"] == "vlp16":
        path = tmp_path / "intrinsics.yaml"
        CalibrationResult(
            imu_intrinsics=imu or ImuIntrinsics(),
            lidar_intrinsics=LidarIntrinsics.nominal(VLP16_ELEVATION),
        ).save(path)
        fields["intrinsics_file"] = path
    else:
        assert imu is None, "IMU intrinsics are set through the VLP-16's intrinsics file"
        fields["intrinsics"] = "none"
    return simulate(SimulationSpec(**fields), tmp_path / "sim").bag_path


def _diagnose(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    try:
        main(["diagnose", *args])
        code = 0
    except SystemExit as err:
        code = int(err.code or 0)
    return code, capsys.readouterr().out


def _diagnose_json(args: list[str], capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    """``licalib diagnose ARGS --json``'s object (it must exit 0)."""
    code, printed = _diagnose([*args, "--json"], capsys)
    assert code == 0
    return dict(json.loads(printed))


def test_a_hidden_gyro_scale_is_named_added_and_its_gap_shrinks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _bag(tmp_path, ImuIntrinsics(gyro_scale=np.array([1.004, 0.996, 1.003])))
    out = tmp_path / "diag"
    data = _diagnose_json([str(bag), "-c", str(CONFIG), "-o", str(out)], capsys)
    assert data["effects_found"][0] == "gyro_scale"
    step = next(s for s in data["steps"] if s["effect"] == "gyro_scale")
    assert step["kept"] and step["delta_bic"] < 0 and step["p_value"] < 1e-6
    # the only effect kept is the last added: the backward check has nothing to take out
    assert step["dropped_for"] == [] and step["drop_delta_bic"] is None
    assert step["gap_shrink"] >= 0.5
    determined = 0
    for a, true in zip("xyz", (1.004, 0.996, 1.003), strict=True):
        value, sigma = step["estimate"][f"imu.gyro_scale.{a}"], step["sigma"][f"imu.gyro_scale.{a}"]
        if sigma is not None and sigma < 1e-3:  # determined by the motion
            determined += 1
            assert abs(value - true) < max(4 * sigma, 3e-4)
    assert determined >= 2
    for s in data["steps"]:
        if s["kept"]:
            assert s["final_p_value"] is None and s["unpaid"] is None
        else:  # scored again on the final fit; a rival named in its place explains it
            assert s["final_p_value"] is not None
            assert s["unpaid"] is None or not s["rival_named"]
    assert set(data) >= {"effects_found", "steps", "calibration", "verdict", "residuals"}
    # the twin recording of each fit is the reference of the gap, shown next to the measured
    base = {r["sensor"]: r for r in data["residuals"]["base"]}
    assert set(base) == {"gyro", "accelerometer", "lidar"}
    for row in base.values():
        assert row["twin"] is not None and row["twin"]["recordings"] >= 1
        assert row["gap"] == pytest.approx(
            row["measured"]["chi2_per_sample"] - row["twin"]["chi2_per_sample"], abs=1e-5
        )
    assert step["gap_before"]["reference"] == "twin"
    assert base["gyro"]["gap"] > 3 * base["gyro"]["twin"]["chi2_spread"]  # the scale shows
    final = {r["sensor"]: r for r in data["residuals"]["final"]}
    assert abs(final["gyro"]["gap"]) < base["gyro"]["gap"] / 2
    assert data["calibration"]["model"]["imu"] == ["gyro_scale"]
    # every candidate neither added nor tried says what size this bag would need to show it
    quiet = {n["effect"]: n for n in data["not_shown"]}
    tried = {s["effect"] for s in data["steps"]}
    assert quiet and not set(quiet) & tried
    assert set(quiet) | tried == set(CANDIDATES)
    offset = quiet["lidar_range_offset"]
    assert offset["unit"] == "mm" and 0.1 < offset["detectable_rms"] < 10.0
    assert offset["p_value"] > 1e-5
    written = yaml.safe_load((out / "diagnosis.yaml").read_text())
    assert written["effects_found"] == data["effects_found"]
    assert CalibrationResult.load(out / "calibration.yaml").imu_intrinsics.gyro_scale[0] > 1.002
    # the config written beside it estimates the model found (calibrate -c reproduces it)
    model = yaml.safe_load((out / "calibration.config.yaml").read_text())["model"]
    assert model["imu"] == ["gyro_scale"] and model["lidar"] == []


def test_calibrate_model_auto_estimates_and_writes_the_model_it_arrives_at(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``calibrate --model auto``: the diagnosis printed, the result of the model it arrived at,
    and that model in the resolved config (calibrating with it estimates the same); with
    ``--intrinsics`` it is refused in one sentence."""
    bag = _bag(tmp_path, ImuIntrinsics(gyro_scale=np.array([1.004, 0.996, 1.003])))
    out = tmp_path / "auto.yaml"
    config_before = CONFIG.read_bytes()
    try:
        main(["calibrate", str(bag), "-c", str(CONFIG), "--model", "auto", "-o", str(out)])
    except SystemExit as err:
        assert not err.code  # PASS or WARN: a result to use
    printed = capsys.readouterr().out
    assert "Effects added to the model: gyro_scale" in " ".join(printed.split())
    result = CalibrationResult.load(out)
    assert result.model is not None and result.model.imu == ("gyro_scale",)
    assert result.imu_intrinsics is not None and result.imu_intrinsics.gyro_scale[0] > 1.002
    resolved = yaml.safe_load((tmp_path / "auto.config.yaml").read_text())
    assert resolved["model"]["imu"] == ["gyro_scale"] and resolved["model"]["lidar"] == []
    assert CONFIG.read_bytes() == config_before
    with pytest.raises(SystemExit) as err:
        main(["calibrate", str(bag), "--model", "auto", "--intrinsics", "all", "-o", str(out)])
    assert err.value.code == 6
    assert "--model auto chooses the intrinsics itself" in capsys.readouterr().err


def test_a_clock_drift_the_score_test_finds_is_estimated_not_truncated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 300 ppm IMU clock drift over 8 s is found by its score test with a sigma of about
    25 ppm; the refit must estimate it (the solver once held it as unobservable, its sigma being
    above the drift's characteristic scale, so the BIC saw no gain and nothing was named)."""
    bag = _bag(tmp_path, effects=("imu_clock_drift",), imu_clock_drift_ppm=300.0)
    out = tmp_path / "diag"
    args = [str(bag), "-c", str(CONFIG), "--candidates", "imu_clock_drift", "-o", str(out)]
    data = _diagnose_json(args, capsys)
    assert data["effects_found"] == ["imu_clock_drift"]
    (step,) = data["steps"]
    drift, sigma = step["estimate"]["ext.time_drift"], step["sigma"]["ext.time_drift"]
    assert sigma is not None and sigma < 1e-4
    assert abs(drift - 300e-6) < max(3 * sigma, 30e-6)
    # the calibration file carries the drift, and the time at which its time offset holds,
    # where the truth's offset (at the first sample) is compared
    result = CalibrationResult.load(out / "calibration.yaml")
    assert result.extra_terms is not None and result.recording is not None
    # the JSON prints 6 digits
    assert result.extra_terms.clock_drift == pytest.approx(drift, rel=1e-5)
    assert result.intrinsics_uncertainty is not None
    assert result.intrinsics_uncertainty.values["clock_drift"][0] is not None
    middle = result.recording.start_ns + 0.5e9 * result.recording.duration_s
    assert abs(result.extra_terms.reference_ns - middle) < 0.05e9
    truth = Truth.load(tmp_path / "sim" / "truth.yaml")
    true_offset = truth.extrinsic_for(result).time_offset_s
    assert true_offset - 0.004 == pytest.approx(300e-6 * 4.0, rel=0.02)
    std = result.uncertainty.time_offset_std_s if result.uncertainty else 0.0
    assert abs(result.extrinsic.time_offset_s - true_offset) < 3 * std
    # the stamps against the record times show the same rate before the fit, and the estimate
    # agrees with it (no finding that the drift stands in for something else)
    assert result.recording.clock_rate_ppm == pytest.approx(300.0, abs=1.0)
    reasons = result.verdict.reasons if result.verdict else ()
    assert not any("differs from the rate of the sensors' stamps" in r for r in reasons)


def test_a_bias_walk_in_pieces_follows_the_walk_better_than_one_drift(tmp_path: Path) -> None:
    """A gyro bias random walk over 20 s: estimated in four pieces of 5 s
    (``model.bias_walk_piece_s``) it leaves a smaller gyro chi-square than one linear drift, and
    the result file carries every piece's drift with its sigma. (Over 8 s the walk's shape is
    not determined: the truncated SVD holds its pieces, and says so.)"""
    bag = _bag(
        tmp_path,
        duration_s=20.0,
        seed=43,
        azimuth_resolution_deg=0.8,
        imu_rate_hz=100.0,
        effects=("gyro_bias_walk",),
        bias_walk_scale=50.0,
    )
    chi2 = {}
    for piece_s in (None, 5.0):
        cfg = {"model": {"imu": ["gyro_bias_walk"], "bias_walk_piece_s": piece_s}}
        cfg_path = tmp_path / f"walk{piece_s}.yaml"
        cfg_path.write_text(yaml.safe_dump({**yaml.safe_load(CONFIG.read_text()), **cfg}))
        out = tmp_path / f"walk{piece_s}.out.yaml"
        try:
            main(["calibrate", str(bag), "-c", str(cfg_path), "-o", str(out)])
        except SystemExit as err:  # a FAIL verdict exits 9, the result written
            assert int(err.code or 0) in (0, 9)
        result = CalibrationResult.load(out)
        assert result.extra_terms is not None and result.intrinsics_uncertainty is not None
        assert result.consistency is not None
        walk = result.extra_terms.gyro_bias_walk
        sigmas = result.intrinsics_uncertainty.values["gyro_bias_walk"]
        assert walk is not None and len(walk) == len(sigmas)
        if piece_s is None:
            assert len(walk) == 3 and result.extra_terms.bias_walk_pieces is None
        else:
            assert len(walk) == 12 and result.extra_terms.bias_walk_pieces == 4
            assert all(s is not None and 0.0 < s < 1e-3 for s in sigmas), (walk, sigmas)
        chi2[piece_s] = next(
            c.chi2_per_sample for c in result.consistency.sensors if c.sensor == "gyro"
        )
    assert chi2[5.0] < chi2[None] - 0.01, chi2


def test_a_walk_far_above_its_scale_is_refitted_expecting_the_size_its_test_shows(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An 8 s OS1-64 shake whose gyro bias walks at a hundred times the MTi-100's rate: the
    drift's sigma is above its characteristic scale, so the first refit holds it and gains
    nothing; refitted expecting the size the score test shows, it is estimated and pays, and
    the resolved config and the result file say at which size."""
    bag = _bag(
        tmp_path,
        scenario="shake",
        lidar="os1-64",
        seed=42,
        azimuth_resolution_deg=2.0,
        effects=("gyro_bias_walk",),
        bias_walk_scale=100.0,
    )
    config = Path(__file__).resolve().parents[2] / "configs" / "os1-64.yaml"
    out = tmp_path / "diag"
    args = [str(bag), "-c", str(config), "--candidates", "gyro_bias_walk", "-o", str(out)]
    data = _diagnose_json(args, capsys)
    assert data["effects_found"] == ["gyro_bias_walk"]
    (step,) = data["steps"]
    assert step["held_delta_bic"] > 0.0 > step["sized_delta_bic"] == step["delta_bic"]
    assert step["held"] == []
    size = step["expected_size"]
    assert size > 1e-5  # above the built-in scale
    drifts = [v for k, v in step["estimate"].items() if k.startswith("imu.gyro_bias_drift")]
    sigmas = [v for k, v in step["sigma"].items() if k.startswith("imu.gyro_bias_drift")]
    assert max(abs(d) for d in drifts) <= size and max(sigmas) < size
    resolved = yaml.safe_load((out / "calibration.config.yaml").read_text())
    assert resolved["model"]["expected_size"] == {"gyro_bias_walk": size}
    result = CalibrationResult.load(out / "calibration.yaml")
    assert result.model is not None and result.model.expected_size == {"gyro_bias_walk": size}


def test_an_accelerometer_scale_the_score_test_finds_is_estimated_in_every_axis(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 10 s hand-held shake with the accelerometer scale off by 0.46 / 0.16 / 0.54 % (the
    simulator's draw at five times the paper's size). Gravity stays near the IMU's z axis, so
    the z scale trades with the z bias and one direction of the scale is determined to only
    about 0.1-0.2 %. The refit must estimate it: at a characteristic scale of 0.1 % the solver's
    truncation held two directions at nominal, the refit gained too little for the BIC, and
    nothing was named although the score test showed the scale at p = 3e-9."""
    spec = SimulationSpec(
        scenario="shake",
        lidar="vlp16",
        duration_s=10.0,
        seed=211,
        intrinsics="none",
        random_time_offset=True,
        effects=("accel_scale",),
        effect_scale=5.0,
    )
    bag = simulate(spec, tmp_path / "sim").bag_path
    true = Truth.load(tmp_path / "sim" / "truth.yaml").imu_intrinsics.accel_scale
    assert np.max(np.abs(true - 1.0)) > 4e-3
    data = _diagnose_json([str(bag), "--candidates", "accel_scale"], capsys)
    assert data["effects_found"] == ["accel_scale"]
    (step,) = data["steps"]
    for a, value_true in zip("xyz", true, strict=True):
        value = step["estimate"][f"imu.accel_scale.{a}"]
        sigma = step["sigma"][f"imu.accel_scale.{a}"]
        assert sigma is not None and sigma < 3e-3
        assert abs(value - value_true) < 3 * sigma
    assert step["held"] == []  # every axis estimated, none held at nominal by the truncation


def test_the_coordinates_a_refit_held_at_nominal_are_named() -> None:
    from types import SimpleNamespace

    from licalib_cli.pipeline.diagnose import _held

    names = (
        "ext.translation.x",
        "imu.accel_scale.x",
        "imu.accel_scale.z",
        "lidar.intrinsics[3].drho",
        "lidar.intrinsics[3].H",
        "lidar.intrinsics[4].drho",
    )
    run = SimpleNamespace(
        solver=SimpleNamespace(
            calibration_names=names,
            truncated_weight=np.array([0.9, 0.2, 0.99, 0.7, 0.6, 0.0]),
        )
    )
    assert _held(run, "accel_scale") == ("imu.accel_scale.z",)  # type: ignore[arg-type]
    assert _held(run, "lidar_horizontal_offset") == ("lidar.intrinsics[3].H",)  # type: ignore[arg-type]
    assert _held(run, "lidar_range_offset") == ("lidar.intrinsics[3].drho",)  # type: ignore[arg-type]
    assert _held(run, "gyro_scale") == ()  # type: ignore[arg-type]


def test_a_clean_bag_shows_no_effect(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _bag(tmp_path)
    # a window of the bag, as calibrate takes one; the default final round (its PASS rests on it)
    args = [str(bag), "-c", str(VLP16), "--start", "0.5", "--duration", "7", "-o", str(tmp_path)]
    code, printed = _diagnose(args, capsys)
    assert code == 0
    recording = yaml.safe_load((tmp_path / "calibration.yaml").read_text())["recording"]
    assert recording["duration_s"] == pytest.approx(7.0, abs=0.01)
    assert "Effects added to the model: none" in printed
    assert "base model PASS" in printed
    assert "Not shown by this bag" in printed and "gyro_bias_walk" in printed


def test_score_tests_are_chi_square_on_clean_simulated_data(tmp_path: Path) -> None:
    """Without any effect in the data every candidate's score statistic is chi-square with its
    degrees of freedom: the false-alarm rate at 5 % is at most about 5 %, and nothing reaches
    the significance level diagnose uses. Clean data: a simulated bag without effects, fitted
    once, and twin recordings of that fit (the fitted model plus fresh noise, refitted).

    The test is somewhat conservative (the statistic averages about 0.85 of its degrees of
    freedom): the surfel planes are fitted to the same points and held fixed in the test, and
    the Huber loss clips the largest distances."""
    from scipy import stats

    from licalib_cli.config import load_config
    from licalib_cli.pipeline import Timer, fit_and_check, prepare
    from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, effect_evidence
    from licalib_cli.pipeline.settings import lm_params
    from licalib_cli.pipeline.twin import twin_recordings
    from licalib_cli.progress import NullProgress

    spec = SimulationSpec(
        scenario="shake",
        duration_s=3.0,
        seed=12,
        intrinsics="none",
        azimuth_resolution_deg=1.0,
    )
    bag = simulate(spec, tmp_path / "clean").bag_path
    cfg = load_config(CONFIG)
    timer, progress = Timer(), NullProgress()
    prepared = prepare(bag, cfg, progress, timer)
    run = fit_and_check(prepared, prepared.guess, cfg, progress, timer)
    scores = [(e.statistic_alone, e.score.rank) for e in run.effects]
    twins = twin_recordings(
        run.state, run.fit.inputs, run.noise, lm_params(cfg, max_iterations=3), 10, seed=7
    )
    for state, inputs in twins:
        scores += [(e.statistic_alone, e.score.rank) for e in effect_evidence(state, inputs, 1.0)]
    statistic, dof = np.array(scores).T
    p = stats.chi2.sf(statistic, dof)
    assert p.size >= 100
    assert np.mean(p < 0.05) < 0.10  # the false-alarm rate at 5 %
    # and the p-values spread as a (somewhat conservative) chi-square's do: 176 of them put
    # 0-2 % below 0.05 depending on the fit's last association, which is too few to bound that
    # tail from below; the wider quantiles are not piled at either end
    assert 0.08 < np.mean(p < 0.25) < 0.35
    assert 0.30 < np.mean(p < 0.5) < 0.60
    assert p.min() > EFFECT_P_VALUE  # no false effect at diagnose's level
    assert 0.65 < statistic.sum() / dof.sum() < 1.3  # chi-square: mean = degrees of freedom


def test_bad_diagnose_options_end_in_one_sentence(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = tmp_path / "missing.bag"
    with pytest.raises(SystemExit) as err:
        main(["diagnose", str(bag), "--candidates", "gyro_wobble"])
    assert err.value.code == 6
    assert "Unknown candidate effect 'gyro_wobble'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as err:
        main(["diagnose", str(bag), "--plots"])
    assert err.value.code == 6


def test_the_sigmas_of_every_candidate_block_go_into_the_result() -> None:
    """A model with a drift or the per-point time (as diagnose builds it) reports their sigmas
    in ``intrinsics_uncertainty`` instead of failing."""
    from licalib_cli.config import load_config
    from licalib_cli.pipeline.diagnose import CANDIDATES
    from licalib_cli.pipeline.effect_models import with_effects
    from licalib_cli.pipeline.intrinsic_sigmas import intrinsics_uncertainty

    cfg = with_effects(load_config(CONFIG), tuple(CANDIDATES))
    names = [
        *(f"imu.gyro_bias_drift.{a}" for a in "xyz"),
        *(f"imu.accel_bias_drift.{a}" for a in "xyz"),
        "ext.time_drift",
        "lidar.point_time_scale",
    ]

    class Report:
        calibration_names = names
        std = np.full(len(names), 2e-4)
        truncated_weight = np.zeros(len(names))

    values = intrinsics_uncertainty(Report(), cfg, 1.0, 16).values  # type: ignore[arg-type]
    assert values["gyro_bias_walk"] == pytest.approx((2e-4,) * 3)
    assert values["accel_bias_walk"] == pytest.approx((2e-4,) * 3)
    assert values["clock_drift"] == pytest.approx((2e-4,))
    assert values["point_time"] == pytest.approx((2e-4,))
    assert values["gyro_scale"] == (None, None, None)  # not in the report: held


def _trial(effect: str, delta_bic: float, rival_scores: dict[str, float]) -> Any:
    """A refitted rival: its BIC change against the base and, on its refit, the p-values of
    the score tests of the other candidates."""
    from types import SimpleNamespace

    from licalib_cli.consistency import EffectScore

    def score(name: str, p: float) -> Any:
        z = np.zeros(1)
        return SimpleNamespace(score=EffectScore(name, 1.0, 1, p, z, z, z, z))

    after = SimpleNamespace(effects=[score(n, p) for n, p in rival_scores.items()])
    return SimpleNamespace(effect=effect, delta_bic=delta_bic, after=after)


def test_rivals_are_compared_on_the_same_data_and_an_indistinguishable_pair_is_named() -> None:
    """A range scale against a range offset on one bag (shake, OS1-64, 150 ppm scales): each
    refit's BIC change against the base was measured on its own data, the offset's 234 lower
    only because the base model left 239 more on the offset's data; on the same data the scale
    fitted better by 2.4, and neither showed anything given the other (p 0.89 and 0.99)."""
    from licalib_cli.pipeline.rivals import not_told_apart, pick_rival

    offset = _trial("lidar_range_offset", -57.2, {"lidar_range_scale": 0.89})
    scale = _trial("lidar_range_scale", -20.0, {"lidar_range_offset": 0.99})
    # both pay: the comparison on the same data decides, not the BIC changes on own data
    assert pick_rival([offset.delta_bic, scale.delta_bic], [2.4, -2.4]) == 1
    # only one pays: it is named whatever the comparison on the same data says
    assert pick_rival([-57.2, 177.1], [2.4, -2.4]) == 0
    assert pick_rival([57.2, 177.1], [2.4, -2.4]) == 1
    assert not_told_apart(offset, scale) and not_told_apart(scale, offset)
    # a range offset of centimetres shows clearly with the scale freed: told apart
    scale_of_offset_bag = _trial("lidar_range_scale", -900.0, {"lidar_range_offset": 1e-40})
    offset_of_offset_bag = _trial("lidar_range_offset", -5000.0, {"lidar_range_scale": 0.5})
    assert not not_told_apart(offset_of_offset_bag, scale_of_offset_bag)


def _evidence(
    name: str, alone: float, rank: int, explained_by: dict[str, float] | None = None
) -> Any:
    from types import SimpleNamespace

    from licalib_cli.consistency import EffectScore

    z = np.zeros(rank)
    return SimpleNamespace(
        score=EffectScore(name, alone, rank, 0.0, z, z, z, z),
        statistic_alone=alone,
        explained_by=explained_by or {},
    )


def test_a_rival_is_a_candidate_that_explains_most_of_the_leaders_score() -> None:
    """Bag 1837 (OS1-64 sinusoid, 2.9 deg gyro rotation and per-beam elevations): after the
    elevations the accelerometer misalignment led (3060 on 3 degrees of freedom); freed with
    it, the gyro rotation explained 0.83 of its score, the g-sensitivity 0.44 and the
    accelerometer scale 0.14 (the shares that run measured). The rotation, of the other sensor,
    is the rival refitted; the accelerometer scale, of the same sensor but explaining little,
    is not. Among several rivals the one explaining most comes first, and one far weaker per
    degree of freedom is not refitted."""
    from licalib_cli.pipeline.rivals import alike, rivals_of, stand_in_share

    misalignment = _evidence(
        "accel_misalignment",
        3060.0,
        3,
        {"gyro_rotation": 0.83, "g_sensitivity": 0.44, "accel_scale": 0.14},
    )
    rotation = _evidence("gyro_rotation", 2000.0, 3, {"accel_misalignment": 0.9})
    g_sens = _evidence("g_sensitivity", 1200.0, 9)
    accel_scale = _evidence("accel_scale", 2900.0, 3)  # stronger than the rotation
    weak = _evidence("accel_bias_walk", 10.0, 3)
    options = [misalignment, rotation, g_sens, accel_scale, weak]
    assert rivals_of(misalignment, options) == [rotation]
    assert rivals_of(rotation, options) == [misalignment]
    assert alike(misalignment, rotation)
    assert not alike(misalignment, accel_scale) and not alike(misalignment, g_sens)
    assert not alike(rotation, accel_scale)
    # the one that explains most first, at most one
    both = _evidence(
        "lidar_range_offset", 900.0, 16, {"lidar_range_scale": 0.7, "lidar_elevation": 0.95}
    )
    scale = _evidence("lidar_range_scale", 800.0, 16)
    elevation = _evidence("lidar_elevation", 400.0, 16)
    assert rivals_of(both, [both, scale, elevation]) == [elevation]
    # a rival far weaker per degree of freedom is not refitted
    assert rivals_of(misalignment, [misalignment, _evidence("gyro_rotation", 500.0, 3)]) == []
    # a per-beam leader near its significance level: noise leaves about half of its score
    # even to the effect in the data, so a candidate explaining 0.3 of it is a rival there
    weak_leader = _evidence("lidar_range_offset", 130.0, 64, {"lidar_range_scale": 0.3})
    assert stand_in_share(weak_leader) == pytest.approx(1.0 - 64 / 130)
    assert rivals_of(weak_leader, [_evidence("lidar_range_scale", 120.0, 64)])
    assert not alike(_evidence("accel_scale", 3000.0, 3, {"gyro_scale": 0.3}), g_sens)
    assert not rivals_of(
        _evidence("accel_scale", 3000.0, 3, {"gyro_scale": 0.3}),
        [_evidence("gyro_scale", 2900.0, 3)],
    )
    # a leader with no shares (none significant beside it) has none
    assert rivals_of(_evidence("accel_scale", 100.0, 3), [_evidence("gyro_scale", 90.0, 3)]) == []


def test_an_effect_the_later_ones_explain_is_dropped_again() -> None:
    """The backward check: on a VLP-16 sinusoid with a rotated gyro the forward selection added
    an accelerometer misalignment and scale before the gyro rotation; with the rotation in, the
    two gained sums of squares of 0.9 and 0 for three parameters each (BIC +27 and +246)."""
    from licalib_cli.pipeline.backward import drop_redundant

    bic = {
        ("accel_misalignment", "accel_scale", "gyro_rotation"): {
            "accel_misalignment": 20.0,
            "accel_scale": 246.0,
        },
        ("accel_misalignment", "gyro_rotation"): {"accel_misalignment": 27.4},
    }
    refits: list[tuple[tuple[str, ...], str]] = []
    dropped = drop_redundant(
        ("accel_misalignment", "accel_scale", "gyro_rotation"),
        lambda kept, effects: {e: bic[kept][e] for e in effects},
        lambda kept, effect: refits.append((kept, effect)),
    )
    # the removal that pays most first, then the check again on what is left; the last effect
    # added is never taken out (it paid with all the others in)
    assert refits == [
        (("accel_misalignment", "accel_scale", "gyro_rotation"), "accel_scale"),
        (("accel_misalignment", "gyro_rotation"), "accel_misalignment"),
    ]
    assert dropped == [
        ("accel_scale", ("gyro_rotation",), 246.0),
        ("accel_misalignment", ("gyro_rotation",), 27.4),
    ]
    # a pair where each explains its own part (gyro rotation and elevations): nothing dropped
    never = {"lidar_elevation": -5000.0}
    assert (
        drop_redundant(  # type: ignore[arg-type]
            ("lidar_elevation", "gyro_rotation"), lambda k, es: {e: never[e] for e in es}, None
        )
        == []
    )
    # a single effect is not checked
    assert drop_redundant(("gyro_scale",), None, None) == []  # type: ignore[arg-type]


@pytest.mark.parametrize("effect", sorted(CANDIDATES))
def test_an_effect_taken_out_is_back_at_its_starting_value_and_nothing_else_moves(
    effect: str,
) -> None:
    from licalib_cli.estimation import intrinsic_coordinates
    from licalib_cli.pipeline.effect_models import of_effect, without_effect
    from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

    knots = UniformKnots(0.0, 0.1, 8)
    rng = np.random.default_rng(3)

    def state(offset: float) -> Any:
        from licalib_cli.estimation import CalibrationState

        n = 4
        imu = ImuIntrinsics(
            gyro_scale=np.full(3, 1.0 + offset),
            gyro_misalignment=np.full(3, offset),
            gyro_rotation=np.array([offset, 0.0, 0.0, 1.0]) / np.hypot(offset, 1.0),
            accel_scale=np.full(3, 1.0 + 2 * offset),
            accel_misalignment=np.full(3, 3 * offset),
            gyro_g_sensitivity=np.full((3, 3), offset),
        )
        lidar = LidarIntrinsics(
            np.linspace(-0.2, 0.2, n),
            *(np.full(n, offset * (k + 1)) for k in range(4)),
            np.full(n, 1.0 + offset),
            np.full(n, 5 * offset),
        )
        return CalibrationState(
            SO3Spline(knots, np.tile([0.0, 0.0, 0.0, 1.0], (knots.num_control_points, 1))),
            R3Spline(knots, rng.normal(size=(knots.num_control_points, 3))),
            np.zeros(3),
            np.zeros(3),
            np.array([0.0, 0.0, -9.81]),
            np.eye(3),
            np.zeros(3),
            0.0,
            imu,
            lidar,
            gyro_bias_drift=np.full(3, offset),
            accel_bias_drift=np.full(3, 2 * offset),
            time_drift=offset,
            point_time_scale=2 * offset,
        )

    start, fitted = state(0.0), state(0.01)
    out = without_effect(fitted, effect, start)
    before, after, nominal = (intrinsic_coordinates(s) for s in (fitted, out, start))
    for name, value in after.items():
        expected = nominal[name] if of_effect(name, effect) else before[name]
        assert value == pytest.approx(expected), name
    # the effect had moved (the test would pass on a no-op otherwise)
    assert any(before[n] != nominal[n] for n in before if of_effect(n, effect))
    assert out.so3_spline is fitted.so3_spline


def test_an_effect_of_a_final_model_with_several_gets_its_share_of_its_sensors_gap(
    tmp_path: Path,
) -> None:
    """A gyro scale and an accelerometer scale hidden together: the final model refitted without
    the gyro scale leaves the gyro's gap where the base model (neither) left it, the final fit
    closes it; the accelerometer's figures are not the gyro scale's."""
    from dataclasses import replace

    from licalib_cli.config import load_config
    from licalib_cli.pipeline import Timer, fit_and_check, prepare
    from licalib_cli.pipeline.diagnose import _gap, share_of
    from licalib_cli.pipeline.effect_models import with_effects, without_effect
    from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, effect_evidence
    from licalib_cli.progress import NullProgress

    bag = _bag(
        tmp_path,
        ImuIntrinsics(
            gyro_scale=np.array([1.004, 0.996, 1.003]),
            accel_scale=np.array([1.006, 0.994, 1.005]),
        ),
    )
    cfg = load_config(CONFIG)
    progress, timer = NullProgress(), Timer()
    base_cfg = with_effects(cfg, ())
    prepared = prepare(bag, base_cfg, progress, timer)
    base = fit_and_check(prepared, prepared.guess, base_cfg, progress, timer)
    # calibrate's checks do not size the rivals (only diagnose reads them); asked, they do
    significant = {e.score.name for e in base.effects if e.score.p_value < EFFECT_P_VALUE}
    assert {"gyro_scale", "accel_scale"} <= significant
    assert all(not e.explained_by for e in base.effects)
    sized = effect_evidence(base.state, base.fit.inputs, base.fit.report.variance_factor)
    shares = {e.score.name: e.explained_by for e in sized if e.score.name in significant}
    assert shares["gyro_scale"] and shares["accel_scale"]
    assert all(0.0 <= v <= 1.0 + 1e-9 for s in shares.values() for v in s.values())
    both = with_effects(cfg, ("gyro_scale", "accel_scale"))
    run = fit_and_check(
        prepared, replace(prepared.guess, state=base.state), both, progress, timer, warm=True
    )
    start = replace(prepared.guess, state=without_effect(run.state, "gyro_scale", base.state))
    rest = with_effects(cfg, ("accel_scale",))
    without = fit_and_check(prepared, start, rest, progress, timer, warm=True)
    rate = 400.0
    before, after = share_of(run, without, "gyro_scale", rate, None)
    assert before.sensor == after.sensor == "gyro"
    # taken out, its sensor's gap is back near the base fit's, which lacked both
    reopened = _gap(base, "gyro", rate, None).excess
    assert before.excess > 3.0 * before.sigma
    assert 0.7 * reopened < before.excess < 1.3 * reopened
    assert max(after.excess, 0.0) < 0.2 * before.excess  # in, it closes it
    assert after.chi2_per_sample == _gap(run, "gyro", rate, None).chi2_per_sample
