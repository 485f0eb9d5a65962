"""``licalib report``: a page from a result file alone or with its report data; the refusals
(not a result, another schema version, an input as output) with one sentence and exit 6, no
partial file."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.report import ReportData, report_data_path, write_report
from licalib_cli.report.figures import direction_parts
from licalib_cli.report.html import render_html
from licalib_cli.results import CalibrationResult, Extrinsic, matrix_from_rpy_deg
from licalib_cli.sections import (
    Observability,
    Provenance,
    RecordingSection,
    Uncertainty,
    VerdictSection,
)

pytest.importorskip("matplotlib")

CREATED = "2026-11-24T07:00:00Z"
PLANAR = (
    "ext.translation along [0.00, 0.00, 1.00] in the IMU frame: unobservable, not estimated "
    "(stays near its initial value)"
)


def run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(args)
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(exc.value.code or 0), out.out, out.err


def _one_sentence_error(err: str, code: int, expected: int) -> str:
    assert code == expected, err
    assert "Traceback" not in err and "Internal error" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines[-1].startswith("Error: "), err
    return " ".join(lines)


def write_result(
    path: Path, verdict: str = "warn", reasons: tuple[str, ...] = ("Not observable: z.",)
) -> CalibrationResult:
    result = CalibrationResult(
        extrinsic=Extrinsic(
            matrix_from_rpy_deg([180.0, 0.0, 90.0]), np.array([0.3, -0.15, 0.05]), -0.0071
        ),
        uncertainty=Uncertainty((0.001, 0.002, float("inf")), (0.01, 0.02, 0.03), 1e-4),
        observability=Observability(
            "S_d = D S D", 1.0, (350.0, 120.0, 80.0, 40.0, 9.0, 2.0, 1e-9), (PLANAR,)
        ),
        verdict=VerdictSection(verdict, reasons),
        recording=RecordingSection(
            str(path.parent / "rig.bag"),
            "/imu/data",
            "/points_raw",
            4001,
            100,
            10.0,
            1700000000000000000,
            0.0,
            0.0,
            gravity_turn_deg=27.365,
        ),
        provenance=Provenance("0.1.0", "0123456789abcdef", CREATED),
    )
    result.save(path)
    return CalibrationResult.load(path)


def test_report_of_a_result_without_report_data(tmp_path, capsys):
    result = tmp_path / "calib.yaml"
    write_result(result)
    code, _, err = run(["report", str(result)], capsys)
    assert code == 0, err
    page = (tmp_path / "calib.html").read_text()
    assert "Verdict: WARN" in page and "Not observable: z." in page
    # The estimate table with the unobservable translation said so, not as a number.
    assert "+0.3000 m" in page and "not observable" in page
    # The unobservable direction in words and as a sketch; the figures it cannot draw named.
    assert "the LiDAR&#x27;s position along the black arrow (+0.00 IMU x, +0.00 IMU y" in page
    assert page.count("data:image/png;base64,") == 2  # spectrum and the sketch
    assert "report-data.npz" in page
    assert "no report data" in err
    # Self-contained: nothing is fetched from elsewhere.
    assert not re.search(r"(src|href)=\"(https?:)?//", page)


def test_verdict_comes_first_and_fail_is_marked(tmp_path, capsys):
    result = tmp_path / "r.yaml"
    write_result(result, "fail", ("The calibration did not converge.",))
    out = tmp_path / "page" / "report.html"
    code, _, err = run(["report", str(result), "-o", str(out)], capsys)
    assert code == 0, err
    page = out.read_text()
    body = page[page.index("<body>") :]
    assert body.index("Verdict: FAIL") < body.index("Estimate") < body.index("Provenance")
    assert "Do not use this result" in page
    assert "The calibration did not converge." in page


def test_a_pass_that_takes_an_effect_as_exact_says_so_beside_the_verdict() -> None:
    """As the console's verdict line: the effects listed with prior 0 in
    ``consistency.unchecked_priors`` (taken as exact, could hide three sigmas) are named under
    a PASS or a WARN, not under a FAIL (which needs no qualification)."""
    from licalib_cli.sections import Consistency, UncheckedPriorCheck

    assumed = UncheckedPriorCheck(
        "lidar_point_time", "% of the sweep time", 0.0, 0.093, "time offset", 6.6
    )
    prior = UncheckedPriorCheck("accel_scale", "ppm", 1000.0, 6600.0, "t_z", 2.0)
    base = CalibrationResult(
        extrinsic=Extrinsic(np.eye(3), np.zeros(3), 0.0),
        consistency=Consistency(unchecked_priors=(assumed, prior)),
    )
    page = render_html(replace(base, verdict=VerdictSection("pass", ())), None)
    said = "It assumes lidar_point_time exact, which this recording cannot check"
    assert said in page and "accel_scale exact" not in page
    assert said not in render_html(replace(base, verdict=VerdictSection("fail", ("x",))), None)


def full_data() -> ReportData:
    """Report data with every figure's arrays (synthetic)."""
    rng = np.random.default_rng(0)
    return ReportData(
        result_created_utc=CREATED,
        command_line="licalib calibrate rig.bag",
        config_text="bag:\n  start_s: 0.0\n",
        truth_matrix=np.eye(4),
        truth_time_offset=np.array([-0.007]),
        distances_before_m=rng.normal(0, 0.02, 500).astype(np.float32),
        distances_after_m=rng.normal(0, 0.01, 500).astype(np.float32),
        imu_t_s=np.linspace(0, 5, 100, dtype=np.float32),
        gyro_residual=rng.normal(0, 1e-3, (100, 3)).astype(np.float32),
        accel_residual=rng.normal(0, 1e-2, (100, 3)).astype(np.float32),
        round_index=np.array([1, 2]),
        round_max_distance_m=np.array([0.09, 0.03]),
        round_points=np.array([100, 120]),
        round_surfels=np.array([10, 12]),
        round_rms_m=np.array([0.02, 0.01]),
        round_map_entropy=np.array([-4.0, -4.1]),
        round_iterations=np.array([5, 4]),
        round_seconds=np.array([1.0, 1.2]),
        round_translation_m=np.array([[0.29, -0.15, 0.05], [0.3, -0.15, 0.05]]),
        round_rpy_deg=np.array([[180.0, 0.0, 90.0], [180.0, 0.0, 90.0]]),
        round_time_offset_s=np.array([-0.007, -0.0071]),
        round_free=np.array(["trajectory, extrinsic", "trajectory, extrinsic"]),
        initial_translation_m=np.array([0.25, -0.1, 0.0]),
        initial_rpy_deg=np.array([179.0, 0.5, 89.0]),
        initial_time_offset_s=np.array([-0.006]),
        motion_t_s=np.linspace(0, 5, 200, dtype=np.float32),
        angular_rate=rng.normal(0, 1, (200, 3)).astype(np.float32),
        specific_force=rng.normal(0, 1, (200, 3)).astype(np.float32),
        segments_s=np.array([[0.5, 4.5]]),
        map_before_top_xy=rng.uniform(-5, 5, (300, 2)).astype(np.float32),
        map_after_top_xy=rng.uniform(-5, 5, (300, 2)).astype(np.float32),
        map_before_side_xz=rng.uniform(-2, 2, (300, 2)).astype(np.float32),
        map_after_side_xz=rng.uniform(-2, 2, (300, 2)).astype(np.float32),
        map_entropy_before=-3.9,
        map_entropy_after=-4.1,
        map_region_m=np.array([-5.0, 5.0, -5.0, 5.0, -2.0, 2.0]),
    )


