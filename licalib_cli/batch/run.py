"""Run a batch: one Dask task per bag, results written as they finish, retries, summary.

The client (this process) plans (:mod:`~licalib_cli.batch.plan`), submits one task per bag that
has no up-to-date result, and writes each result atomically as soon as its task finishes, so
an interrupted batch (Ctrl-C, a crash of the client) keeps every finished result and a rerun
continues where it stopped. A task that raises, or whose worker dies, is submitted again up to
``retries`` times; a bag licalib refuses fails at once (see :mod:`~licalib_cli.batch.task`).
"""

from __future__ import annotations

import logging
import time
import uuid
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from licalib_cli.batch.cluster import connect
from licalib_cli.batch.inputs import BatchJob
from licalib_cli.batch.plan import PlannedBag, plan
from licalib_cli.batch.summary import (
    BagRow,
    RigRow,
    bag_row,
    earlier_seconds,
    rig_rows,
    write_summaries,
)
from licalib_cli.batch.task import TaskInput, TaskOutcome, calibrate_task
from licalib_cli.config import dump_config
from licalib_cli.errors import ConfigError
from licalib_cli.progress import NullProgress, Progress
from licalib_cli.results import CalibrationResult, create_folder, write_text_atomic

if TYPE_CHECKING:
    from distributed import Client, Future

__all__ = ["BatchReport", "run_batch"]

logger = logging.getLogger(__name__)

Task = Callable[[TaskInput], TaskOutcome]

_POLL_S = 0.02
"""How often the client looks for finished tasks, s."""
_REFRESH_S = 0.5
"""How often the running count of the progress display is refreshed, s."""


@dataclass(frozen=True)
class BatchReport:
    """What a batch did.

    Attributes:
        out_dir: the output folder.
        bags: one row per bag, in the order given (``summary.csv``).
        rigs: one row per rig (``rigs.csv``).
        workers: worker threads of the cluster (0 when no bag needed one).
        wall_s: wall seconds of the whole batch.
    """

    out_dir: Path
    bags: tuple[BagRow, ...]
    rigs: tuple[RigRow, ...]
    workers: int
    wall_s: float

    def count(self, status: str) -> int:
        """Bags with this ``status``."""
        return sum(1 for b in self.bags if b.status == status)

    @property
    def verdict_fail(self) -> int:
        """Results whose verdict is ``fail`` (written for inspection)."""
        return sum(1 for b in self.bags if b.verdict == "fail")

    @property
    def complete(self) -> bool:
        """Every bag has a result whose verdict is not ``fail``."""
        return all(b.status in ("calibrated", "up to date") and b.usable for b in self.bags)


class _Tracker:
    """Outcome per planned bag, and the rows of the summary."""

    def __init__(self, planned: Sequence[PlannedBag], out_dir: Path) -> None:
        self.planned = list(planned)
        self.out_dir = out_dir
        self.rows: list[BagRow | None] = [None] * len(planned)
        self.attempts = [0] * len(planned)
        seconds = earlier_seconds(out_dir)
        for i, p in enumerate(planned):
            if p.existing is not None:
                rel = self._rel(p)
                self.rows[i] = self._row(i, "up to date", p.existing, seconds.get(rel))

    def _rel(self, p: PlannedBag) -> str:
        return str(p.result_path.relative_to(self.out_dir))

    def _row(self, i: int, status: str, result: Any, seconds: float | None, **kw: Any) -> BagRow:
        p = self.planned[i]
        return bag_row(
            p.job.rig,
            p.job.stem,
            status,
            result,
            calibration_s=float("nan") if seconds is None else round(seconds, 2),
            attempts=self.attempts[i],
            result=self._rel(p) if result is not None else "",
            path=str(p.job.bag),
            **kw,
        )

    def finished(self, i: int, outcome: TaskOutcome) -> None:
        p = self.planned[i]
        if outcome.result is None:
            self.rows[i] = self._row(
                i,
                "failed",
                None,
                outcome.seconds,
                error=outcome.error,
                exit_code=outcome.exit_code,
            )
            return
        result = _with_fingerprint(outcome.result, p.config_fingerprint)
        # The resolved config first: the result is what marks the bag as done.
        write_text_atomic(p.config_path, dump_config(p.cfg))
        result.save(p.result_path)
        self.rows[i] = self._row(i, "calibrated", result, outcome.seconds)

    def failed(self, i: int, sentence: str) -> None:
        self.rows[i] = self._row(i, "failed", None, None, error=sentence, exit_code=1)

    def summary(self) -> tuple[list[BagRow], list[RigRow]]:
        rows = [
            row
            if row is not None
            else self._row(i, "not run", None, None, error="The batch stopped before this bag.")
            for i, row in enumerate(self.rows)
        ]
        return rig_rows(rows)


