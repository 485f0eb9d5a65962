"""licalib_cli.parallel.forked: a function run in a forked process gives what it gives in the
caller (value, exception, log), and the caller falls back on itself when the child dies."""

from __future__ import annotations

import logging
import os
import time

import numpy as np
import pytest

from licalib_cli.parallel import forked
from licalib_cli.parallel import threads as thr

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")


@pytest.fixture
def two_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fork even when the suite runs with LICALIB_THREADS=1."""
    monkeypatch.setattr(thr, "THREADS", 2)


def _pid_and_sum(x: np.ndarray) -> tuple[int, float]:
    logging.getLogger("licalib_cli.test_child").info("summed %d values", x.size)
    return os.getpid(), float(x.sum())


def _fails(message: str) -> None:
    raise ValueError(message)


def _dies_in_child(parent: int) -> int:
    if os.getpid() != parent:
        os._exit(7)  # as if killed: no result is sent
    return 42


def _nested() -> tuple[int, int]:
    inner = forked.start(os.getpid)
    return os.getpid(), inner.result()


def test_value_comes_from_a_child_and_its_log_is_emitted_again(
    two_cores: None, caplog: pytest.LogCaptureFixture
) -> None:
    x = np.arange(1000.0)
    caplog.set_level(logging.INFO)
    with forked.start(_pid_and_sum, x) as pending:
        pid, total = pending.result()
    assert pid != os.getpid()
    assert total == float(x.sum())
    assert [r.getMessage() for r in caplog.records if r.name == "licalib_cli.test_child"] == [
        "summed 1000 values"
    ]


def test_exception_of_the_child_is_raised_in_the_caller(two_cores: None) -> None:
    with pytest.raises(ValueError, match="no planes in the map"):
        forked.start(_fails, "no planes in the map").result()


def test_a_child_that_dies_without_result_is_replaced_by_the_caller(two_cores: None) -> None:
    assert forked.start(_dies_in_child, os.getpid()).result() == 42


def test_nested_start_runs_in_the_child_itself(two_cores: None) -> None:
    outer, inner = forked.start(_nested).result()
    assert outer != os.getpid()
    assert inner == outer


def test_one_core_runs_in_the_caller(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(thr, "THREADS", 1)
    assert not forked.enabled()
    pid, _ = forked.start(_pid_and_sum, np.ones(3)).result()
    assert pid == os.getpid()


def test_leaving_the_block_stops_the_child(two_cores: None) -> None:
    with forked.start(time.sleep, 30.0) as pending:
        pid = pending._pid
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # reaped: no such process any more


def _bad_scans() -> None:
    from licalib_cli.errors import DataError

    raise DataError("A LiDAR scan has no points; drop empty scans before odometry.")


def test_a_user_error_in_the_child_keeps_its_class_and_sentence(two_cores: None) -> None:
    """The command line turns licalib's errors into one sentence and an exit code by class: an
    error raised in the child arrives as that class with that sentence."""
    from licalib_cli.errors import DataError

    with pytest.raises(DataError, match=r"^A LiDAR scan has no points; drop empty scans"):
        forked.start(_bad_scans).result()