def test_report_data_round_trip_and_figures(tmp_path):
    data = full_data()
    result_path = tmp_path / "calib.yaml"
    write_result(result_path)
    data.save(report_data_path(result_path))
    back = ReportData.load(report_data_path(result_path))
    assert back.command_line == data.command_line and back.map_entropy_after == -4.1
    assert back.truth is not None and back.truth.time_offset_s == -0.007
    np.testing.assert_array_equal(back.round_free, data.round_free)
    np.testing.assert_array_equal(back.map_after_top_xy, data.map_after_top_xy)
    page = render_html(CalibrationResult.load(result_path), back, "calib.yaml")
    # spectrum, sketch, distances, IMU residuals, rounds, motion, map
    assert page.count("data:image/png;base64,") == 7
    assert "no report data" not in page
    assert "-3.9000" in page and "-4.1000" in page  # both entropies
    assert "licalib calibrate rig.bag" in page and "start_s: 0.0" in page
    assert "initial guess" in page and "truth" in page and "+0.25" in page
    assert 'gravity turned in the IMU frame</td><td class="">27.4 deg RMS' in page


@pytest.mark.slow
def test_page_in_chromium(tmp_path, browser):
    """The page as a person sees it: rendered by headless Chromium, the verdict box on top in
    its colour, the verdict and its reasons, the estimate table with the truth, the checks."""
    result_path = tmp_path / "calib.yaml"
    write_result(result_path, "warn", ("Not observable from this data: the lever arm's z.",))
    full_data().save(report_data_path(result_path))
    page = tmp_path / "calib.html"
    write_report(page, CalibrationResult.load(result_path), full_data(), str(result_path))
    pixels = browser.screenshot(page, tmp_path / "shot.png", 1000, 1800)
    assert pixels.shape[:2] == (1800, 1000)
    assert float(pixels[..., :3].std()) > 0.05  # not blank
    assert browser.verdict_share(pixels, "warn") > 0.05
    dom = browser.dom(page)
    text = browser.text(dom)
    assert "Verdict: WARN" in text
    assert "Not observable from this data: the lever arm's z." in text
    cells = browser.table_cells(dom, "estimate")
    assert cells[:6] == ["parameter", "estimate", "1-sigma", "initial guess", "truth", "error"]
    assert cells[6:12] == ["t_x", "+0.3000 m", "1.00 mm", "+0.2500 m", "+0.0000 m", "+300.00 mm"]
    assert cells[18:21] == ["t_z", "+0.0500 m", "not observable"]
    assert cells[-6:-3] == ["time offset", "-7.100 ms", "0.100 ms"]
    assert browser.table_cells(dom, "entropy")[2:] == [
        "initial calibration",
        "-3.9000",
        "final calibration",
        "-4.1000",
    ]
    for heading in ("What the data determined", "The fit", "The motion", "The map", "Provenance"):
        assert heading in text


