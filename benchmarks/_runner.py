"""Runs a benchmark's cases, each in a fresh subprocess, a few at a time.

Every case runs as ``command(case)`` (the benchmark script again with ``--one CASE``), which
prints its row as the last line of its output, one JSON object. :func:`run_cases` yields
``(case, row, error)`` as each finishes: ``row`` None and ``error`` the last line of its
standard error when it printed no row.
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence


def run_cases(
    todo: Sequence[dict], command: Callable[[dict], list[str]], jobs: int
) -> Iterator[tuple[dict, dict | None, str]]:
    """Run ``command(case)`` for every case, at most ``jobs`` at a time, in order of start."""
    running: list[tuple[subprocess.Popen, dict]] = []
    queue = list(todo)
    while queue or running:
        while queue and len(running) < max(jobs, 1):
            c = queue.pop(0)
            proc = subprocess.Popen(
                command(c), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
            )
            running.append((proc, c))
        time.sleep(0.5)
        for proc, c in list(running):
            if proc.poll() is None:
                continue
            running.remove((proc, c))
            out, err = proc.communicate()
            try:
                yield c, json.loads(out.strip().splitlines()[-1]), ""
            except (IndexError, json.JSONDecodeError):
                yield c, None, (err.strip().splitlines() or ["?"])[-1]
