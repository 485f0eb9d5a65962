"""``licalib simulate`` through the command line (CliRunner)."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from licalib_cli.cli import main
from licalib_cli.commands.simulate import simulate_command
from licalib_cli.errors import ConfigError
from licalib_cli.simulation import SimulationSpec
from licalib_cli.simulation.ground_truth import draw_time_offset
from licalib_cli.truth import Truth


def _app() -> typer.Typer:
    app = typer.Typer()
    app.command("simulate")(simulate_command)

    @app.command("noop")
    def _noop() -> None:  # a second command keeps "simulate" a subcommand
        """Nothing."""

    return app


def test_simulate_smoke(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    args = [
        "simulate",
        str(out_dir),
        "--duration",
        "1",
        "--seed",
        "3",
        "--time-offset",
        "-0.005",
        "--format",
        "ros2-db3",
        "--translation",
        "-0.1",
        "0.2",
        "0.05",
    ]
    result = CliRunner().invoke(_app(), args)
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    assert lines[-1] == str(out_dir / "bag")
    assert (out_dir / "bag" / "metadata.yaml").exists()
    assert "10 vlp16 scans" in result.output and "401 IMU samples" in result.output
    truth = Truth.load(out_dir / "truth.yaml")
    assert truth.extrinsic.time_offset_s == pytest.approx(-0.005)
    assert truth.extrinsic.translation.tolist() == [-0.1, 0.2, 0.05]
    assert truth.simulation is not None
    cmd = truth.simulation.command_line
    assert "--seed 3" in cmd and "--translation -0.1 0.2 0.05" in cmd

    again = CliRunner().invoke(_app(), args)
    assert again.exit_code != 0
    assert isinstance(again.exception, ConfigError) and "--force" in str(again.exception)
    forced = CliRunner().invoke(_app(), [*args, "--force"])
    assert forced.exit_code == 0, forced.output
    assert Truth.load(out_dir / "truth.yaml").noise_seed is None  # the seed's own noise
    # another noise draw for the same truth is recorded beside the seed
    redrawn = CliRunner().invoke(_app(), [*args, "--force", "--noise-seed", "11"])
    assert redrawn.exit_code == 0, redrawn.output
    again_truth = Truth.load(out_dir / "truth.yaml")
    assert again_truth.seed == 3 and again_truth.noise_seed == 11
    assert again_truth.extrinsic.translation.tolist() == [-0.1, 0.2, 0.05]


def test_tilted_shake_records_its_tilt(tmp_path: Path) -> None:
    out_dir = tmp_path / "tilted"
    args = ["simulate", str(out_dir), "--scenario", "shake", "--duration", "1", "--tilt-deg", "25"]
    result = CliRunner().invoke(_app(), args)
    assert result.exit_code == 0, result.output
    truth = Truth.load(out_dir / "truth.yaml")
    assert truth.scenario is not None and truth.scenario.tilt_deg == 25.0
    assert truth.simulation is not None and "--tilt-deg 25.0" in truth.simulation.command_line
    plain = tmp_path / "plain"
    plain_args = ["simulate", str(plain), "--scenario", "shake", "--duration", "1"]
    assert CliRunner().invoke(_app(), plain_args).exit_code == 0
    # the key is absent without a tilt (truth files of earlier runs read the same)
    assert "tilt_deg" not in (plain / "truth.yaml").read_text()
    assert Truth.load(plain / "truth.yaml").scenario.tilt_deg is None  # type: ignore[union-attr]


def test_invalid_option_is_a_clear_error(tmp_path: Path) -> None:
    result = CliRunner().invoke(_app(), ["simulate", str(tmp_path), "--duration", "-1"])
    assert isinstance(result.exception, ConfigError)
    assert "--duration" in str(result.exception)
    for option in ("--seed", "--noise-seed"):  # a seed sequence takes no negative number
        result = CliRunner().invoke(_app(), ["simulate", str(tmp_path), option, "-1"])
        assert isinstance(result.exception, ConfigError), result.output
        assert "must not be negative" in str(result.exception)
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path), "--scenario", "spiral"])
    assert exc.value.code == ConfigError.exit_code
    with pytest.raises(SystemExit) as exc:  # a tilt belongs to the shake
        main(["simulate", str(tmp_path), "--scenario", "walk", "--tilt-deg", "10"])
    assert exc.value.code == ConfigError.exit_code
    assert not (tmp_path / "truth.yaml").exists()


@pytest.mark.parametrize(
    ("lidar", "rate", "words"),
    [
        ("vlp16", "25", "the VLP-16 spins at 5-20 Hz"),
        ("hdl-32", "4", "the HDL-32E spins at 5-20 Hz"),
        ("os1-32", "15", "the OS1-32 runs at 10 or 20 Hz"),
        ("os1-128", "5", "the OS1-128 runs at 10 or 20 Hz"),
    ],
)
def test_a_rate_the_lidar_cannot_spin_at_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], lidar: str, rate: str, words: str
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path / "sim"), "--lidar", lidar, "--lidar-rate", rate])
    assert exc.value.code == ConfigError.exit_code
    err = capsys.readouterr().err
    assert f"--lidar-rate {float(rate)} Hz: {words}." in err and "Traceback" not in err
    assert not (tmp_path / "sim").exists()


def test_a_lever_arm_too_long_for_the_room_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The simulator keeps the rig inside its room (``ground_truth.in_free_space``); a lever arm
    no shift can fit is refused in one sentence, exit 6, and no output folder is left."""
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path / "sim"), "--translation", "0", "0", "12"])
    assert exc.value.code == ConfigError.exit_code
    err = capsys.readouterr().err
    assert "does not fit in the simulated room; use a shorter lever arm (--translation)" in err
    assert "Traceback" not in err
    assert not (tmp_path / "sim").exists()


