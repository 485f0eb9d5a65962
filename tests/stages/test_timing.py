"""Wall and CPU seconds per stage."""

from __future__ import annotations

import time

from licalib_cli.pipeline.timing import StageTime, Stopwatch, Timer
from licalib_cli.progress import NullProgress


def test_a_stage_entered_twice_adds_up_and_cpu_counts_only_work() -> None:
    timer = Timer()
    with timer.stage("odometry", NullProgress()):
        time.sleep(0.05)  # wall time without CPU time
    with timer.stage("checks", NullProgress()):
        end = time.process_time() + 0.05
        while time.process_time() < end:  # CPU time
            pass
    with timer.stage("odometry", NullProgress()):
        time.sleep(0.05)
    assert list(timer.stages) == ["odometry", "checks"]
    odo, checks = timer.stages["odometry"], timer.stages["checks"]
    assert odo.wall_s >= 0.1
    assert odo.cpu_s < 0.05
    assert checks.cpu_s >= 0.05
    assert timer.timings == {"odometry": odo.wall_s, "checks": checks.wall_s}


def test_stopwatch_laps_and_stage_times_add() -> None:
    watch = Stopwatch()
    time.sleep(0.02)
    first = watch.lap()
    second = watch.lap()
    assert first.wall_s >= 0.02
    assert second.wall_s < first.wall_s
    total = StageTime(1.0, 0.5) + StageTime(2.0, 0.25)
    assert total == StageTime(3.0, 0.75)
