"""``licalib export``: standard output or an atomic file, refusals with one sentence and a
documented exit code, never a partial file and never an input overwritten."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.export import ExportTarget, export, resolve_frames
from licalib_cli.results import CalibrationResult, Extrinsic, matrix_from_rpy_deg
from licalib_cli.sections import Provenance, RecordingSection, VerdictSection


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
    path: Path,
    verdict: str = "pass",
    reasons: tuple[str, ...] = (),
    shift: float = 0.0,
) -> CalibrationResult:
    result = CalibrationResult(
        extrinsic=Extrinsic(
            matrix_from_rpy_deg([180.0, 0.0, 90.0]), np.array([0.3, -0.15, 0.05]), -0.0071
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
            shift,
            shift,
        ),
        provenance=Provenance("0.1.0", "0123456789abcdef", "2026-11-24T07:00:00Z"),
    )
    result.save(path)
    return CalibrationResult.load(path)


@pytest.mark.parametrize("target", list(ExportTarget), ids=[t.value for t in ExportTarget])
def test_each_target_to_stdout_and_to_a_file(
    target: ExportTarget, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    result = write_result(tmp_path / "calib.yaml")
    frames = ["--parent", "imu", "--child", "lidar"] if target.value in ("urdf", "tf2") else []
    args = ["export", str(tmp_path / "calib.yaml"), "--to", target.value, *frames]
    code, out, err = run(args, capsys)
    assert code == 0, err
    expected = export(
        result,
        target,
        frames=resolve_frames(result, "imu", "lidar") if frames else None,
    )
    assert out == expected
    dest = tmp_path / "sub" / f"out.{target.value}"
    code, out, err = run([*args, "-o", str(dest)], capsys)
    assert code == 0, err
    assert out == "" and dest.read_text() == expected
    assert not [p for p in dest.parent.iterdir() if p.name.startswith(".")]  # no temporary left
    # an existing output is replaced
    code, _, err = run([*args, "-o", str(dest)], capsys)
    assert code == 0 and dest.read_text() == expected, err


def test_fast_lio_ros2_form_from_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write_result(tmp_path / "calib.yaml")
    code, out, err = run(
        ["export", str(tmp_path / "calib.yaml"), "--to", "fast-lio", "--ros2"], capsys
    )
    assert code == 0, err
    params = yaml.safe_load(out)["/**"]["ros__parameters"]
    assert params["common"]["time_offset_lidar_to_imu"] == pytest.approx(-0.0071, abs=1e-12)


def test_fail_verdict_exits_9_without_a_file_unless_forced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "calib.yaml"
    write_result(src, "fail", ("the translation along z is not observable",))
    dest = tmp_path / "fast_lio.yaml"
    code, out, err = run(["export", str(src), "--to", "fast-lio", "-o", str(dest)], capsys)
    text = _one_sentence_error(err, code, 9)
    assert "verdict is fail" in text and "not observable" in text and "--force" in text
    assert out == "" and not dest.exists()
    code, out, err = run(
        ["export", str(src), "--to", "fast-lio", "-o", str(dest), "--force"], capsys
    )
    assert code == 0, err
    assert dest.exists() and "verdict is fail" in err
    assert "verdict: fail" in dest.read_text()


def test_warn_verdict_and_clock_shift_are_exported_with_warnings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "calib.yaml"
    write_result(src, "warn", ("the gyro residuals grow with the angular rate",), shift=-2.0)
    code, out, err = run(["export", str(src), "--to", "kalibr"], capsys)
    assert code == 0, err
    assert "verdict is warn" in err and "LiDAR clock shift" in err
    assert yaml.safe_load(out)["lidar0"]["timeshift_lidar_imu"] == pytest.approx(-2.0071)


def _bad_inputs(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    (tmp_path / "config.yaml").write_text("imu:\n  topic: /imu\n")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    (tmp_path / "empty.yaml").write_text("")
    (tmp_path / "broken.yaml").write_text("extrinsic: [1, 2\n")
    (tmp_path / "binary.bag").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "v2.yaml").write_text("schema_version: 2\nextrinsic: {}\n")
    (tmp_path / "no_extrinsic.yaml").write_text("schema_version: 1\nverdict: {status: pass}\n")
    (tmp_path / "folder").mkdir()
    return {
        "config-file": (
            tmp_path / "config.yaml",
            "is not a licalib result (it has no schema_version)",
        ),
        "list": (tmp_path / "list.yaml", "is not a licalib result (not a YAML mapping)"),
        "empty": (tmp_path / "empty.yaml", "is not a licalib result (not a YAML mapping)"),
        "broken": (tmp_path / "broken.yaml", "is not valid YAML"),
        "binary": (tmp_path / "binary.bag", "is not a licalib result (not a text file)"),
        "other-version": (
            tmp_path / "v2.yaml",
            "schema version 2, but this licalib exports version 1",
        ),
        "no-extrinsic": (tmp_path / "no_extrinsic.yaml", "is not a complete licalib result"),
        "missing": (tmp_path / "nope.yaml", "does not exist"),
        "folder": (tmp_path / "folder", "cannot be read"),
    }


@pytest.mark.parametrize(
    "name",
    [
        "config-file",
        "list",
        "empty",
        "broken",
        "binary",
        "other-version",
        "no-extrinsic",
        "missing",
        "folder",
    ],
)
def test_bad_result_files_exit_6_in_one_sentence_without_a_file(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, words = _bad_inputs(tmp_path)[name]
    dest = tmp_path / "out.yaml"
    code, out, err = run(["export", str(path), "--to", "fast-lio", "-o", str(dest)], capsys)
    text = _one_sentence_error(err, code, 6)
    assert words in text
    assert out == "" and not dest.exists()


def test_inputs_are_never_overwritten(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "calib.yaml"
    write_result(src)
    config = tmp_path / "calib.config.yaml"
    config.write_text("imu: {}\n")
    bag = tmp_path / "rig.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    link = tmp_path / "link.yaml"
    link.symlink_to(src)
    before = {p: p.read_bytes() for p in (src, config, bag)}
    for dest, what in (
        (src, "the result file being exported"),
        (link, "the result file being exported"),
        (tmp_path / "sub" / ".." / "calib.yaml", "the result file being exported"),
        (config, "the result's resolved config"),
        (bag, "the calibrated bag"),
    ):
        code, _, err = run(["export", str(src), "--to", "json", "-o", str(dest)], capsys)
        assert what in _one_sentence_error(err, code, 6)
    assert {p: p.read_bytes() for p in before} == before


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--to", "urdf"], "records no frame ids"),
        (["--to", "tf2", "--parent", "imu"], "pass --parent and --child"),
        (["--to", "urdf", "--parent", "imu", "--child", "lidar", "--ros2"], "--ros2 applies to"),
        (["--to", "fast-lio", "--parent", "imu"], "apply to urdf and tf2 only"),
        (["--to", "kalibr", "--parent-sensor", "lidar"], "apply to urdf and tf2 only"),
    ],
    ids=["urdf-no-frames", "tf2-parent-only", "ros2-urdf", "frames-fast-lio", "sensor-kalibr"],
)
def test_option_problems_exit_6(
    args: list[str], words: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "calib.yaml"
    write_result(src)
    dest = tmp_path / "out.txt"
    code, _, err = run(["export", str(src), *args, "-o", str(dest)], capsys)
    assert words in _one_sentence_error(err, code, 6)
    assert not dest.exists()


def test_unknown_target_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "calib.yaml"
    write_result(src)
    code, _, err = run(["export", str(src), "--to", "ros"], capsys)
    assert code == 6 and "Invalid value for '--to'" in err


def test_the_golden_result_file_exports(capsys: pytest.CaptureFixture[str]) -> None:
    """A result with every section ``calibrate`` writes (tests/golden/result_v1.yaml)."""
    golden = Path(__file__).parents[1] / "golden" / "result_v1.yaml"
    result = CalibrationResult.load(golden)
    code, out, err = run(["export", str(golden), "--to", "fast-lio"], capsys)
    assert code == 0, err
    assert "LiDAR clock shift" in err  # the golden recording carries one
    mapping = yaml.safe_load(out)["mapping"]
    np.testing.assert_allclose(
        np.reshape(mapping["extrinsic_R"], (3, 3)), result.extrinsic.rotation, atol=1e-9
    )
    code, out, err = run(["export", str(golden), "--to", "json"], capsys)
    assert code == 0, err
    assert CalibrationResult.from_dict(json.loads(out)).to_dict() == result.to_dict()


def test_frames_default_to_the_ids_calibrate_recorded(capsys: pytest.CaptureFixture[str]) -> None:
    """calibrate records the sensors' header.frame_id (recording.imu_frame, lidar_frame), so the
    URDF joint and the tf2 lines need no names."""
    golden = Path(__file__).parents[1] / "golden" / "result_v1.yaml"
    code, out, err = run(["export", str(golden), "--to", "urdf"], capsys)
    assert code == 0, err
    assert '<parent link="imu_link"/>' in out and '<child link="velodyne"/>' in out
    code, out, err = run(["export", str(golden), "--to", "tf2", "--parent-sensor", "lidar"], capsys)
    assert code == 0, err
    assert "--frame-id velodyne --child-frame-id imu_link" in out
