"""Test factories: a stand-in for a finished calibration run, as the stages that name what they
did in its result and its findings (after the last one that assembles the result) see it."""

from __future__ import annotations

from dataclasses import dataclass

from licalib_cli.pipeline.checks import Finding
from licalib_cli.sections import ModelInfo


@dataclass(frozen=True)
class FinishedResult:
    model: ModelInfo


@dataclass(frozen=True)
class FinishedChecks:
    findings: tuple[Finding, ...]


@dataclass(frozen=True)
class FinishedRun:
    """A run's result (its model section) and its checks' findings."""

    result: FinishedResult
    checks: FinishedChecks


def finished_run(model: ModelInfo, *findings: Finding) -> FinishedRun:
    """A finished run whose result has ``model`` and whose checks found ``findings``."""
    return FinishedRun(FinishedResult(model), FinishedChecks(tuple(findings)))
