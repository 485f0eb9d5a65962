"""``--set KEY=VALUE``: one setting changed on the command line, over the config file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, LicalibError
from tests.cli.test_bad_input import run

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "sinusoid_vlp16" / "bag.bag"


def _dump(argv: list[str], capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    code, out, err = run(["config", "dump", *argv], capsys)
    assert code == 0, err
    return yaml.safe_load(out)


def test_settings_change_the_resolved_config_over_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("surfels:\n  final_points_per_scan: 3000\n  max_points: 900000\n")
    dense = _dump(
        [
            "-c",
            str(cfg),
            "--set",
            "surfels.final_points_per_scan=15000",
            "--set",
            "surfels.max_points=1500000",
            "--set",
            "model.imu=[gyro_scale, accel_scale]",
        ],
        capsys,
    )
    assert dense["surfels"]["final_points_per_scan"] == 15000
    assert dense["surfels"]["max_points"] == 1500000
    assert dense["model"]["imu"] == ["gyro_scale", "accel_scale"]
    default = yaml.safe_load(yaml.safe_dump(CalibConfig().model_dump(mode="json")))
    assert dense["imu"] == default["imu"]  # what no setting names: the file's (the default)
    # null unsets an optional setting; of one key given twice the later wins
    unset = _dump(["-c", str(cfg), "--set", "surfels.final_points_per_scan=null"], capsys)
    assert unset["surfels"]["final_points_per_scan"] is None
    assert unset["surfels"]["max_points"] == 900000  # the file's
    twice = _dump(["--set", "bag.start_s=2", "--set", "bag.start_s=3.5"], capsys)
    assert twice["bag"]["start_s"] == 3.5
    assert cfg.read_text().startswith("surfels:\n  final_points_per_scan: 3000\n")  # untouched


@pytest.mark.parametrize(
    ("setting", "said"),
    [
        ("surfels.final_points_per_scan", "--set takes KEY=VALUE, such as"),
        ("=3", "--set takes KEY=VALUE, such as"),
        ("surfels..x=1", "--set takes KEY=VALUE, such as"),
        ("surfels.final_points_per_scan=", "write surfels.final_points_per_scan=null to unset"),
        ("imu.topic=[a", "The value of --set imu.topic is not valid YAML ('[a')"),
        ("surfels.foo=1", "Unknown setting 'surfels.foo' in --set; licalib config dump prints"),
        ("nosuch.key=1", "Unknown setting 'nosuch.key' in --set"),
        ("surfels.final_points_per_scan=abc", "Invalid value 'abc' for --set surfels.final_"),
        ("surfels.max_points=10", "Invalid value 10 for --set surfels.max_points"),
    ],
)
def test_a_bad_setting_is_one_sentence_and_exit_6(
    setting: str, said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run(["config", "dump", "--set", setting], capsys)
    assert code == ConfigError.exit_code == 6, err
    (line,) = [ln for ln in err.splitlines() if ln.startswith("Error: ")]
    assert said in line and line.endswith("."), line
    assert "Extra inputs" not in err and "Value error," not in err


def test_an_unknown_key_in_the_file_is_named_with_where_to_find_the_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("surfels:\n  final_points: 3000\n")
    code, _, err = run(["config", "dump", "-c", str(cfg)], capsys)
    assert code == 6
    assert (
        f"Unknown setting 'surfels.final_points' in the config file {cfg}; licalib config dump "
        "prints every setting with its default." in " ".join(err.split())
    ), err


class _Stop(LicalibError):
    exit_code = 9


@pytest.mark.parametrize(
    ("command", "target"),
    [
        (["calibrate"], "licalib_cli.pipeline.calibrate"),
        (["diagnose"], "licalib_cli.pipeline.diagnose.diagnose"),
        (["select-segments"], "licalib_cli.pipeline.segments.select_segments"),
    ],
)
def test_the_commands_that_solve_take_the_settings(
    command: list[str],
    target: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each command hands the pipeline the config with its settings; a bad one is refused
    before the bag is read."""
    seen: list[CalibConfig] = []

    def stop(bag: Path, cfg: CalibConfig, *args: object, **kwargs: object) -> None:
        seen.append(cfg)
        raise _Stop("stopped")

    monkeypatch.setattr(target, stop)
    out = ["-o", str(tmp_path / ("out.yaml" if command == ["calibrate"] else "out"))]
    if command == ["select-segments"]:
        out = []
    argv = [*command, str(SAMPLE), *out, "--set", "surfels.final_points_per_scan=12000"]
    code, _, err = run(argv, capsys)
    assert code == 9 and "stopped" in err, err
    assert seen and seen[0].surfels.final_points_per_scan == 12000
    code, _, err = run([*argv[:-1], "surfels.final_point_per_scan=12000"], capsys)
    assert code == 6 and "Unknown setting 'surfels.final_point_per_scan' in --set" in err, err
    assert len(seen) == 1


def test_info_reads_the_segment_the_settings_give(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(["info", str(SAMPLE), "--set", "bag.start_s=2", "--json"], capsys)
    assert code == 0, err
    assert '"start_s": 2.0' in out, out[:400]
    code, _, err = run(["info", str(SAMPLE), "--set", "bag.start=2"], capsys)
    assert code == 6 and "Unknown setting 'bag.start' in --set" in err, err
