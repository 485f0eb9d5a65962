"""What a bag's stamps say: findings (fatal or warnings) and stamp statistics, shared by the
readers and ``licalib info``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import DataError, LicalibError, TimestampError
from licalib_cli.io.bag import MessageLosses

__all__ = [
    "IMU_GAP_FACTOR",
    "LIDAR_GAP_FACTOR",
    "MIN_IMU_SAMPLES",
    "Finding",
    "StampStats",
    "count_noun",
    "first_fatal",
    "imu_problems",
    "lidar_stamp_problems",
    "loss_findings",
    "raise_fatal",
    "stamp_stats",
    "stamp_text",
    "verb_for",
]

_NS = 1_000_000_000
IMU_GAP_FACTOR = 5.0
LIDAR_GAP_FACTOR = 2.5
MIN_IMU_SAMPLES = 10


def count_noun(n: int, noun: str, plural: str | None = None) -> str:
    """``"1 gap"``, ``"3 gaps"``: a number with its noun in agreement."""
    return f"{n} {noun if n == 1 else (plural or noun + 's')}"


def _times(n: int) -> str:
    """``"once"``, ``"twice"``, ``"3 times"``."""
    return {1: "once", 2: "twice"}.get(n, f"{n} times")


def _first(n: int) -> str:
    """``"first "`` before the position of the first of several events, else nothing."""
    return "first " if n > 1 else ""


def verb_for(n: int, singular: str, plural: str) -> str:
    """The verb form agreeing with a count."""
    return singular if n == 1 else plural


def stamp_text(stamp_ns: int) -> str:
    """A header stamp as ``sec.nanosec``, as ROS tools print it."""
    sec, nsec = divmod(int(stamp_ns), _NS)
    return f"{sec}.{nsec:09d}"


@dataclass(frozen=True)
class Finding:
    """A finding about the data.

    Attributes:
        message: one sentence naming the problem and the fix.
        fatal: True when the data cannot be used as is.
        error: the :class:`LicalibError` subclass raised for it (gives the exit code).
    """

    message: str
    fatal: bool
    error: type[LicalibError] = DataError

    @property
    def exit_code(self) -> int:
        """Exit code of the error class (0 for warnings)."""
        return self.error.exit_code if self.fatal else 0

    def exception(self) -> LicalibError:
        """The exception to raise for this finding."""
        return self.error(self.message)


def first_fatal(findings: list[Finding]) -> Finding | None:
    """The first fatal finding, or None."""
    return next((f for f in findings if f.fatal), None)


def raise_fatal(findings: list[Finding]) -> None:
    fatal = first_fatal(findings)
    if fatal is not None:
        raise fatal.exception()


@dataclass(frozen=True)
class StampStats:
    """Statistics of one topic's header stamps.

    Attributes:
        count: number of stamps.
        first_ns: first stamp, ns (0 when empty).
        last_ns: last stamp, ns (0 when empty).
        period_ns: median positive stamp difference, ns (0 when unknown).
        backwards: number of times a stamp is smaller than the previous one.
        first_backwards_s: seconds after ``first_ns`` of the first backwards step.
        duplicates: number of stamps equal to the previous one.
        first_duplicate_s: seconds after ``first_ns`` of the first duplicate.
        gaps: number of differences longer than the gap factor times the period.
        max_gap_s: largest stamp difference, seconds.
        max_gap_at_s: seconds after ``first_ns`` where the largest difference starts.
        missing_in_gaps: periods missing in the gaps, about the messages they lack.
    """

    count: int
    first_ns: int
    last_ns: int
    period_ns: int
    backwards: int
    first_backwards_s: float
    duplicates: int
    first_duplicate_s: float
    gaps: int
    max_gap_s: float
    max_gap_at_s: float
    missing_in_gaps: int = 0

    @property
    def rate_hz(self) -> float:
        """Nominal rate from the median period, Hz (0 when unknown)."""
        return _NS / self.period_ns if self.period_ns > 0 else 0.0

    @property
    def duration_s(self) -> float:
        """Last minus first stamp, seconds."""
        return (self.last_ns - self.first_ns) / _NS


def stamp_stats(t_ns: npt.NDArray[np.int64], gap_factor: float) -> StampStats:
    """Order, duplicates, rate and gaps of a stamp sequence (in arrival order).

    Args:
        t_ns: (N,) stamps in the order they were recorded, ns.
        gap_factor: a difference longer than ``gap_factor * period`` counts as a gap.

    Returns:
        The statistics.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    if t.size == 0:
        return StampStats(0, 0, 0, 0, 0, 0.0, 0, 0.0, 0, 0.0, 0.0)
    d = np.diff(t)
    pos = d[d > 0]
    period = int(np.median(pos)) if pos.size else 0
    t0 = int(t[0])
    back = np.flatnonzero(d < 0)
    dup = np.flatnonzero(d == 0)
    long = d[d > gap_factor * period] if period else d[:0]
    imax = int(np.argmax(d)) if d.size else 0
    return StampStats(
        count=int(t.size),
        first_ns=t0,
        last_ns=int(t[-1]),
        period_ns=period,
        backwards=int(back.size),
        first_backwards_s=float((t[back[0] + 1] - t0) / _NS) if back.size else 0.0,
        duplicates=int(dup.size),
        first_duplicate_s=float((t[dup[0] + 1] - t0) / _NS) if dup.size else 0.0,
        gaps=int(long.size),
        max_gap_s=float(d[imax] / _NS) if d.size else 0.0,
        max_gap_at_s=float((t[imax] - t0) / _NS) if d.size else 0.0,
        missing_in_gaps=int(np.sum(np.round(long / period) - 1)) if long.size else 0,
    )