def test_report_data_of_another_run_is_not_used(tmp_path, capsys):
    result = tmp_path / "calib.yaml"
    write_result(result)
    ReportData(result_created_utc="2020-01-01T00:00:00Z", command_line="old").save(
        report_data_path(result)
    )
    code, _, err = run(["report", str(result)], capsys)
    assert code == 0
    assert "belongs to another run" in err
    assert "old" not in (tmp_path / "calib.html").read_text().split("Provenance")[1]


def test_direction_parts_reads_the_result_text():
    parts = direction_parts(
        "ext.translation along [0.00, 0.60, 0.80] in the IMU frame + ext.rotation along "
        "[1.00, 0.00, 0.00] in the LiDAR frame: unobservable"
    )
    np.testing.assert_allclose(parts["ext.translation"], [0.0, 0.6, 0.8])
    np.testing.assert_allclose(parts["ext.rotation"], [1.0, 0.0, 0.0])
    assert direction_parts("imu.gyro_scale (imu.gyro_scale.x +1.00): unobservable") == {}


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("just some words\n", "is not a licalib result (not a YAML mapping)"),
        ("a: 1\n", "is not a licalib result (it has no schema_version)"),
        (
            "schema_version: 2\nextrinsic: {translation: [0, 0, 0], time_offset_s: 0}\n",
            "schema version 2, but this licalib reads version 1",
        ),
        (
            "schema_version: 1\nextrinsic: {translation: [0, 0, 0], "
            "rotation_quaternion: [0, 0, 0, 1], time_offset_s: 0}\nscenario: {name: x}\n",
            "is not a calibration result (it has no verdict",
        ),
    ],
)
def test_not_a_result_is_refused(tmp_path, capsys, content, expected):
    path = tmp_path / "x.yaml"
    path.write_text(content)
    code, _, err = run(["report", str(path)], capsys)
    text = _one_sentence_error(err, code, 6)
    assert expected in text
    assert not (tmp_path / "x.html").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.yaml"]


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        (("consistency", "split_half", "compared"), 5, "is 5, not a list of strings"),
        (("consistency", "split_half", "chi2"), "abc", "is 'abc', not a number"),
        (("consistency", "sensors", 0, "patterns"), "x", "is 'x', not a list of mappings"),
        (("uncertainty", "translation_std_m"), [1], "is [1], not a list of 3 numbers"),
        (("verdict",), 5, "is 5, not a mapping"),
        (("extrinsic", "rotation_quaternion"), [0, 0, 0, 0], "is [0, 0, 0, 0], not a unit"),
        (("imu_intrinsics", "gyro_g_sensitivity"), [1], "is [1], not 3 rows of 3"),
        (("gravity_G",), "down", "is 'down', not a list of 3"),
        (("observability", "weakly_determined"), 5, "is 5, not a list of strings"),
        (("observability", "weak_floor"), "tenth", "is 'tenth', not a number"),
    ],
)
def test_a_value_of_the_wrong_type_is_named_by_its_key(tmp_path, capsys, key, value, expected):
    golden = Path(__file__).parents[1] / "golden" / "result_v1.yaml"
    data = yaml.safe_load(golden.read_text())
    node = data
    for k in key[:-1]:
        node = node[k]
    node[key[-1]] = value
    path = tmp_path / "x.yaml"
    path.write_text(yaml.safe_dump(data))
    code, _, err = run(["report", str(path)], capsys)
    text = _one_sentence_error(err, code, 6)
    dotted = ".".join(str(k) for k in key)
    assert f"In the result file {path}, `{dotted}` {expected}" in text
    assert "regenerate the file" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.yaml"]


