"""Console output shared by the commands (rich): consoles, and how a calibration is shown."""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Sequence
from functools import cache
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from licalib_cli.results import CalibrationResult, estimate_rows
from licalib_cli.sections import Consistency, VerdictSection
from licalib_cli.truth import Truth

if TYPE_CHECKING:
    from licalib_cli.pipeline import CalibrationRun


@cache
def console() -> Console:
    """Standard-output console."""
    return Console(highlight=False)


@cache
def console_err() -> Console:
    """Standard-error console (logs, progress)."""
    return Console(stderr=True, highlight=False)


def _fmt(v: float, unit: str, scale: float = 1.0, digits: int = 4) -> str:
    if not np.isfinite(v):
        return "unobservable"
    return f"{v * scale:.{digits}f} {unit}"


def render_estimate(result: CalibrationResult, truth: Truth | None) -> Table:
    """The extrinsic and time offset with their 1-sigma (and the truth and error if given)."""
    true_ext = truth.extrinsic_for(result) if truth is not None else None
    table = Table(
        title="T_imu_lidar (p_imu = R p_lidar + t) and time offset (t_imu = t_lidar + dt)",
        caption="rotation 1-sigma" + (" and error" if truth else "") + " about LiDAR x, y, z",
    )
    for name in ("parameter", "estimate", "1-sigma") + (("truth", "error") if truth else ()):
        table.add_column(name, justify="left" if name == "parameter" else "right")
    drift = 1e-6 * truth.simulation.imu.clock_drift_ppm if truth and truth.simulation else None
    for row in estimate_rows(result, true_ext, true_clock_drift=drift):
        table.add_row(*row)
    return table


def render_checks(consistency: Consistency) -> Table:
    """One row per fit check: what was compared, the figure, the outcome."""
    table = Table(title="Checks of the fit")
    table.add_column("check")
    table.add_column("figure")
    table.add_column("outcome")
    for check, figure, outcome, warn in consistency.rows():
        table.add_row(check, figure, f"[yellow]{outcome}[/]" if warn else outcome)
    return table


_MAX_INTRINSIC_DIRECTIONS = 3
"""Intrinsic-only unobservable directions printed one by one; more are summarised."""

_BEAM_COORDINATE = re.compile(r"lidar\.intrinsics\[\d+\]\.(\w+)")
_BEAM_KIND = {
    "dphi": "elevation",
    "dtheta": "azimuth",
    "V": "vertical offset",
    "H": "horizontal offset",
    "s": "range scale",
    "drho": "range offset",
}


def unobservable_lines(texts: tuple[str, ...] | list[str]) -> list[str]:
    """The unobservable directions as printed: every one that involves the extrinsic or the
    time offset, and the intrinsic-only ones one by one up to
    :data:`_MAX_INTRINSIC_DIRECTIONS`; beyond that one line counts them by the beam
    coordinate that leads each (the result file lists them all)."""
    about_extrinsic = [t for t in texts if "ext." in t.split(":", 1)[0]]
    intrinsic = [t for t in texts if "ext." not in t.split(":", 1)[0]]
    if len(intrinsic) <= _MAX_INTRINSIC_DIRECTIONS:
        return about_extrinsic + intrinsic
    kinds: Counter[str] = Counter()
    for t in intrinsic:
        lead = _BEAM_COORDINATE.search(t.split(":", 1)[0])
        kinds[_BEAM_KIND.get(lead.group(1), lead.group(1)) if lead else "IMU intrinsics"] += 1
    led = ", ".join(f"{n} by {k}" for k, n in kinds.most_common())
    return [
        *about_extrinsic,
        f"{len(intrinsic)} directions of the intrinsics alone ({led}) stay at their initial "
        "values; the result file lists each (observability.unobservable).",
    ]


VERDICT_COLOURS = {"pass": "green", "warn": "yellow", "fail": "red"}
"""The console colour of each verdict."""


def reason_lines(reasons: Sequence[str]) -> list[str]:
    """A verdict's reasons as console lines (plain text: a bracketed word in them, such as
    ``model.lidar: [range_scale]``, is not markup)."""
    return [f"  - {escape(reason)}" for reason in reasons]


def verdict_lines(verdict: VerdictSection, assumed: Sequence[str] = ()) -> list[str]:
    """The verdict and its reasons as console lines; ``assumed``: the effects the result takes
    as exact though the recording cannot check them (the checks' ``taken as exact`` row), named
    beside a verdict that is not a failure."""
    colour = VERDICT_COLOURS[verdict.status]
    head = f"Verdict: [bold {colour}]{verdict.status.upper()}[/]"
    if assumed and verdict.status != "fail":
        names = ", ".join(assumed)
        head += f" (assumes {escape(names)} exact: see the checks' row 'taken as exact')"
    return [head, *reason_lines(verdict.reasons)]


def render_run(run: CalibrationRun, truth: Truth | None) -> None:
    """Print the estimate table, the checks, the observability findings, the verdict and the
    stage timings."""
    r = run.result
    out = console()
    out.print(render_estimate(r, truth))
    shift = r.recording.lidar_clock_shift_s if r.recording else 0.0
    if shift:
        out.print(
            f"The LiDAR clock was {-shift:+.9f} s off the IMU clock and was shifted before "
            f"calibrating: t_imu = t_lidar + ({shift:+.9f} s) + time offset"
            + ("; the truth is shown on the same footing." if truth is not None else ".")
        )
    if truth is not None:
        err = r.extrinsic.error_to(truth.extrinsic_for(r))
        out.print(
            f"Error against truth: translation {1e3 * err['translation_m']:.2f} mm, rotation "
            f"{err['rotation_deg']:.4f} deg, time offset {1e3 * err['time_offset_s']:.3f} ms"
        )
    if r.factory_extrinsic is not None:
        f = r.factory_extrinsic
        out.print(
            f"Against the factory extrinsic ({escape(f.source)}, clouds in {f.cloud_frame}): "
            f"translation differs by {1e3 * f.difference_translation_norm_m:.1f} mm, rotation "
            f"by {f.difference_rotation_deg:.3f} deg."
        )
    if r.consistency is not None:
        out.print(render_checks(r.consistency))
        for why in r.consistency.inflation:
            out.print(f"Sigmas enlarged {escape(why)}.")
    if r.observability is not None:
        for text in unobservable_lines(r.observability.unobservable):
            out.print(f"[yellow]Not observable:[/] {escape(text)}")
        for text in r.observability.weakly_determined:
            out.print(f"[yellow]Weakly determined:[/] {escape(text)}")
    for finding in run.checks.findings:
        if finding.severity == "note":
            out.print(f"Note: {escape(finding.text)}")
    assumed = r.consistency.assumed_exact if r.consistency is not None else ()
    for line in verdict_lines(run.checks.verdict, assumed):
        out.print(line)
    total = sum(run.timings.values())
    out.print(
        "Stages: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in run.timings.items())
        + f" (total {total:.1f} s)"
    )
