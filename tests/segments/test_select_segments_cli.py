"""select-segments and calibrate --segments on a short simulated walk with one shaking burst."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.simulation import SimulationSpec, simulate

pytestmark = pytest.mark.slow

KNOWN = """\
initialization:
  rotation_rpy_deg: [1.0, 2.0, 5.0]
  translation_m: [0.3, 0.15, 0.05]
  time_offset_s: 0.0
"""


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[list[float]]]:
    """12 s of walking with a burst of shaking at 6.1-10.4 s (seed 0), and a config that gives
    the extrinsic (the selection then skips the odometry)."""
    folder = tmp_path_factory.mktemp("walk")
    spec = SimulationSpec(
        scenario="walk", duration_s=12.0, seed=0, intrinsics="none", azimuth_resolution_deg=2.0
    )
    sim = simulate(spec, folder / "sim")
    truth = yaml.safe_load((sim.bag_path.parent / "truth.yaml").read_text())
    config = folder / "known.yaml"
    config.write_text(KNOWN)
    return sim.bag_path, config, truth["scenario"]["bursts_s"]


def test_the_burst_windows_rank_first_and_json_lists_every_window(walk, capsys) -> None:
    bag, config, bursts = walk
    assert bursts == [[6.143, 10.375]]
    main(["select-segments", str(bag), "-c", str(config), "--length", "3", "--top", "2", "--json"])
    out = json.loads(capsys.readouterr().out)
    seg = out["segments"]
    assert [(s["start_s"], s["end_s"]) for s in seg[:2]] == [(6.0, 9.0), (9.0, 12.0)]
    assert {(s["start_s"], s["end_s"]) for s in seg} == {(0, 3), (3, 6), (6, 9), (9, 12)}
    for s in seg:
        for key in ("min_singular_value", "trace", "logdet", "weak_directions", "selected"):
            assert key in s
        assert s["weak_directions"] and s["weak_directions"][0].startswith("ext.")
    assert [s["selected"] for s in seg] == [True, True, False, False]
    # the shaking burst tilts the rig; calm walking hardly does
    tilt = {(s["start_s"], s["end_s"]): s["tilt_deg"] for s in seg}
    assert tilt[(6.0, 9.0)] > 2.5 * tilt[(0, 3)] and tilt[(0, 3)] < 3.0
    # ranked by the minimum singular value; the shaking window by a wide margin
    values = [s["min_singular_value"] for s in seg]
    assert values == sorted(values, reverse=True)
    assert values[0] > 5 * values[2]
    assert out["estimate"]["source"] == "config"
    # the two selected windows together determine more than the better one alone
    together = out["selected_together"]
    assert together["min_singular_value"] > values[0]
    assert together["weakest_direction"].startswith("ext.")
    assert len(together["singular_values"]) == 6  # each window keeps its own time offset


def _ranked(walk, capsys, *extra: str) -> dict:
    bag, config, _ = walk
    main(["select-segments", str(bag), "-c", str(config), "--length", "3", "--json", *extra])
    return json.loads(capsys.readouterr().out)


def test_the_models_imu_intrinsics_count_as_unknown_in_the_metric(walk, capsys) -> None:
    base = _ranked(walk, capsys)
    imu = _ranked(walk, capsys, "--intrinsics", "imu")
    lidar = _ranked(walk, capsys, "--intrinsics", "lidar")
    assert base["intrinsics_unknown"] == [] and base["model_not_ranked"] == []
    assert imu["intrinsics_unknown"] == [
        "imu.gyro_scale",
        "imu.gyro_misalignment",
        "imu.gyro_rotation",
        "imu.accel_scale",
        "imu.accel_misalignment",
    ]
    assert imu["model_not_ranked"] == []
    assert lidar["intrinsics_unknown"] == []
    assert lidar["model_not_ranked"][0] == "lidar.elevation" and len(lidar["model_not_ranked"]) == 6

    def metric(out: dict) -> dict:
        return {s["start_s"]: s["min_singular_value"] for s in out["segments"]}

    m0, m_imu, m_lidar = metric(base), metric(imu), metric(lidar)
    assert m_lidar == pytest.approx(m0, rel=1e-9)  # the LiDAR's are not part of it
    for start, value in m0.items():
        # unknown intrinsics can only take information away; the extrinsic rotation trades
        # with the accelerometer's misalignment on a rig that hardly tilts
        assert m_imu[start] < 0.8 * value
    assert imu["segments"][0]["start_s"] == 6.0  # the shaking still ranks first
    for s in imu["segments"]:
        assert s["weak_directions"][0].startswith("ext.")
        assert any(w.startswith("imu.accel_misalignment") for w in s["weak_directions"])
    bag, config, _ = walk
    main(["select-segments", str(bag), "-c", str(config), "--length", "6", "--intrinsics", "all"])
    printed = " ".join(capsys.readouterr().out.split())
    assert "Metric with the model's imu.gyro_scale, imu.gyro_misalignment," in printed
    assert "Not part of the metric: lidar.elevation, lidar.azimuth," in printed


def test_table_overlapping_windows_and_plot(walk, tmp_path, capsys) -> None:
    bag, config, _ = walk
    plot = tmp_path / "figs" / "segments.png"
    main(
        [
            "select-segments",
            str(bag),
            "-c",
            str(config),
            "--length",
            "4",
            "--step",
            "2",
            "--start",
            "1",
            "--plot",
            str(plot),
        ]
    )
    printed = capsys.readouterr().out
    assert "weakest direction" in printed and "Selected: " in printed
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # windows 1-5, 3-7, 5-9, 7-11, then one aligned to the end of the bag
    for w in ("1.0-5.0", "3.0-7.0", "5.0-9.0", "7.0-11.0"):
        assert w in printed


def _refused(bag: Path, tmp_path: Path, capsys, *options: str) -> tuple[int, str]:
    """``calibrate BAG OPTIONS -o r.yaml`` expected to exit before writing: its exit code and
    standard error."""
    with pytest.raises(SystemExit) as info:
        main(["calibrate", str(bag), *options, "-o", str(tmp_path / "r.yaml")])
    assert not (tmp_path / "r.yaml").exists()
    return int(info.value.code or 0), capsys.readouterr().err


@pytest.mark.parametrize(
    ("segments", "code", "text"),
    [
        ("1-5,4-8", 6, "overlap"),
        ("5-20", 6, "reaches past the end of the bag"),
        ("2-3", 7, "too short to calibrate"),
        ("2-x", 6, "Invalid --segments window"),
    ],
)
def test_segments_option_errors(walk, tmp_path, capsys, segments, code, text) -> None:
    bag, _, _ = walk
    got, err = _refused(bag, tmp_path, capsys, "--segments", segments)
    assert got == code
    assert text in err and "Traceback" not in err


def test_segments_with_start_is_refused(walk, tmp_path, capsys) -> None:
    bag, _, _ = walk
    code, _ = _refused(bag, tmp_path, capsys, "--segments", "auto", "--start", "2")
    assert code == 6


@pytest.mark.parametrize("through", ["config", "truth", "link"])
def test_an_input_a_windows_report_data_would_overwrite_is_refused_before_the_fit(
    walk, tmp_path, capsys, through
) -> None:
    """``r.seg3.report-data.npz`` beside ``-o r.yaml`` is what the third window's report data
    would be written to: given as an input (or linked to from one), it is refused at once,
    whatever the windows, and left as it was."""
    bag, config, _ = walk
    victim = tmp_path / "r.seg3.report-data.npz"
    victim.write_text(config.read_text())
    given = victim
    if through == "link":
        given = tmp_path / "linked.yaml"
        given.symlink_to(victim)
    option = "--truth" if through == "truth" else "-c"
    code, err = _refused(bag, tmp_path, capsys, "--segments", "auto", option, str(given))
    assert code == 6 and "Traceback" not in err
    text = " ".join(err.split())
    assert f"The report data of seg3 that calibrate writes next to the result, {victim}" in text
    assert "give another output path with -o" in text
    assert victim.read_text() == config.read_text()
    # beside a result of another name it is no window's report data: accepted
    from licalib_cli.commands.segments_render import check_window_outputs

    check_window_outputs(tmp_path / "other.yaml", [("the config file", given)])


def _ply_points(path: Path) -> np.ndarray:
    """The records of a map file ``calibrate --map`` wrote as PLY."""
    from licalib_cli.io.map_writer import POINT_DTYPE

    raw = path.read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    count = int(
        next(x for x in head.decode().splitlines() if x.startswith("element vertex")).split()[-1]
    )
    points = np.frombuffer(body, dtype=POINT_DTYPE)
    assert points.shape[0] == count
    return points


def test_calibrate_two_segments_jointly(walk, tmp_path, capsys) -> None:
    bag, config, _ = walk
    out = tmp_path / "joint.yaml"
    truth = bag.parent / "truth.yaml"
    main(
        [
            "calibrate",
            str(bag),
            "-c",
            str(config),
            "--segments",
            "6-9,9-12",
            "-o",
            str(out),
            "--truth",
            str(truth),
            "--map",
            str(tmp_path / "map.ply"),
            "--map-before",
            str(tmp_path / "before.ply"),
            "--report",
            str(tmp_path / "joint.html"),
            "--plots",
            str(tmp_path / "plots"),
        ]
    )
    printed = capsys.readouterr().out
    assert "joint" in printed and "Verdict:" in printed
    # The report shows the joint estimate with each window's own beside it, says which
    # figures the joint fit has none of (no single trajectory and map) instead of drawing one
    # window's as the joint's, and draws each window's own fit, motion and map in its section.
    page = (tmp_path / "joint.html").read_text()
    assert "<h2>Segments</h2>" in page and "6.0-9.0 s" in page and "9.0-12.0 s" in page
    assert ">seg2<" in page and ">joint<" in page
    assert "(reference)" in page and "calibrated alone" in page
    assert "not shown for the joint fit" in page
    assert "the result has no report data" not in page
    windows = page.split('<h2 id="seg1">seg1 (6.0-9.0 s) calibrated alone</h2>')
    assert len(windows) == 2
    first, second = windows[1].split('<h2 id="seg2">seg2 (9.0-12.0 s) calibrated alone</h2>')
    for section in (first, second.split("<h2>Provenance</h2>")[0]):
        # distances, IMU residuals, rounds, motion, map: five figures, nothing missing
        assert section.count("<img ") == 5 and 'class="missing"' not in section
    assert "--segments" in page.split("<h2>Provenance</h2>")[1]  # the command line
    assert "truth" in page.split("<h2>Segments</h2>")[0].lower()  # the --truth column
    sidecars = ["joint.report-data.npz", "joint.seg1.report-data.npz", "joint.seg2.report-data.npz"]
    assert all((tmp_path / n).is_file() for n in sidecars)
    # licalib report on the joint result draws the same page from the files
    main(["report", str(out), "-o", str(tmp_path / "again.html")])
    again = (tmp_path / "again.html").read_text()
    assert again.count("<img ") == page.count("<img ") and "calibrated alone</h2>" in again
    # a window without its report data: its section says so, the other's is drawn
    (tmp_path / "joint.seg2.report-data.npz").unlink()
    main(["report", str(out), "-o", str(tmp_path / "third.html")])
    third = (tmp_path / "third.html").read_text()
    assert "seg2's figures not shown: its report data" in third
    assert third.count("<img ") == page.count("<img ") - 5
    # a window's report data is never overwritten, and a damaged one is one sentence
    from tests.report.test_report_cli import _one_sentence_error, run

    seg1 = tmp_path / "joint.seg1.report-data.npz"
    kept = seg1.read_bytes()
    code, _, err = run(["report", str(out), "-o", str(seg1)], capsys)
    assert "give another output path" in _one_sentence_error(err, code, 6)
    assert seg1.read_bytes() == kept
    seg1.write_bytes(b"not a zip")
    code, _, err = run(["report", str(out), "-o", str(tmp_path / "fourth.html")], capsys)
    assert "is not a licalib report-data file" in _one_sentence_error(err, code, 6)
    assert not (tmp_path / "fourth.html").exists()
    # The joint spectrum, the windows against the joint estimate, and each window's own fit.
    drawn = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert drawn == [
        "observability.png",
        "seg1.fit.png",
        "seg1.map_entropy.png",
        "seg2.fit.png",
        "seg2.map_entropy.png",
        "segments.png",
    ]
    assert all((tmp_path / "plots" / n).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for n in drawn)
    # One map per segment, each with its own points on its own time axis (s since its start);
    # the joint calibration and trajectory place them otherwise than the initial guess does.
    maps = {p.name: _ply_points(p) for p in sorted(tmp_path.glob("*.ply"))}
    assert sorted(maps) == ["before.seg1.ply", "before.seg2.ply", "map.seg1.ply", "map.seg2.ply"]
    for name, points in maps.items():
        assert points.shape[0] > 10_000, name
        assert points["beam"].min() >= 0 and points["beam"].max() == 15  # VLP-16
        assert 0.0 <= points["time"].min() and points["time"].max() <= 3.2, name
        said = f"{tmp_path / name}({points.shape[0]}points)"
        assert said in "".join(printed.split())  # rich wraps long lines
    assert not np.array_equal(maps["map.seg1.ply"], maps["map.seg2.ply"])
    for k in (1, 2):
        joint, before = maps[f"map.seg{k}.ply"], maps[f"before.seg{k}.ply"]
        assert np.array_equal(joint["beam"], before["beam"])  # the same points, placed twice
        xyz = lambda p: np.stack([p["x"], p["y"], p["z"]], axis=1)  # noqa: E731
        assert not np.allclose(xyz(joint), xyz(before), atol=1e-4)
    result = yaml.safe_load(out.read_text())
    seg = result["segments"]
    assert [(s["start_s"], s["end_s"]) for s in seg["segments"]] == [(6.0, 9.0), (9.0, 12.0)]
    assert all(s["disagrees"] is False for s in seg["segments"])
    ext = result["extrinsic"]
    assert abs(ext["translation"][0] - 0.3) < 0.01
    # the joint sigma is below each segment's own
    joint_sigma = result["uncertainty"]["translation_std_m"]
    for s in seg["segments"]:
        assert all(j < o for j, o in zip(joint_sigma, s["translation_std_m"], strict=True))
    assert (tmp_path / "joint.config.yaml").exists()


def test_the_joint_sigmas_meet_the_checks_limits_of_a_pass(walk, tmp_path, capsys) -> None:
    """The joint estimate is held to the same ``checks`` limits as one segment: with a limit
    below its sigmas the verdict warns and says which; as the windows' last rounds kept 1000 of
    the about 2900 points of each sweep, it says that more would narrow the joint sigma."""
    bag, config, _ = walk
    strict = tmp_path / "strict.yaml"
    strict.write_text(
        config.read_text()
        + "checks:\n  max_translation_sigma_m: 1.0e-6\n"
        + "surfels:\n  points_per_scan: 500\n  final_points_per_scan: 1000\n"
    )
    out = tmp_path / "joint.yaml"
    main(["calibrate", str(bag), "-c", str(strict), "--segments", "6-9,9-12", "-o", str(out)])
    capsys.readouterr()
    verdict = yaml.safe_load(out.read_text())["verdict"]
    assert verdict["status"] != "pass"
    (said,) = [r for r in verdict["reasons"] if r.startswith("Joint estimate: Translation is")]
    kept = re.search(r"The last round kept (\d+) of about (\d+) points a sweep: more", said)
    assert kept is not None and int(kept[1]) == 1000 and 2800 < int(kept[2]) < 3000, said


def test_the_segments_figure_measures_each_window_as_the_disagreement_check_does(walk) -> None:
    """``segments.png`` draws each window alone minus the joint estimate over its own sigmas:
    the largest of those over the translation and rotation axes is the result's
    ``disagreement_sigmas``, computed from the runs themselves (same rotation convention)."""
    from licalib_cli.config import load_config
    from licalib_cli.pipeline.joint import calibrate_segments
    from licalib_cli.plots import segment_offsets

    bag, config, _ = walk
    run = calibrate_segments(bag, load_config(config), "6-9,9-12")
    own, own_sd, joint_sd, windows = segment_offsets(run)
    assert own.shape == own_sd.shape == joint_sd.shape == (2, 7)
    assert windows.tolist() == [[6.0, 9.0], [9.0, 12.0]]
    for k, e in enumerate(run.segments.segments):
        z = np.abs(own[k, :6]) / own_sd[k, :6]
        z = z[np.isfinite(z) & np.isfinite(own_sd[k, :6])]
        assert (float(z.max()) if z.size else 0.0) == pytest.approx(e.disagreement_sigmas, abs=1e-3)
        assert own[k, 6] == pytest.approx(1e3 * (e.time_offset_s - e.joint_time_offset_s))
    # the joint sigmas of the shared extrinsic are below each window's own where the window
    # determines the coordinate; a segment's time offset is its own in the joint problem too
    # (no more information than alone, and the joint's enlargements): about the same
    finite = np.isfinite(own_sd)
    shared = finite[:, :6]
    assert np.all(joint_sd[:, :6][shared] < own_sd[:, :6][shared])
    assert np.all(joint_sd[finite[:, 6], 6] < 1.05 * own_sd[finite[:, 6], 6])


def test_model_auto_diagnoses_every_window_and_calibrates_them_with_what_they_kept(
    walk, tmp_path, capsys
) -> None:
    """``--segments --model auto``: each window is diagnosed alone, the joint calibration
    estimates what any of them kept (nothing on this clean walk), and the resolved config
    written beside the result estimates exactly that model."""
    bag, config, _ = walk
    out = tmp_path / "joint.yaml"
    args = ["calibrate", str(bag), "-c", str(config), "--segments", "6-9,9-12", "--model", "auto"]
    main([*args, "-o", str(out)])
    printed = " ".join(capsys.readouterr().out.split())
    assert "seg1 (6.0-9.0 s) diagnosed alone" in printed
    assert "seg2 (9.0-12.0 s) diagnosed alone" in printed
    assert printed.count("Base model: residuals measured and on its twin recording") == 2
    assert "Model of the joint calibration (every effect a window kept): the base model" in printed
    assert printed.index("diagnosed alone") < printed.index("Verdict:")
    result = yaml.safe_load(out.read_text())
    resolved = yaml.safe_load((tmp_path / "joint.config.yaml").read_text())
    assert resolved["model"]["imu"] == [] and resolved["model"]["lidar"] == []
    assert [(s["start_s"], s["end_s"]) for s in result["segments"]["segments"]] == [
        (6.0, 9.0),
        (9.0, 12.0),
    ]
    assert abs(result["extrinsic"]["translation"][0] - 0.3) < 0.01


def test_model_auto_with_intrinsics_is_refused_with_segments_too(walk, tmp_path, capsys) -> None:
    bag, _, _ = walk
    options = ("--segments", "6-9,9-12", "--model", "auto", "--intrinsics", "imu")
    code, err = _refused(bag, tmp_path, capsys, *options)
    assert code == 6
    assert "--model auto chooses the intrinsics itself" in err and "Traceback" not in err
