"""The calibration report: one self-contained HTML page per result.

``calibrate`` keeps the arrays the figures need next to the result
(:mod:`licalib_cli.report.data`, ``<stem>.report-data.npz``); :func:`write_report` draws the page
(:mod:`licalib_cli.report.html`, figures in :mod:`licalib_cli.report.figures`) from the result
and, when present, those arrays.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from licalib_cli.report.data import (
    ReportData,
    build_report_data,
    report_data_path,
    window_report_data_path,
)
from licalib_cli.results import CalibrationResult, write_text_atomic

__all__ = [
    "ReportData",
    "build_report_data",
    "load_report_data",
    "load_window_report_data",
    "report_data_path",
    "window_report_data_path",
    "window_report_data_paths",
    "write_report",
]

logger = logging.getLogger(__name__)


def load_report_data(result_path: Path, result: CalibrationResult) -> ReportData | None:
    """The report data beside ``result_path``, or None when there is none or it belongs to
    another run (a warning says so).

    Raises:
        ConfigError: the sidecar exists but is not report data of this version.
    """
    return _load_tied(report_data_path(result_path), result_path, result)


def load_window_report_data(
    result_path: Path, result: CalibrationResult
) -> tuple[ReportData | None, ...]:
    """For a result of ``calibrate --segments``, each window's report data beside it
    (:func:`~licalib_cli.report.data.window_report_data_path`; None for a window without,
    a warning says so); empty for a result of one segment.

    Raises:
        ConfigError: a sidecar exists but is not report data of this version.
    """
    return tuple(
        _load_tied(path, result_path, result)
        for path in window_report_data_paths(result_path, result)
    )


def window_report_data_paths(result_path: Path, result: CalibrationResult) -> tuple[Path, ...]:
    """The report data of each window beside a result of ``calibrate --segments``, in the
    order of its segments (:func:`~licalib_cli.report.data.window_report_data_path`); empty for
    a result of one segment."""
    if result.segments is None:
        return ()
    count = len(result.segments.segments)
    return tuple(window_report_data_path(result_path, k) for k in range(1, count + 1))


def _load_tied(path: Path, result_path: Path, result: CalibrationResult) -> ReportData | None:
    """The report data in ``path`` when it belongs to ``result`` (same creation time)."""
    if not path.is_file():
        logger.warning(
            "%s has no report data (%s), so the report shows what the result file holds; "
            "calibrate with this licalib to get every figure.",
            result_path,
            path.name,
        )
        return None
    data = ReportData.load(path)
    created = result.provenance.created_utc if result.provenance else ""
    if data.result_created_utc and created and data.result_created_utc != created:
        logger.warning(
            "%s belongs to another run (created %s, the result %s); it is not used.",
            path,
            data.result_created_utc,
            created,
        )
        return None
    return data


def write_report(
    path: Path,
    result: CalibrationResult,
    data: ReportData | None,
    source: str,
    windows: Sequence[ReportData | None] = (),
) -> None:
    """Draw the report of ``result`` and write it to ``path`` atomically; ``windows``: a joint
    result's windows' report data (:func:`load_window_report_data`).

    Raises:
        ConfigError: matplotlib is not installed.
    """
    from licalib_cli.report.html import render_html

    write_text_atomic(Path(path), render_html(result, data, source, windows))
