"""The work of one Dask task: calibrate one bag, as ``licalib calibrate`` does.

The task runs in a worker process; it reads the bag itself (workers must see the bag's path)
and hands the result back to the client, which writes it. A bag that licalib refuses (a
:class:`~licalib_cli.errors.LicalibError`: unreadable, unusable, not excited, ...) is an
outcome, not an exception: trying it again would give the same sentence. Anything else that
goes wrong (an internal error, the worker dying) is left to the client's retries.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from licalib_cli.config import CalibConfig
from licalib_cli.errors import LicalibError
from licalib_cli.results import CalibrationResult

__all__ = ["TaskInput", "TaskOutcome", "calibrate_task"]


@dataclass(frozen=True)
class TaskInput:
    """What a task needs.

    Attributes:
        label: ``rig/stem``, for messages.
        bag: the bag, absolute (as the workers see it).
        cfg: the resolved configuration.
        attempt: 1 for the first try, 2 for the first retry, ...
        segments: ``"auto"`` or ``"START-END,..."``: calibrate over several segments in one
            problem (``calibrate --segments``); None: one segment (``calibrate``).
    """

    label: str
    bag: Path
    cfg: CalibConfig
    attempt: int = 1
    segments: str | None = None


@dataclass(frozen=True)
class TaskOutcome:
    """What a task hands back.

    Attributes:
        result: the calibration (None when the bag was refused).
        exit_status: ``ok``, ``fail`` or ``not converged`` as for ``calibrate``; ``error``
            when the bag was refused.
        error: the refusal's sentence.
        exit_code: the exit code ``calibrate`` would give the refusal (0 otherwise).
        seconds: wall time of the calibration.
        warnings: what the calibration warned about (log messages of level WARNING and up).
    """

    result: CalibrationResult | None
    exit_status: str
    seconds: float
    error: str = ""
    exit_code: int = 0
    warnings: tuple[str, ...] = ()


class _Collect(logging.Handler):
    """Keeps the licalib log records of one thread (a worker may run several tasks)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.thread = threading.get_ident()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.messages.append(record.getMessage())


def calibrate_task(task: TaskInput) -> TaskOutcome:
    """Calibrate one bag (``licalib_cli.pipeline.calibrate``, or
    ``licalib_cli.pipeline.joint.calibrate_segments`` with ``task.segments``) and return the
    outcome.

    Warnings are collected into the outcome instead of the worker's standard error.
    """
    log = logging.getLogger("licalib_cli")
    collect = _Collect()
    log.addHandler(collect)
    propagate = log.propagate
    log.propagate = False
    start = time.perf_counter()
    try:
        result, exit_status, warnings = _calibrate(task)
    except LicalibError as err:
        return TaskOutcome(
            result=None,
            exit_status="error",
            seconds=time.perf_counter() - start,
            error=str(err),
            exit_code=err.exit_code,
            warnings=tuple(collect.messages),
        )
    finally:
        log.removeHandler(collect)
        log.propagate = propagate
    return TaskOutcome(
        result=result,
        exit_status=exit_status,
        seconds=time.perf_counter() - start,
        warnings=tuple(dict.fromkeys((*warnings, *collect.messages))),
    )


def _calibrate(task: TaskInput) -> tuple[CalibrationResult, str, tuple[str, ...]]:
    """The result, the exit status and the warnings of one bag's calibration."""
    if task.segments is None:
        from licalib_cli.pipeline import calibrate

        run = calibrate(task.bag, task.cfg)
        return run.result, run.checks.exit_status, tuple(run.warnings)
    from licalib_cli.pipeline.joint import calibrate_segments

    joint = calibrate_segments(task.bag, task.cfg, task.segments)
    verdict = joint.result.verdict
    # as calibrate --segments: the joint verdict decides (each segment's own is a reason)
    exit_status = "fail" if verdict is not None and verdict.status == "fail" else "ok"
    warnings = tuple(w for run in joint.runs for w in run.warnings)
    return joint.result, exit_status, warnings
