"""The ``licalib`` command line: thin wiring of commands to library calls.

Every known failure is a :class:`~licalib_cli.errors.LicalibError`; ``main`` prints its one-line
message and exits with its code. Tracebacks appear only with ``--debug``.

Exit codes: 0 success; 1 generic error (and an output pipe closed early, quietly); 2 bag
unreadable; 3 topic problem; 4 unusable data; 5 timestamp problem; 6 invalid configuration or
option (command-line usage errors included); 7 insufficient excitation; 8 solver failure;
9 verdict fail; 10 not converged; 11 Dask cluster unreachable (``batch``); 12 some bags of a
``batch`` failed; 130 interrupted ("Interrupted." on standard error, also when
Ctrl-C lands inside a library that turns it into another exception). ``info --json`` prints
one JSON object with ``problems`` whatever the outcome.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import re
import signal
import sys
import threading
import warnings
from types import FrameType

# The dense products of the solver are small; OpenBLAS threads only add contention on them.
# Set before numpy is imported; an explicit setting in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import typer

from licalib_cli import __version__
from licalib_cli.errors import ConfigError, LicalibError
from licalib_cli.parallel.memory import keep_freed_memory

app = typer.Typer(
    name="licalib",
    help="Targetless LiDAR-IMU calibration from ROS1/ROS2 bags, without ROS.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_state: dict[str, object] = {"debug": False, "args": ()}


def command_line() -> str:
    """The command line of this run as a shell would take it (for provenance)."""
    import shlex

    return shlex.join(["licalib", *(str(a) for a in _state["args"])])  # type: ignore[attr-defined]


USAGE_ERROR_EXIT_CODE = ConfigError.exit_code
"""Exit code of a command-line usage error: an invalid option is an invalid configuration."""


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
    from licalib_cli.commands import (
        batch,
        calibrate,
        config_cmd,
        diagnose,
        export,
        info,
        report,
        select_segments,
        simulate,
    )

    app.command("calibrate")(calibrate.calibrate_command)
    app.command("info")(info.info_command)
    app.command("simulate")(simulate.simulate_command)
    app.add_typer(config_cmd.app, name="config")
    app.command("export")(export.export_command)
    app.command("report")(report.report_command)
    app.command("diagnose")(diagnose.diagnose_command)
    app.command("batch")(batch.batch_command)
    app.command("select-segments")(select_segments.select_segments_command)


_register()


def _click_exception_types() -> tuple[tuple[type, ...], tuple[type, ...], tuple[type, ...]]:
    """``(ClickException, UsageError, Abort)`` classes of typer's bundled click and of click.

    Typer >= 0.24 raises its own copy (``typer._click``); older typer raises the standalone
    ``click`` package's classes. Both are recognised, whichever is installed.
    """
    exc: list[type] = []
    usage: list[type] = []
    abort: list[type] = [typer.Abort]
    for name in ("typer._click.exceptions", "click.exceptions"):
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        for found, attr in ((exc, "ClickException"), (usage, "UsageError"), (abort, "Abort")):
            cls = getattr(mod, attr, None)
            if isinstance(cls, type):
                found.append(cls)
    return tuple(exc), tuple(usage), tuple(abort)


def _usage_message(err: Exception) -> str:
    """Click's message of a usage error as one sentence (pydantic's prefix removed), and for
    an option of several numbers given joined by commas, the same numbers apart."""
    fmt = getattr(err, "format_message", None)
    text = str(fmt() if callable(fmt) else err).strip()
    text = text.replace("Value error, ", "").rstrip(".")
    args = _state["args"]
    return text + "." + _numbers_apart(err, list(args) if isinstance(args, tuple) else [])


def _numbers_apart(err: Exception, args: list[str]) -> str:
    """`` Give the 3 numbers apart: --translation 0.1 -0.3 0.08.`` when ``err`` is about an
    option that takes several values and ``args`` give it ``0.1,-0.3,0.08``; else ``""``."""
    param = getattr(err, "param", None)
    nargs = getattr(param, "nargs", 1)
    opts = list(getattr(param, "opts", ()))
    named = getattr(err, "option_name", None)
    if param is None and named:  # the value was the last word: "requires 3 arguments"
        found = re.search(r"requires (\d+) arguments", str(err))
        nargs, opts = (int(found.group(1)) if found else 1), [str(named)]
    if not isinstance(nargs, int) or nargs < 2:
        return ""
    for opt in opts:
        for i, arg in enumerate(args[:-1]):
            if arg == opt and "," in args[i + 1]:
                apart = " ".join(p for p in args[i + 1].split(",") if p.strip())
                return f" Give the {nargs} numbers apart, not joined by commas: {opt} {apart}."
    return ""


def _show_usage_error(err: Exception) -> None:
    """Print the usage line, the help hint and ``Error: <message>`` on standard error."""
    ctx = getattr(err, "ctx", None)
    if ctx is not None:
        typer.echo(ctx.get_usage(), err=True)
        if ctx.command.get_help_option(ctx) is not None:
            typer.echo(f"Try '{ctx.command_path} {ctx.help_option_names[0]}' for help.", err=True)
        typer.echo("", err=True)
    typer.echo(f"Error: {_usage_message(err)}", err=True)


INTERRUPTED_EXIT_CODE = 130
"""Exit code after Ctrl-C (128 + SIGINT, as shells report it)."""

_interrupt = threading.Event()


def _on_sigint(signum: int, frame: FrameType | None) -> None:
    """Python's own Ctrl-C behaviour, remembering that it happened: a library may turn the
    KeyboardInterrupt into another exception (an ImportError while it loads, click's Abort)."""
    _interrupt.set()
    raise KeyboardInterrupt


def _watch_interrupts() -> None:
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_sigint)