def test_binary_and_missing_files_are_refused(tmp_path, capsys):
    binary = tmp_path / "b.yaml"
    binary.write_bytes(b"\x00\xff\xfe" * 10)
    code, _, err = run(["report", str(binary)], capsys)
    assert "not a licalib result" in _one_sentence_error(err, code, 6)
    code, _, err = run(["report", str(tmp_path / "none.yaml")], capsys)
    assert code == 6 and "Traceback" not in err


def test_corrupt_report_data_is_one_sentence(tmp_path, capsys):
    result = tmp_path / "calib.yaml"
    write_result(result)
    report_data_path(result).write_bytes(b"not a zip")
    code, _, err = run(["report", str(result)], capsys)
    text = _one_sentence_error(err, code, 6)
    assert "is not a licalib report-data file" in text
    assert not (tmp_path / "calib.html").exists()


@pytest.mark.parametrize("target", ["calib.yaml", "calib.config.yaml", "calib.report-data.npz"])
def test_output_never_overwrites_an_input(tmp_path, capsys, target):
    result = tmp_path / "calib.yaml"
    write_result(result)
    (tmp_path / "calib.config.yaml").write_text("bag: {}\n")
    ReportData(result_created_utc=CREATED).save(report_data_path(result))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    code, _, err = run(["report", str(result), "-o", str(tmp_path / target)], capsys)
    text = _one_sentence_error(err, code, 6)
    assert "give another output path" in text
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_calibrate_refuses_bad_report_and_map_paths_before_reading(tmp_path, capsys):
    bag = tmp_path / "rig.bag"
    bag.write_bytes(b"not read")
    base = ["calibrate", str(bag), "-o", str(tmp_path / "c.yaml")]
    code, _, err = run([*base, "--map", str(tmp_path / "map.xyz")], capsys)
    assert "name the file .ply or .pcd" in _one_sentence_error(err, code, 6)
    code, _, err = run([*base, "--map", str(bag.with_suffix(".ply")), "--report", str(bag)], capsys)
    assert "is the input bag" in _one_sentence_error(err, code, 6)
    same = str(tmp_path / "m.ply")
    code, _, err = run([*base, "--map", same, "--map-before", same], capsys)
    assert "is also the output of --map" in _one_sentence_error(err, code, 6)
    code, _, err = run([*base, "--report", str(tmp_path / "c.yaml")], capsys)
    assert "is also the output of -o" in _one_sentence_error(err, code, 6)
    assert bag.read_bytes() == b"not read"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.bag"]


