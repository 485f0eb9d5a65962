"""Exception hierarchy.

Every failure a user can cause is raised as a subclass of :class:`LicalibError` whose message
is one sentence naming the problem and the fix. Only the CLI turns these into exit codes.
"""

from __future__ import annotations


class LicalibError(Exception):
    """Base class of every error licalib reports to a user."""

    exit_code: int = 1


class BagError(LicalibError):
    """The input is missing, not a bag, corrupt or truncated."""

    exit_code = 2


class TopicError(LicalibError):
    """A topic is missing, ambiguous or of the wrong message type."""

    exit_code = 3


class DataError(LicalibError):
    """The messages are unusable: empty or NaN clouds, bad point layout, wrong units."""

    exit_code = 4


class TimestampError(DataError):
    """Stamps are unsorted, duplicated, have gaps, or a time field has no span."""

    exit_code = 5


class ConfigError(LicalibError):
    """A configuration file or option is invalid."""

    exit_code = 6


class ExcitationError(LicalibError):
    """The data does not excite the motion the calibration needs."""

    exit_code = 7


class MapLost(ExcitationError):
    """The map lost its planes after the first round: the estimate diverged from the guess.

    Attributes:
        beams_held: the model held a spinning LiDAR's beams at nominal, so beams that disagree
            may be what blurred the map.
    """

    def __init__(self, msg: str, beams_held: bool = False) -> None:
        super().__init__(msg)
        self.beams_held = beams_held


class SolverError(LicalibError):
    """The optimisation failed."""

    exit_code = 8


class VerdictFailure(LicalibError):
    """The calibration ran and its result was written, but its verdict is ``fail``."""

    exit_code = 9


class NotConverged(VerdictFailure):
    """The calibration ran out of rounds while the estimate still moved (result written)."""

    exit_code = 10


class ManifestError(ConfigError):
    """``batch``: an input list that cannot be used: an unreadable manifest, an unknown column,
    a bad value, a bag that does not exist or a pattern that matches none."""


class ClusterError(LicalibError):
    """``batch``: the Dask cluster cannot be started or reached (a bad or unreachable scheduler
    address, a scheduler without workers, the ``batch`` extra not installed)."""

    exit_code = 11


class BatchIncomplete(LicalibError):
    """``batch`` ran to the end, but some bags have no usable result (they failed, or their
    verdict is ``fail``); every other result is written and ``summary.csv`` names each."""

    exit_code = 12