def _losses_explain(stats: StampStats, lost: MessageLosses | None) -> bool:
    """Whether unreadable messages account for the gaps (at least 80 % of what they lack)."""
    return lost is not None and lost.total > 0 and lost.total >= 0.8 * stats.missing_in_gaps


def imu_problems(
    stats: StampStats, exact_duplicates: int = 0, lost: MessageLosses | None = None
) -> list[Finding]:
    """Findings on the IMU stamps (see the module table).

    Args:
        stats: IMU stamp statistics.
        exact_duplicates: how many duplicates are exact copies of the previous message
            (they are dropped and only warned about).
        lost: the topic's unreadable messages, to tell a damaged bag from a sensor that
            stopped publishing.
    """
    out: list[Finding] = []
    if stats.count < MIN_IMU_SAMPLES:
        out.append(
            Finding(
                f"Only {count_noun(stats.count, 'IMU sample')} in the segment; choose a longer "
                "segment with --start/--duration or check the IMU topic.",
                True,
                DataError,
            )
        )
        return out
    if stats.backwards:
        out.append(
            Finding(
                f"IMU stamps go backwards {_times(stats.backwards)} "
                f"({_first(stats.backwards)}at {stats.first_backwards_s:.3f} s); re-record, or "
                "rewrite the bag in stamp order (e.g. with `rosbags-convert` and a script), or "
                "pick a segment without it with --start/--duration.",
                True,
                TimestampError,
            )
        )
    real_dups = stats.duplicates - exact_duplicates
    if real_dups > 0:
        out.append(
            Finding(
                f"IMU stamps are duplicated {_times(real_dups)} with different values "
                f"({_first(real_dups)}at {stats.first_duplicate_s:.3f} s); the IMU driver "
                "stamps messages wrongly, fix its time stamping and re-record.",
                True,
                TimestampError,
            )
        )
    if exact_duplicates > 0:
        out.append(
            Finding(
                f"{count_noun(exact_duplicates, 'IMU message')} "
                f"{'was' if exact_duplicates == 1 else 'were'} recorded twice; the copies are "
                "dropped.",
                False,
                TimestampError,
            )
        )
    if stats.gaps:
        gap = (
            f"The IMU stream has {count_noun(stats.gaps, 'gap')} longer than "
            f"{IMU_GAP_FACTOR:g}x its period of {stats.period_ns / 1e6:.2f} ms (largest "
            f"{stats.max_gap_s:.3f} s at {stats.max_gap_at_s:.3f} s)"
        )
        if lost is not None and _losses_explain(stats, lost):
            n = lost.total
            gap += (
                f", caused by {count_noun(n, 'IMU message')} of the bag that cannot be read "
                f"({lost.describe()}); repair the bag or choose a segment without "
                f"{verb_for(n, 'it', 'them')} with --start/--duration."
            )
        else:
            gap += "; choose a segment without gaps with --start/--duration."
        out.append(Finding(gap, True, TimestampError))
    return out


def lidar_stamp_problems(stats: StampStats, lost: MessageLosses | None = None) -> list[Finding]:
    """Findings on the LiDAR header stamps (see the module table)."""
    out: list[Finding] = []
    if stats.count == 0:
        out.append(
            Finding(
                "No LiDAR clouds in the segment; choose another segment with --start/--duration.",
                True,
                DataError,
            )
        )
        return out
    if stats.backwards:
        out.append(
            Finding(
                f"LiDAR stamps go backwards {_times(stats.backwards)} "
                f"({_first(stats.backwards)}at {stats.first_backwards_s:.3f} s); re-record, or "
                "pick a segment without it with --start/--duration.",
                True,
                TimestampError,
            )
        )
    if stats.duplicates:
        out.append(
            Finding(
                f"LiDAR stamps are duplicated {_times(stats.duplicates)} "
                f"({_first(stats.duplicates)}at {stats.first_duplicate_s:.3f} s); the driver "
                "stamps clouds wrongly, fix it and re-record, or pick another segment with "
                "--start/--duration.",
                True,
                TimestampError,
            )
        )
    if stats.gaps:
        gap = (
            f"The LiDAR stream has {count_noun(stats.gaps, 'gap')} longer than "
            f"{LIDAR_GAP_FACTOR:g}x "
            f"its period (largest {stats.max_gap_s:.3f} s at {stats.max_gap_at_s:.3f} s)"
        )
        if lost is not None and _losses_explain(stats, lost):
            gap += (
                f", caused by {count_noun(lost.total, 'cloud')} of the bag that cannot be read "
                f"({lost.describe()}); repair the bag to use them."
            )
        else:
            gap += "; clouds were dropped while recording."
        out.append(Finding(gap, False, TimestampError))
    return out


def loss_findings(topic: str, what: str, lost: MessageLosses) -> list[Finding]:
    """A warning on the messages of ``topic`` that could not be used, if any."""
    if lost.total == 0:
        return []
    n = lost.total
    return [
        Finding(
            f"{count_noun(n, what + ' message')} on {topic} cannot be read ({lost.describe()}) "
            f"and {verb_for(n, 'is', 'are')} skipped; the bag is damaged, repair or re-record it "
            "if the data there is needed.",
            False,
            DataError,
        )
    ]
