"""The ``licalib`` command line: thin wiring of commands to library calls.

Every known failure is a :class:`~licalib_cli.errors.LicalibError`; ``main`` prints its one-line
message and exits with its code. Tracebacks appear only with ``--debug``.

Exit codes: 0 success; 1 generic error; 2 bag unreadable; 3 topic problem; 4 unusable data;
5 timestamp problem; 6 configuration; 7 insufficient excitation; 8 solver failure;
130 interrupted.
"""

from __future__ import annotations

import logging
import os
import sys

# The dense products of the solver are small; OpenBLAS threads only add contention on them.
# Set before numpy is imported; an explicit setting in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import typer

from licalib_cli import __version__
from licalib_cli.errors import LicalibError

app = typer.Typer(
    name="licalib",
    help="Targetless LiDAR-IMU calibration from ROS1/ROS2 bags, without ROS.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_state = {"debug": False}


def _version(value: bool) -> None:
    if value:
        typer.echo(f"licalib {__version__}")
        raise typer.Exit


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks and debug logs."),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log output."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only warnings and errors."),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version."
    ),
) -> None:
    """Targetless LiDAR-IMU calibration from ROS1/ROS2 bags, without ROS."""
    _state["debug"] = debug
    level = logging.DEBUG if (debug or verbose > 1) else logging.INFO
    if quiet:
        level = logging.WARNING
    from rich.logging import RichHandler

    from licalib_cli.commands.render import console_err

    handler = RichHandler(console=console_err(), show_path=False, show_time=False)
    logging.basicConfig(level=logging.WARNING, handlers=[handler], format="%(message)s", force=True)
    explicit = verbose or debug or quiet
    logging.getLogger("licalib_cli").setLevel(level if explicit else logging.INFO)


def _register() -> None:
    from licalib_cli.commands import calibrate, config_cmd, info, simulate

    app.command("calibrate")(calibrate.calibrate_command)
    app.command("info")(info.info_command)
    app.command("simulate")(simulate.simulate_command)
    app.add_typer(config_cmd.app, name="config")


_register()


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point."""
    debug = "--debug" in (argv if argv is not None else sys.argv)
    try:
        app(args=argv, standalone_mode=False)
    except KeyboardInterrupt:
        typer.echo("Interrupted.", err=True)
        sys.exit(130)
    except LicalibError as err:
        if debug:
            raise
        typer.secho(f"Error: {err}", err=True, fg=typer.colors.RED)
        sys.exit(err.exit_code)
    except typer.Exit as err:
        sys.exit(err.exit_code)
    except Exception as err:  # click usage errors and the unexpected
        import click

        if isinstance(err, click.exceptions.ClickException):
            err.show()
            sys.exit(err.exit_code)
        if isinstance(err, click.exceptions.Abort):
            sys.exit(1)
        if debug:
            raise
        typer.secho(
            f"Internal error: {type(err).__name__}: {err}. Rerun with --debug for the traceback "
            "and report it.",
            err=True,
            fg=typer.colors.RED,
        )
        sys.exit(1)