def test_registered_in_the_licalib_app(tmp_path: Path) -> None:
    try:
        from licalib_cli import cli
    except ImportError as err:  # another command module is not there yet
        pytest.skip(f"licalib_cli.cli not importable: {err}")
    result = CliRunner().invoke(
        cli.app,
        [
            "simulate",
            str(tmp_path),
            "--duration",
            "0.2",
            "--azimuth-resolution-deg",
            "4",
            "--lidar",
            "os1-64",
            "--format",
            "ros2-mcap",
        ],
    )
    assert result.exit_code == 0, result.output
    assert result.output.strip().splitlines()[-1] == str(tmp_path / "bag")


def test_effects_by_name_and_random_time_offset(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "fx"
    argv = [
        "simulate",
        str(out_dir),
        "--duration",
        "0.2",
        "--azimuth-resolution-deg",
        "4",
        "--seed",
        "4",
        "--effect",
        "bias-random-walk",
        "--effect",
        "imu-clock-drift",
        "--random-time-offset",
        "--format",
        "ros2-mcap",
    ]
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    assert exc.value.code == 0, capsys.readouterr().err
    truth = Truth.load(out_dir / "truth.yaml")
    sim = truth.simulation
    assert sim is not None
    # the earlier names are recorded under diagnose's names, each with its size
    assert sim.imu.effects == ("gyro_bias_walk", "accel_bias_walk", "imu_clock_drift")
    assert sim.imu.bias_walk_scale == 10.0 and sim.imu.clock_drift_ppm == 50.0
    assert [e.name for e in sim.effects] == list(sim.imu.effects)
    expected = draw_time_offset(SimulationSpec(seed=4, random_time_offset=True))
    assert truth.extrinsic.time_offset_s == pytest.approx(expected, abs=1e-12)
    assert 0 < abs(expected) <= 0.05 and sim.clock.time_offset_drawn is True
    assert "--random-time-offset" in sim.command_line
    assert "--effect bias-random-walk --effect imu-clock-drift" in sim.command_line


def test_output_that_is_a_file_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "taken").write_text("x")
    result = CliRunner().invoke(_app(), ["simulate", str(tmp_path / "taken"), "--duration", "0.2"])
    assert isinstance(result.exception, ConfigError)
    assert "is a file; give a folder path" in str(result.exception)


def test_the_help_shows_three_numbers_apart_for_a_vector() -> None:
    # the typed tuple rendered as <float,float,float> led to --translation 0.3,0.15,0.05,
    # which is refused; the help shows the form the option takes
    result = CliRunner().invoke(_app(), ["simulate", "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "float,float" not in result.output
    for option, metavar in [
        ("--translation", "X Y Z"),
        ("--rpy-deg", "ROLL PITCH YAW"),
        ("--gyro-bias", "X Y Z"),
        ("--accel-bias", "X Y Z"),
    ]:
        line = next(x for x in result.output.splitlines() if option in x)
        assert metavar in line, line
    assert "--translation 0.3 -0.15 0.05" in " ".join(result.output.split())
