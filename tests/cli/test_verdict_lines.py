"""The verdict's reasons reach the console as written."""

from __future__ import annotations

from rich.console import Console

from licalib_cli.commands.render import verdict_lines
from licalib_cli.sections import VerdictSection


def test_a_bracketed_word_in_a_reason_is_printed_not_taken_for_markup() -> None:
    """The paper's case under --model auto: the reason named ``model.lidar: [range_scale]``,
    and the console printed ``model.lidar:  in the config`` (the word read as a style tag)."""
    reason = (
        "Translation is uncertain. It comes from the effects the model holds fixed "
        "(lidar_range_scale); estimate them (model.lidar: [range_scale] in the config)."
    )
    out = Console(width=200, record=True, color_system=None)
    for line in verdict_lines(VerdictSection("warn", (reason,))):
        out.print(line)
    text = out.export_text()
    assert text.splitlines()[0] == "Verdict: WARN"
    assert "(model.lidar: [range_scale] in the config)" in text


def test_a_verdict_names_what_it_assumes_exact_unless_it_fails() -> None:
    """An effect taken as exact that could hide three sigmas (``consistency.unchecked_priors``
    with prior 0) is named beside the verdict: a PASS that rests on it says so where the user
    reads the verdict; a FAIL needs no such qualification."""
    out = Console(width=200, record=True, color_system=None)
    for line in verdict_lines(VerdictSection("pass", ()), ["lidar_point_time", "g_sensitivity"]):
        out.print(line)
    assert out.export_text().splitlines()[0] == (
        "Verdict: PASS (assumes lidar_point_time, g_sensitivity exact: see the checks' row "
        "'taken as exact')"
    )
    out = Console(width=200, record=True, color_system=None)
    for line in verdict_lines(VerdictSection("fail", ("It failed.",)), ["lidar_point_time"]):
        out.print(line)
    assert out.export_text().splitlines()[0] == "Verdict: FAIL"
