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


@pytest.mark.parametrize(
    ("setting", "said"),
    [
        (
            "checks=5",
            "'checks' is a section of settings, not a value; give its keys one by one, such as "
            "checks.max_translation_sigma_m.",
        ),
        ("model=null", "'model' is a section of settings, not a value;"),
        ("model.lidar_prior=3", "such as model.lidar_prior.elevation_deg."),
        ("model.imu=gyro_scale", "'model.imu' takes a list; write [gyro_scale] for that one item."),
        ("surfels.cell_sizes_m={a: 1}", "'surfels.cell_sizes_m' takes a list, such as [1.0, 0.5]."),
        (
            "initialization.translation_m=abc",
            "'initialization.translation_m' takes a list of 3 items.",
        ),
        ("model.expected_size=[1]", "takes a mapping of names to values, such as {name: value}."),
    ],
)
def test_a_value_of_the_wrong_form_says_the_form(
    setting: str, said: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A section given one value, or a list or mapping given a single value: the message shows
    the form the setting takes, not the form's class name, from --set and from a file alike."""
    code, _, err = run(["config", "dump", "--set", setting], capsys)
    assert code == 6
    text = " ".join(err.split())
    assert said in text and "Section" not in text, text
    key, _, value = setting.partition("=")
    *sections, leaf = key.split(".")
    nested = leaf + ": " + value
    for name in reversed(sections):  # the same setting written in a file
        nested = name + ":\n" + "\n".join("  " + ln for ln in nested.splitlines())
    cfg = tmp_path / "c.yaml"
    cfg.write_text(nested + "\n")
    code, _, err = run(["config", "dump", "-c", str(cfg)], capsys)
    assert code == 6
    text = " ".join(err.split())
    assert f"Invalid setting '{key}' in the config file" in text and said in text, text


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
