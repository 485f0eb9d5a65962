"""Command-line usage errors: click's usage message, exit code 6, no traceback; help exits 0."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest

from licalib_cli import cli
from licalib_cli.cli import main
from licalib_cli.errors import BagError, ConfigError, LicalibError

LICALIB = Path(sys.executable).parent / "licalib"


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(exc.value.code or 0), out.out, out.err


def _check_usage_error(code: int, out: str, err: str, usage: str, message: str) -> None:
    assert code == ConfigError.exit_code == 6, err
    assert "Internal error" not in out + err and "Traceback" not in out + err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines[0].startswith(f"Usage: {usage}"), err
    assert lines[-1].startswith("Error: ") and lines[-1].endswith("."), err
    assert message in lines[-1], err
    assert "Value error," not in err


@pytest.mark.parametrize(
    ("argv", "usage", "message"),
    [
        (["info", "--bogus", "x"], "licalib info", "No such option: --bogus"),
        (["info"], "licalib info", "Missing argument 'BAG'"),
        (
            ["simulate", "OUT", "--scenario", "spiral"],
            "licalib simulate",
            "Invalid value for '--scenario': 'spiral' is not one of 'sinusoid'",
        ),
        (["info", "x.bag", "--start", "abc"], "licalib info", "Invalid value for '--start'"),
        (["simulate", "OUT", "--effect", "rain"], "licalib simulate", "'rain' is not one of"),
        (
            ["select-segments", "x.bag", "--intrinsics", "some"],
            "licalib select-segments",
            "'some' is not one of 'none', 'imu', 'lidar', 'all'",
        ),
        (
            ["calibrate", "x.bag", "--model", "bogus"],
            "licalib calibrate",
            "'bogus' is not one of 'evident', 'config', 'auto'",
        ),
        (["frobnicate"], "licalib [OPTIONS] COMMAND", "No such command 'frobnicate'"),
        (
            ["simulate", "OUT", "--translation", "0.12,-0.31,0.08", "--duration", "1"],
            "licalib simulate",
            "Give the 3 numbers apart, not joined by commas: --translation 0.12 -0.31 0.08.",
        ),
        (
            ["simulate", "OUT", "--rpy-deg", "3,178,91", "--duration", "1"],
            "licalib simulate",
            "Give the 3 numbers apart, not joined by commas: --rpy-deg 3 178 91.",
        ),
    ],
    ids=[
        "unknown-option",
        "missing-bag",
        "bad-choice",
        "bad-number",
        "bad-effect",
        "bad-intrinsics",
        "bad-model",
        "bad-command",
        "vector-with-commas",
        "angles-with-commas",
    ],
)
def test_usage_error_exit_code_6(
    argv: list[str], usage: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = _run(argv, capsys)
    _check_usage_error(code, out, err, usage, message)


def test_no_arguments_prints_help_and_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run([], capsys)
    assert code == 0, err
    assert "Usage: licalib" in out and "simulate" in out and "info" in out
    assert "Error" not in out + err


def test_standalone_click_usage_error_is_recognised(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Older typer raises the standalone click package's exceptions: same handling."""
    click = pytest.importorskip("click")

    def fake_app(**_: object) -> None:
        raise click.exceptions.UsageError("Got unexpected extra argument (y)")

    monkeypatch.setattr(cli, "app", fake_app)
    code, _out, err = _run(["info", "x", "y"], capsys)
    assert code == 6 and "Internal error" not in err
    assert err.strip().splitlines()[-1] == "Error: Got unexpected extra argument (y)."


def test_installed_command(tmp_path: Path) -> None:
    """The console script itself: help without arguments, exit 6 on a bad option."""
    if not LICALIB.exists():
        pytest.skip("the licalib console script is not installed next to this Python")
    res = subprocess.run([str(LICALIB)], capture_output=True, text=True, timeout=60, check=False)
    assert res.returncode == 0, res.stderr
    assert "Usage: licalib" in res.stdout and "Traceback" not in res.stderr
    res = subprocess.run(
        [str(LICALIB), "info", str(tmp_path), "--bogus", "x"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert res.returncode == 6, res.stderr
    assert res.stderr.strip().splitlines()[-1] == "Error: No such option: --bogus."


def test_global_options_are_read_after_the_command_too() -> None:
    """``-v``, ``-q`` and ``--debug`` may follow the command; nothing after ``--`` moves."""
    argv = ["calibrate", "b.bag", "-vv", "-o", "out.yaml", "--debug", "--", "-q"]
    assert cli._global_options_first(argv) == [
        "-vv",
        "--debug",
        "calibrate",
        "b.bag",
        "-o",
        "out.yaml",
        "--",
        "-q",
    ]
    assert cli._global_options_first(["-v", "info", "b.bag"]) == ["-v", "info", "b.bag"]
    assert cli._global_options_first(["simulate", "OUT", "--rpy-deg", "-5", "0", "90"]) == [
        "simulate",
        "OUT",
        "--rpy-deg",
        "-5",
        "0",
        "90",
    ]


def test_debug_after_the_command_shows_the_traceback(tmp_path: Path) -> None:
    """``licalib info BAG --debug`` re-raises the error as ``licalib --debug info BAG`` does,
    instead of refusing ``--debug`` as an unknown option of ``info``."""
    missing = str(tmp_path / "missing.bag")
    with pytest.raises(LicalibError):
        main(["info", missing, "--debug"])
    with pytest.raises(SystemExit) as exc:
        main(["info", missing])
    assert exc.value.code == BagError.exit_code


def test_verbosity_after_the_command(capsys: pytest.CaptureFixture[str]) -> None:
    logger = logging.getLogger("licalib_cli")
    before = logger.level
    try:
        code, _out, err = _run(["config", "dump", "-vv"], capsys)
        assert code == 0, err
        assert logger.level == logging.DEBUG
        code, _out, err = _run(["config", "dump", "-q"], capsys)
        assert code == 0, err
        assert logger.level == logging.WARNING
    finally:
        logger.setLevel(before)


def test_numbers_joined_by_commas_as_the_last_word_get_the_same_hint(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # click then says only that the option wants 3 values, without a usage line
    code, out, err = _run(["simulate", "OUT", "--rpy-deg", "-3,178,91"], capsys)
    assert code == ConfigError.exit_code and out == "", err
    assert err.strip() == (
        "Error: Option '--rpy-deg' requires 3 arguments. Give the 3 numbers apart, not joined "
        "by commas: --rpy-deg -3 178 91."
    )


def test_a_single_number_option_gets_no_hint_about_commas(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, err = _run(["info", "x.bag", "--start", "1,5"], capsys)
    _check_usage_error(code, out, err, "licalib info", "Invalid value for '--start'")
    assert "apart" not in err
