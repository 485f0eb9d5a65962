"""A small shared thread pool for the block loops of the vectorised evaluations.

The spline and residual evaluations process their queries in blocks of a few thousand (see
:mod:`licalib_cli.spline.so3_spline`); the blocks are independent and write disjoint slices of
preallocated outputs. numpy releases the GIL inside its element-wise loops (ufuncs, ``einsum``,
``take``), so on a machine with a spare core two threads working on different blocks overlap
most of their time, while the Python glue between numpy calls (a microsecond or so per call)
stays serialised.

:func:`map_blocks` runs ``fn(0) .. fn(count - 1)`` on the calling thread and ``THREADS - 1``
pool threads, which claim block numbers from a shared counter (no fixed split: blocks of the
same size do not take the same time when another process competes for a core). Every block
computes exactly what the serial loop computes, so the results are bit-for-bit identical;
callers collect per-block results from the returned list, which is in block order.

The gain is modest (measured on 2 cores: ``SO3Spline.evaluate`` of 250k queries 1.2-1.4 times
faster, the sample's optimisation stage about 6 %): the threads hand the GIL over between
hundreds of short numpy calls per block, and the page faults of the blocks' large temporaries
serialise in the kernel. Smaller blocks make it worse (more hand-overs).

``THREADS`` is read once from the environment variable ``LICALIB_THREADS`` (default 2, the
cores of the machines the tool is tuned on, or 1 when the process may use a single core; more
threads have not been measured); ``LICALIB_THREADS=1`` runs every block loop
serially on the calling thread and never creates the pool. :func:`serial` forces the serial
path in the current thread (tests use it to compare both paths). Block functions run with the
serial path forced, so a block that itself evaluates something block-wise does not wait for a
pool its own caller occupies.
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import contextmanager
from typing import TypeVar

__all__ = [
    "BLOCK",
    "MIN_BLOCKS",
    "THREADS",
    "Filled",
    "map_blocks",
    "map_slices",
    "serial",
    "threads",
    "usable_cores",
]

T = TypeVar("T")

logger = logging.getLogger(__name__)


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity; all CPUs where that is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _threads_from_env() -> int:
    """``LICALIB_THREADS`` as a positive int; unset: 2, or 1 on a single usable core (a second
    thread would only add the hand-over). A value that is not a positive integer falls back to
    1, with a warning saying so."""
    raw = os.environ.get("LICALIB_THREADS", "").strip()
    if not raw:
        return min(2, usable_cores())
    try:
        value = int(raw)
    except ValueError:
        value = 0
    if value < 1:
        logger.warning(
            "LICALIB_THREADS=%r is not a positive whole number; the evaluations run on one "
            "thread (unset it, or set 1 or 2).",
            raw,
        )
        return 1
    return value


THREADS: int = _threads_from_env()
"""Threads that work on one block loop (the caller included); 1 = serial."""

MIN_BLOCKS = 2
"""Fewer blocks than this run serially: one block cannot be shared between threads."""

BLOCK = 8192
"""Queries per evaluation block of the splines and the point-to-plane residual: temporaries of a
few hundred kB stay in cache and numpy's per-call overhead is spread over enough queries
(smaller blocks were measured slower, also threaded). One size for all of them, so that the
residual evaluating the splines block by block computes exactly what one evaluation of all its
points does."""

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()
_local = threading.local()


def _get_pool() -> ThreadPoolExecutor:
    """The shared pool of ``THREADS - 1`` threads, created on first use.

    Its threads are joined by the interpreter at exit after their current block (they only
    ever run short block loops), so an idle pool never holds the process open.
    """
    global _pool
    pool = _pool
    if pool is None:
        with _pool_lock:
            pool = _pool
            if pool is None:
                pool = ThreadPoolExecutor(
                    max_workers=THREADS - 1, thread_name_prefix="licalib-blocks"
                )
                _pool = pool
    return pool


def _forget_pool() -> None:
    """Drop the pool in a forked child: its threads were not copied into the child."""
    global _pool, _pool_lock
    _pool = None
    _pool_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def threads() -> int:
    """Threads a block loop started from the current thread would use (1 = serial)."""
    return 1 if getattr(_local, "serial", False) else THREADS


@contextmanager
def serial() -> Iterator[None]:
    """Run the block loops started from the current thread serially while in the context."""
    before = getattr(_local, "serial", False)
    _local.serial = True
    try:
        yield
    finally:
        _local.serial = before


def map_blocks(fn: Callable[[int], T], count: int) -> list[T]:
    """``[fn(0), ..., fn(count - 1)]``, the calls shared between up to ``THREADS`` threads.

    ``fn`` must only write outputs no other block writes (disjoint slices) and must not rely
    on the order the blocks run in; the returned list is in block order. With one thread, fewer
    than :data:`MIN_BLOCKS` blocks or inside a block function it is the plain serial loop.
    An exception raised by a block stops the others from claiming more blocks and is re-raised
    once every thread has left the loop.

    Args:
        fn: Computes block ``k`` (0-based) and returns its result.
        count: Number of blocks.

    Returns:
        The blocks' results, in block order.
    """
    workers = min(threads(), count)
    if workers < 2 or count < MIN_BLOCKS:
        return [fn(k) for k in range(count)]
    results: list[T | None] = [None] * count
    claim = itertools.count().__next__  # atomic under the GIL
    failed = threading.Event()

    def drain() -> None:
        with serial():
            try:
                while not failed.is_set():
                    k = claim()
                    if k >= count:
                        return
                    results[k] = fn(k)
            except BaseException:
                failed.set()
                raise

    pool = _get_pool()
    futures: list[Future[None]] = [pool.submit(drain) for _ in range(workers - 1)]
    try:
        drain()
    finally:
        wait(futures)
    for future in futures:
        future.result()
    return results  # type: ignore[return-value]  # every slot was filled


def map_slices(fn: Callable[[slice], T], size: int, block: int = BLOCK) -> list[T]:
    """``fn`` on the consecutive slices of ``range(size)`` of ``block`` items (the last one
    shorter), shared as :func:`map_blocks` shares its blocks; results in slice order."""
    return map_blocks(lambda k: fn(slice(k * block, min((k + 1) * block, size))), -(-size // block))


class Filled:
    """How many leading entries of an array one thread fills in order are final, for another
    thread that reads them as they come (:meth:`wait_for`).

    The producer calls :meth:`publish` after writing an entry and :meth:`fail` when it stops
    early; a reader waiting for entries that will never come then raises instead of waiting
    forever.
    """

    def __init__(self) -> None:
        self._count = 0
        self._failed = False
        self._changed = threading.Condition()

    @property
    def count(self) -> int:
        """Entries final so far."""
        return self._count

    def publish(self, count: int) -> None:
        """The first ``count`` entries are final."""
        with self._changed:
            self._count = max(self._count, count)
            self._changed.notify_all()

    def fail(self) -> None:
        """The producer stopped: no more entries will come."""
        with self._changed:
            self._failed = True
            self._changed.notify_all()

    def wait_for(self, count: int) -> None:
        """Return once the first ``count`` entries are final.

        Raises:
            RuntimeError: the producer stopped before filling them.
        """
        with self._changed:
            while self._count < count and not self._failed:
                self._changed.wait()
            if self._count < count:
                msg = f"the producing thread stopped after {self._count} of {count} entries"
                raise RuntimeError(msg)
