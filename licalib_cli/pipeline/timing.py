"""Wall and CPU seconds per pipeline stage.

The CPU seconds are the process's (``time.process_time``: every thread, user and system), so on
a machine shared with other work they say what a stage costs while the wall seconds say how long
it took; a stage run by several threads at once can use more CPU than wall time.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from licalib_cli.progress import Progress

__all__ = ["StageTime", "Stopwatch", "Timer"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class StageTime:
    """Seconds spent in one stage (a stage entered several times adds up).

    Attributes:
        wall_s: elapsed wall-clock seconds.
        cpu_s: CPU seconds of the process (all threads) over the same time.
    """

    wall_s: float = 0.0
    cpu_s: float = 0.0

    def __add__(self, other: StageTime) -> StageTime:
        return StageTime(self.wall_s + other.wall_s, self.cpu_s + other.cpu_s)


class Stopwatch:
    """Wall and CPU time since it was started (or last read with :meth:`lap`)."""

    def __init__(self) -> None:
        self._wall = time.perf_counter()
        self._cpu = time.process_time()

    def lap(self) -> StageTime:
        """Time since the start or the previous lap; starts the next lap."""
        wall, cpu = time.perf_counter(), time.process_time()
        out = StageTime(wall - self._wall, cpu - self._cpu)
        self._wall, self._cpu = wall, cpu
        return out


class Timer:
    """Wall and CPU seconds per named stage, in the order the stages first ran."""

    def __init__(self) -> None:
        self.stages: dict[str, StageTime] = {}

    @property
    def timings(self) -> dict[str, float]:
        """Wall seconds per stage."""
        return {name: t.wall_s for name, t in self.stages.items()}

    def add(self, name: str, spent: StageTime) -> None:
        """Add ``spent`` to stage ``name``."""
        self.stages[name] = self.stages.get(name, StageTime()) + spent

    @contextmanager
    def stage(self, name: str, progress: Progress, total: int | None = None) -> Iterator[None]:
        """Time the body as stage ``name`` and announce it to ``progress``."""
        progress.stage(name, total)
        watch = Stopwatch()
        try:
            yield
        finally:
            spent = watch.lap()
            self.add(name, spent)
            logger.debug("Stage %s: %.2f s wall, %.2f s CPU.", name, spent.wall_s, spent.cpu_s)