def _with_fingerprint(result: CalibrationResult, fingerprint: str) -> CalibrationResult:
    """The result with the planned ``provenance.config_fingerprint`` (the config's, and the
    segments choice's: a multi-segment result carries its reference segment's provenance),
    which a rerun compares to decide whether the bag is up to date."""
    prov = result.provenance
    if prov is None or prov.config_fingerprint == fingerprint:
        return result
    return replace(result, provenance=replace(prov, config_fingerprint=fingerprint))


def _sentence(err: BaseException, attempts: int) -> str:
    """One sentence for a task that raised or lost its worker on its last attempt."""
    tries = "its only attempt" if attempts == 1 else f"each of its {attempts} attempts"
    if type(err).__name__ == "KilledWorker":
        return (
            f"The worker calibrating it died on {tries} (out of memory, or killed); check the "
            "workers' memory and logs, or calibrate the bag alone with licalib calibrate."
        )
    if type(err).__name__ == "CancelledError":
        return (
            f"Its task was cancelled by the cluster on {tries}; check the scheduler's log and "
            "run the batch again."
        )
    text = str(err).strip().rstrip(".") or "no message"
    return (
        f"Internal error on {tries}: {type(err).__name__}: {text}; calibrate the bag alone with "
        "licalib --debug calibrate for the traceback and report it."
    )


def _what_happened(err: BaseException) -> str:
    if type(err).__name__ == "KilledWorker":
        return "its worker died"
    return f"it raised {type(err).__name__}"


def run_batch(
    jobs: Sequence[BatchJob],
    out_dir: Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    retries: int = 2,
    progress: Progress | None = None,
    task: Task = calibrate_task,
    connect_timeout_s: float = 10.0,
    quiet_dask: bool = True,
    settings: Mapping[str, Any] | None = None,
) -> BatchReport:
    """Calibrate every bag on a Dask cluster; write each result, ``summary.csv``, ``rigs.csv``.

    Args:
        jobs: the bags (:func:`licalib_cli.batch.read_inputs`).
        out_dir: results go to ``out_dir/<rig>/<bag-stem>.yaml`` (with ``.config.yaml``).
        scheduler: ``tcp://host:port`` of a running Dask scheduler; None: a local cluster.
        workers: worker processes of the local cluster (default: one per core).
        retries: how often a task that raised or whose worker died is tried again.
        progress: receives the stage ``calibrating``, the bags done of those to calibrate and a
            note ``N running, N failed``.
        task: the function each task runs (:func:`~licalib_cli.batch.task.calibrate_task`);
            it must be importable, or picklable, on the workers.
        connect_timeout_s: how long to wait for an existing scheduler and its first worker.
        quiet_dask: keep Dask's own log lines off.
        settings: ``--set`` settings by dotted key, applied over every bag's config file.

    Returns:
        The report.

    Raises:
        ManifestError, ConfigError: a job or the output folder cannot be used (before any
            calibration).
        ClusterError: the cluster cannot be started or reached.
        KeyboardInterrupt: after Ctrl-C, once the finished results and the summary (with the
            unfinished bags as ``not run``) are written and the cluster is closed.
    """
    start = time.perf_counter()
    progress = progress or NullProgress()
    if retries < 0:
        msg = f"--retries {retries} is not a number of retries; give 0 or more."
        raise ConfigError(msg)
    out_dir = Path(out_dir).absolute()
    if out_dir.exists() and not out_dir.is_dir():
        msg = f"The output {out_dir} is a file; -o takes a folder, give another one."
        raise ConfigError(msg)
    planned = plan(jobs, out_dir, settings)
    create_folder(out_dir, "The output folder", "give another folder with -o")
    tracker = _Tracker(planned, out_dir)
    todo = [i for i, p in enumerate(planned) if p.existing is None]
    for i in todo:
        logger.debug("%s: to calibrate (%s)", planned[i].label, planned[i].reason)
    threads = 0
    interrupted = False
    started = not todo  # the summary is written once the batch has reached its cluster
    try:
        if todo:
            with connect(
                scheduler, workers, timeout_s=connect_timeout_s, quiet=quiet_dask
            ) as client:
                started = True
                threads = sum(client.nthreads().values())
                _run(client, tracker, todo, retries, progress, task)
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        progress.close()
        bags, rigs = tracker.summary()
        if started or interrupted:
            write_summaries(out_dir, bags, rigs)
        if interrupted:
            done = sum(1 for r in tracker.rows if r is not None)
            logger.info(
                "Interrupted: %d of %d bags have a result or a failure recorded in %s; "
                "run the same command again to go on.",
                done,
                len(planned),
                out_dir / "summary.csv",
            )
    return BatchReport(
        out_dir=out_dir,
        bags=tuple(bags),
        rigs=tuple(rigs),
        workers=threads,
        wall_s=time.perf_counter() - start,
    )