def _interrupted(args: list[str]) -> None:
    _info_json(args, "Interrupted.", INTERRUPTED_EXIT_CODE)
    sys.stderr.write("Interrupted.\n")
    sys.exit(INTERRUPTED_EXIT_CODE)


def _broken_pipe() -> None:
    """Standard output was closed by its reader (``licalib info BAG | head -1``): stop quietly,
    with the exit code click and rich give it, and keep Python's final flush from failing."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # stdout without a file descriptor (captured)
        pass
    sys.exit(1)


def _info_json(args: list[str], message: str, code: int) -> None:
    """For ``info --json``, the JSON object of an error that the command itself could not
    report (a usage error, an internal error, an interrupt): scripts always get one object."""
    if "info" not in args or "--json" not in args:
        return
    from licalib_cli.inspection import error_report

    rest = args[args.index("info") + 1 :]
    bag = next((a for a in rest if not a.startswith("-")), None)
    try:
        typer.echo(json.dumps(error_report(bag, message, code), indent=2))
    except BrokenPipeError:
        _broken_pipe()


_GLOBAL_FLAGS = frozenset({"--debug", "--verbose", "--quiet", "-q"})
"""The root's flags (:func:`_root`) that take no value; ``-v`` also as a cluster (``-vv``)."""


def _is_global_flag(arg: str) -> bool:
    return arg in _GLOBAL_FLAGS or (len(arg) > 1 and arg[0] == "-" and set(arg[1:]) == {"v"})


def _global_options_first(args: list[str]) -> list[str]:
    """The global flags moved before the command, where click reads them, so that
    ``licalib calibrate BAG -v`` means ``licalib -v calibrate BAG`` instead of failing on an
    unknown option (no command has an option of these names). Arguments after ``--`` stay
    where they are; the order of everything else is kept."""
    end = args.index("--") if "--" in args else len(args)
    flags = [a for a in args[:end] if _is_global_flag(a)]
    rest = [a for a in args[:end] if not _is_global_flag(a)]
    return flags + rest + args[end:]


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point.

    Exits with 0 on success (and after printing help when called without arguments), with
    the code of the :class:`LicalibError` raised, with :data:`USAGE_ERROR_EXIT_CODE` for a
    command-line usage error (unknown option, missing argument, invalid value), 130 on
    Ctrl-C and 1, quietly, when standard output is closed early. Numeric RuntimeWarnings are
    not shown unless ``--debug``.
    """
    args = _global_options_first(list(argv) if argv is not None else sys.argv[1:])
    _state["args"] = tuple(args)
    debug = "--debug" in args
    keep_freed_memory()
    _interrupt.clear()
    _watch_interrupts()
    if not debug:
        warnings.filterwarnings("ignore", category=RuntimeWarning)
    try:
        # Without standalone mode click returns (not raises) the code of a typer.Exit.
        code = app(args=args, prog_name="licalib", standalone_mode=False)
        if code == INTERRUPTED_EXIT_CODE:  # typer turns Ctrl-C into a quiet Exit(130)
            _interrupted(args)
        if isinstance(code, int) and code != 0:
            sys.exit(code)
    except KeyboardInterrupt:
        _interrupted(args)
    except BrokenPipeError:
        _broken_pipe()
    except LicalibError as err:
        if debug:
            raise
        typer.secho(f"Error: {err}", err=True, fg=typer.colors.RED)
        sys.exit(err.exit_code)
    except typer.Exit as err:
        sys.exit(err.exit_code)
    except Exception as err:  # click usage errors and the unexpected
        if _interrupt.is_set() or isinstance(err.__context__, KeyboardInterrupt):
            _interrupted(args)
        click_exc, usage_exc, abort_exc = _click_exception_types()
        if type(err).__name__ == "NoArgsIsHelpError":
            # The help text was rendered when the error was built (rich help prints it);
            # plain help comes back as the message.
            text = getattr(err, "format_message", lambda: "")()
            if text.strip():
                typer.echo(text)
            sys.exit(0)
        if isinstance(err, usage_exc) or (
            isinstance(err, click_exc) and getattr(err, "ctx", None) is not None
        ):
            _info_json(args, _usage_message(err), USAGE_ERROR_EXIT_CODE)
            _show_usage_error(err)
            sys.exit(USAGE_ERROR_EXIT_CODE)
        duck = callable(getattr(err, "show", None)) and isinstance(
            getattr(err, "exit_code", None), int
        )
        if isinstance(err, click_exc) or duck:
            err.show()  # type: ignore[attr-defined]
            sys.exit(err.exit_code)  # type: ignore[attr-defined]
        if isinstance(err, abort_exc):
            typer.echo("Aborted.", err=True)
            sys.exit(1)
        if debug:
            raise
        text = (
            f"Internal error: {type(err).__name__}: {err}. Rerun with --debug for the "
            "traceback and report it."
        )
        _info_json(args, text, 1)
        typer.secho(text, err=True, fg=typer.colors.RED)
        sys.exit(1)
