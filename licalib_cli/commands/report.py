"""``licalib report``: a result file (and its report data) as one self-contained HTML page."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import typer

from licalib_cli.errors import ConfigError
from licalib_cli.report.data import ReportData
from licalib_cli.results import CalibrationResult, check_not_an_input, prepare_output
from licalib_cli.truth import Truth

logger = logging.getLogger(__name__)


def report_inputs(result_path: Path) -> list[tuple[str, Path | None]]:
    """The files a report of ``result_path`` must never overwrite."""
    from licalib_cli.report import report_data_path

    return [
        ("the result file", result_path),
        ("the result's resolved config", result_path.with_name(result_path.stem + ".config.yaml")),
        ("the result's report data", report_data_path(result_path)),
    ]


def with_truth(data: ReportData | None, result: CalibrationResult, truth: Truth) -> ReportData:
    """``data`` (or empty report data) with ``truth`` on the result's clock."""
    ext = truth.extrinsic_for(result)
    created = result.provenance.created_utc if result.provenance else ""
    base = data if data is not None else ReportData(result_created_utc=created)
    return replace(base, truth_matrix=ext.matrix(), truth_time_offset=np.array([ext.time_offset_s]))


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
    truth: Path | None = typer.Option(
        None,
        "--truth",
        help="A truth.yaml (or another result) to show beside the estimate, instead of the "
        "one calibrate --truth kept.",
    ),
) -> None:
    """Write the calibration report of a result: one HTML page, plots embedded."""
    from licalib_cli.export import load_result
    from licalib_cli.plots import pyplot
    from licalib_cli.report import (
        load_report_data,
        load_window_report_data,
        window_report_data_paths,
        write_report,
    )

    out = out if out is not None else result_path.with_suffix(".html")
    inputs = [*report_inputs(result_path), ("the truth file", truth)]
    result = load_result(result_path, purpose="report")
    if result.verdict is None:
        msg = (
            f"{result_path} is not a calibration result (it has no verdict; a simulator's "
            "truth.yaml?); give the file `licalib calibrate -o` wrote."
        )
        raise ConfigError(msg)
    inputs += [
        (f"the report data of seg{k}", path)
        for k, path in enumerate(window_report_data_paths(result_path, result), start=1)
    ]
    check_not_an_input(out, inputs)
    if result.recording is not None:
        check_not_an_input(out, [("the calibrated bag", Path(result.recording.bag))])
    prepare_output(out, example="report.html")
    pyplot()
    data = load_report_data(result_path, result)
    windows = load_window_report_data(result_path, result)
    if truth is not None:
        reference = Truth.load(truth)
        data = with_truth(data, result, reference)
        # the windows are of the same bag: the joint result's clock split is theirs
        windows = tuple(None if w is None else with_truth(w, result, reference) for w in windows)
    write_report(out, result, data, str(result_path), windows)
    status = result.verdict.status.upper() if result.verdict else "without a verdict"
    logger.info("Wrote the report %s (verdict %s).", out, status)
