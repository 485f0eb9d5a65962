"""Progress reporting, injected into long-running library calls.

The library reports through a :class:`Progress`; the default :class:`NullProgress` does nothing.
The command line passes a rich implementation when standard error is a terminal.
"""

from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    """Receives stage names and per-stage progress."""

    def stage(self, name: str, total: int | None = None) -> None:
        """A new stage starts; ``total`` steps if known."""

    def advance(self, done: int, total: int | None = None) -> None:
        """``done`` of ``total`` steps of the current stage are finished."""

    def note(self, text: str) -> None:
        """A one-line status message within the current stage."""

    def close(self) -> None:
        """All work is done."""


class NullProgress:
    """A :class:`Progress` that ignores everything."""

    def stage(self, name: str, total: int | None = None) -> None:
        return None

    def advance(self, done: int, total: int | None = None) -> None:
        return None

    def note(self, text: str) -> None:
        return None

    def close(self) -> None:
        return None