def _run(
    client: Client,
    tracker: _Tracker,
    todo: Sequence[int],
    retries: int,
    progress: Progress,
    task: Task,
) -> None:
    """Submit, wait, write, retry until every bag of ``todo`` is done or failed.

    No more tasks are submitted than the cluster has worker threads: each waits on the
    client, not on a worker, so that a worker that dies takes only the bag it was calibrating
    with it (the scheduler would otherwise hand a worker several tasks of a small batch).
    """
    from distributed import as_completed

    planned = tracker.planned
    waiting = deque(todo)
    index: dict[Future, int] = {}
    completed = as_completed(loop=client.loop)

    def submit(i: int) -> None:
        tracker.attempts[i] += 1
        p = planned[i]
        spec = TaskInput(p.label, p.job.bag, p.cfg, tracker.attempts[i], p.job.segments)
        key = f"licalib-calibrate-{p.label}-{tracker.attempts[i]}-{uuid.uuid4().hex[:8]}"
        future = client.submit(task, spec, key=key, pure=False)
        index[future] = i
        completed.add(future)

    def fill() -> None:
        free = max(1, _threads(client)) - len(index)
        while waiting and free > 0:
            submit(waiting.popleft())
            free -= 1

    total = len(todo)
    done = failed = 0
    progress.stage("calibrating", total)
    fill()
    shown = time.monotonic()
    try:
        while index:
            finished = completed.next_batch(block=False)
            if not finished:
                if time.monotonic() - shown > _REFRESH_S:
                    fill()  # a worker may have joined
                    progress.note(f"{len(index)} running, {failed} failed")
                    shown = time.monotonic()
                time.sleep(_POLL_S)
                continue
            for future in finished:
                i = index.pop(future)
                label = planned[i].label
                if future.status == "finished":
                    outcome: TaskOutcome = future.result()
                    tracker.finished(i, outcome)
                    for text in outcome.warnings:
                        logger.warning("%s: %s", label, text)
                    if outcome.result is None:
                        failed += 1
                        logger.error("%s failed: %s", label, outcome.error)
                    else:
                        row = tracker.rows[i]
                        verdict = row.verdict.upper() if row else "?"
                        logger.info("%s: %s (%.1f s)", label, verdict, outcome.seconds)
                    done += 1
                    continue
                err = _exception(future)
                attempts = tracker.attempts[i]
                if attempts <= retries:
                    logger.warning(
                        "%s: %s on attempt %d; retry %d of %d.",
                        label,
                        _what_happened(err),
                        attempts,
                        attempts,
                        retries,
                    )
                    waiting.appendleft(i)
                    continue
                sentence = _sentence(err, attempts)
                tracker.failed(i, sentence)
                logger.error("%s failed: %s", label, sentence)
                failed += 1
                done += 1
            fill()
            progress.advance(done, total)
            progress.note(f"{len(index)} running, {failed} failed")
            shown = time.monotonic()
    except BaseException:
        client.cancel(list(index), force=True)
        raise


def _exception(future: Future) -> BaseException:
    try:
        err = future.exception(timeout=5)
    except BaseException as exc:  # a cancelled future raises here
        return exc
    return err if err is not None else RuntimeError("the task ended without a result")


def _threads(client: Client) -> int:
    """Worker threads of the cluster now (0 when it cannot be asked)."""
    try:
        return sum(client.nthreads().values())
    except Exception:  # a scheduler that went away: the futures say so
        return 0
