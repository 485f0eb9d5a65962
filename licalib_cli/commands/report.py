"""``licalib report``: a result file (and its report data) as one self-contained HTML page."""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from licalib_cli.errors import ConfigError
from licalib_cli.results import check_not_an_input, prepare_output

logger = logging.getLogger(__name__)


def report_inputs(result_path: Path) -> list[tuple[str, Path | None]]:
    """The files a report of ``result_path`` must never overwrite."""
    from licalib_cli.report import report_data_path

    return [
        ("the result file", result_path),
        ("the result's resolved config", result_path.with_name(result_path.stem + ".config.yaml")),
        ("the result's report data", report_data_path(result_path)),
    ]


def report_command(
    result_path: Path = typer.Argument(
        ..., metavar="RESULT", help="A result file written by `licalib calibrate`."
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        "-o",
        help="The HTML file to write (default: the result's name with .html).",
    ),
) -> None:
    """Write the calibration report of a result: one HTML page, plots embedded."""
    from licalib_cli.export import load_result
    from licalib_cli.plots import pyplot
    from licalib_cli.report import load_report_data, write_report

    out = out if out is not None else result_path.with_suffix(".html")
    inputs = report_inputs(result_path)
    result = load_result(result_path, purpose="report")
    if result.verdict is None:
        msg = (
            f"{result_path} is not a calibration result (it has no verdict; a simulator's "
            "truth.yaml?); give the file `licalib calibrate -o` wrote."
        )
        raise ConfigError(msg)
    check_not_an_input(out, inputs)
    if result.recording is not None:
        check_not_an_input(out, [("the calibrated bag", Path(result.recording.bag))])
    prepare_output(out, example="report.html")
    pyplot()
    data = load_report_data(result_path, result)
    write_report(out, result, data, str(result_path))
    status = result.verdict.status.upper() if result.verdict else "without a verdict"
    logger.info("Wrote the report %s (verdict %s).", out, status)