def test_estimated_intrinsics_are_tabled_with_their_sigmas(tmp_path):
    from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
    from licalib_cli.sections import AddedEffect, IntrinsicsUncertainty, ModelInfo

    base = write_result(tmp_path / "calib.yaml")
    lidar = LidarIntrinsics.nominal(np.radians([-15.0, 15.0]))
    result = CalibrationResult(
        extrinsic=base.extrinsic,
        imu_intrinsics=ImuIntrinsics(gyro_scale=np.array([1.002, 0.999, 1.0])),
        lidar_intrinsics=LidarIntrinsics(
            lidar.nominal_elevation,
            lidar.elevation_correction,
            lidar.azimuth_correction,
            lidar.vertical_offset,
            lidar.horizontal_offset,
            lidar.range_scale,
            np.array([0.0, 0.012]),
        ),
        model=ModelInfo(("gyro_scale",), ("range_offset",), 0, ()),
        intrinsics_uncertainty=IntrinsicsUncertainty(
            {"gyro_scale": (1e-4, 2e-4, None), "range_offset_m": (0.001, 0.002)}
        ),
        verdict=base.verdict,
    )
    page = render_html(result, None, "calib.yaml")
    assert '<td class="l">gyro_scale x</td><td class="">1.002</td><td class="">0.0001</td>' in page
    assert '<td class="l">gyro_scale z</td><td class="">1</td><td class="">-</td>' in page
    assert "range_offset (mm)" in page and "12 +- 2" in page
    assert "spread across beams" not in page
    spread = ModelInfo(("gyro_scale",), ("range_offset",), 0, (), {"range_offset": 0.0021})
    page = render_html(replace(result, model=spread), None, "calib.yaml")
    assert "drawn toward nominal with the spread across beams range_offset 0.0021" in page
    saved = tmp_path / "spread.yaml"
    replace(result, model=spread).save(saved)
    assert CalibrationResult.load(saved).model.lidar_spread == {"range_offset": 0.0021}
    assert "beyond doubt" not in page
    added = AddedEffect("lidar_range_offset", 35716.5, 16, -909137.0, 0.0132, 0.0291, 7.7e-5)
    page = render_html(replace(result, model=replace(spread, added=(added,))), None, "calib.yaml")
    assert (
        "Added to the configured model because the data showed them beyond doubt: "
        "lidar_range_offset (score test 35716 on 16 degrees of freedom; its refit&#x27;s BIC "
        "-909137, extrinsic moved 13.20 mm / 0.0291 deg / 0.077 ms)." in page
    )
    # an effect estimated in place of a rival the recording does not tell it from says so
    rival = replace(
        added,
        effect="gyro_rotation",
        rival="gyro_scale",
        rival_delta_bic=-17.1,
        not_told_apart=("gyro_scale",),
    )
    page = render_html(replace(result, model=replace(spread, added=(rival,))), None, "calib.yaml")
    assert (
        "0.077 ms; this recording does not tell it from gyro_scale, which fit the same data 17 "
        "worse in BIC)." in page
    )
    told = replace(rival, not_told_apart=())
    page = render_html(replace(result, model=replace(spread, added=(told,))), None, "calib.yaml")
    assert "0.077 ms; gyro_scale, which could stand in for it, fit the same data worse)." in page
    assert "determines none of the numbers" not in page
    weighed = replace(spread, undetermined=("accel_misalignment",))
    page = render_html(replace(result, model=weighed), None, "calib.yaml")
    assert (
        "The recording determines none of the numbers of accel_misalignment: estimated as "
        "configured, the sigmas include how far holding it at nominal moves the extrinsic." in page
    )


def test_truth_given_to_report_is_shown_beside_the_estimate(tmp_path, capsys):
    result = tmp_path / "calib.yaml"
    write_result(result)
    truth = tmp_path / "truth.yaml"
    CalibrationResult(
        extrinsic=Extrinsic(
            matrix_from_rpy_deg([180.0, 0.0, 90.0]), np.array([0.31, -0.15, 0.05]), -0.007
        )
    ).save(truth)
    code, _, err = run(["report", str(result), "--truth", str(truth)], capsys)
    assert code == 0, err
    page = (tmp_path / "calib.html").read_text()
    assert '<th class="">truth</th>' in page and "-10.00 mm" in page and "-0.100 ms" in page
    code, _, err = run(["report", str(result), "--truth", str(truth), "-o", str(truth)], capsys)
    assert "is the truth file" in _one_sentence_error(err, code, 6)


def test_a_weakly_determined_direction_is_listed_and_the_page_does_not_say_all_determined(
    tmp_path, capsys
):
    weak = (
        "ext.rotation along [-0.30, 0.76, -0.55] in the LiDAR frame: weakly determined by the "
        "data (singular value 0.77, below the threshold: one standard deviation of 1.1 "
        "characteristic scales along it, which the sigmas include)"
    )
    path = tmp_path / "calib.yaml"
    result = write_result(path, "warn", (f"Weakly determined by this data: {weak}.",))
    assert result.observability is not None
    obs = replace(result.observability, unobservable=(), weakly_determined=(weak,))
    replace(result, observability=obs).save(path)
    assert CalibrationResult.load(path).observability.weakly_determined == (weak,)
    code, _, err = run(["report", str(path)], capsys)
    assert code == 0, err
    page = (tmp_path / "calib.html").read_text()
    assert "1 direction(s) were weakly determined" in page
    assert f"<li>{weak}</li>" in page
    assert "Every calibration direction was determined" not in page
    assert "at least 0.1 of the threshold" in page  # the rule as the fit applied it
    # another floor, and none: the page states the rule of the result, not the default
    for floor, said in ((0.25, "at least 0.25 of the threshold"), (0.0, "solver.weak_floor off")):
        replace(result, observability=replace(obs, weak_floor=floor)).save(path)
        assert CalibrationResult.load(path).observability.weak_floor == floor
        code, _, err = run(["report", str(path)], capsys)
        assert code == 0, err
        assert said in (tmp_path / "calib.html").read_text()
