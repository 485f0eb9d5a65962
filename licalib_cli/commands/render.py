"""Console helpers shared by the commands (rich)."""

from __future__ import annotations

from functools import cache

from rich.console import Console


@cache
def console() -> Console:
    """Standard-output console."""
    return Console(highlight=False)


@cache
def console_err() -> Console:
    """Standard-error console (logs, progress)."""
    return Console(stderr=True, highlight=False)
