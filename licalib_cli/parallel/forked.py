"""Independent work in a forked process while the caller goes on.

Some stages hold the GIL for most of their time (kiss-icp's registrations, open3d's import, the
Python steps of a small solve), so threads cannot overlap them; two processes can. ``start(fn,
*args)`` forks a child that runs ``fn(*args)`` and sends the pickled result back through a
pipe; the caller does other work and collects the value with :meth:`Pending.result`::

    with forked.start(run_odometry, scans, cfg) as pending:
        sweeps = prepare_sweeps(scans, cfg)  # meanwhile, in this process
        poses = pending.result()

The inputs are not copied: the child sees the caller's memory as it was at the fork. Only the
calling thread is: a child must not use a library whose worker threads the caller has started.
open3d's oneTBB is one: a child registering scans after the caller had estimated normals waited
for TBB workers that do not exist in it, forever (kiss-icp links its own TBB, which the caller
never starts).

What the child logs is emitted again, in order, by the caller when it collects the result (the
child never writes to the terminal, so progress displays stay intact). An exception of ``fn`` is
raised again by :meth:`Pending.result`. A child that ends without a result (killed, out of
memory, a value or exception that cannot be pickled) costs the time it ran: ``fn`` then runs in
the caller, so the outcome is the same.

``fn`` runs in the caller, at :func:`start`, when forking cannot help or is not possible: one
usable core (``LICALIB_THREADS=1``, which ``licalib batch``'s local workers and ``pytest -n``
workers set since each core already runs a process), no ``os.fork`` (Windows), or inside a
forked child. Leaving the ``with`` block without collecting the result kills the child.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import struct
import sys
import time
from collections.abc import Callable
from types import TracebackType
from typing import Generic, TypeVar

from licalib_cli.parallel import threads as _threads

__all__ = ["Pending", "enabled", "start"]

T = TypeVar("T")

logger = logging.getLogger(__name__)

_HEADER = struct.Struct("<Q")
_in_child = False


def enabled() -> bool:
    """Whether :func:`start` forks (else it runs ``fn`` at once in the caller)."""
    return _threads.THREADS > 1 and hasattr(os, "fork") and not _in_child


class _Records(logging.Handler):
    """Collects the child's log records as (logger name, level, message)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if record.exc_info:
            message += "\n" + logging.Formatter().formatException(record.exc_info)
        self.records.append((record.name, record.levelno, message))


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def _read_exactly(fd: int, size: int) -> bytes | None:
    chunks: list[bytes] = []
    left = size
    while left:
        chunk = os.read(fd, min(left, 1 << 24))
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _child(fn: Callable[..., object], args: tuple[object, ...], fd: int) -> None:
    """Run in the forked child: ``fn(*args)``, its log and its outcome into ``fd``; never
    returns."""
    global _in_child
    code = 0
    try:
        _in_child = True
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        root = logging.getLogger()
        records = _Records()
        for handler in list(root.handlers):
            root.removeHandler(handler)
        root.addHandler(records)
        start = time.perf_counter()
        try:
            outcome: tuple[bool, object] = (True, fn(*args))
        except Exception as err:  # raised again by the caller
            logger.debug("%r failed in the forked process:", fn, exc_info=True)
            outcome = (False, err)
        seconds = time.perf_counter() - start
        try:
            data = pickle.dumps((outcome, records.records, seconds), pickle.HIGHEST_PROTOCOL)
        except Exception:  # not picklable: the caller runs fn itself
            code = 3
        else:
            _write_all(fd, _HEADER.pack(len(data)))
            _write_all(fd, data)
    except BaseException:  # interrupted, or the caller is gone (broken pipe)
        code = 2
    finally:
        os._exit(code)


class Pending(Generic[T]):
    """The outcome of ``fn(*args)``, running in a child (or already computed)."""

    def __init__(self, fn: Callable[..., T], args: tuple[object, ...]) -> None:
        self._fn = fn
        self._args = args
        self._pid = 0
        self._fd = -1
        self._done = False
        self._value: T | None = None
        if not enabled():
            self._value = fn(*args)
            self._done = True
            return
        for stream in (sys.stdout, sys.stderr):
            stream.flush()  # nothing buffered before the fork is written twice
        read_fd, write_fd = os.pipe()
        try:
            pid = os.fork()
        except OSError as err:  # no memory or process left for a child: work here
            os.close(read_fd)
            os.close(write_fd)
            logger.debug("No second process (%s); running %r here.", err, fn)
            self._value = fn(*args)
            self._done = True
            return
        if pid == 0:  # pragma: no cover - the child exits inside _child
            os.close(read_fd)
            _child(fn, args, write_fd)
        os.close(write_fd)
        self._pid, self._fd = pid, read_fd

    def result(self) -> T:
        """``fn(*args)``: the child's value, or its exception raised again."""
        if self._done:
            return self._value  # type: ignore[return-value]
        received = self._receive()
        self._done = True
        name = getattr(self._fn, "__qualname__", repr(self._fn))
        if received is None:
            logger.debug("The forked %s ended without a result; running it here.", name)
            self._value = self._fn(*self._args)
            return self._value
        (ok, value), records, seconds = received
        for logger_name, level, message in records:
            logging.getLogger(logger_name).log(level, message)
        logger.debug("%s ran in a forked process (%.2f s).", name, seconds)
        if not ok:
            assert isinstance(value, BaseException)
            raise value
        self._value = value  # type: ignore[assignment]
        return self._value  # type: ignore[return-value]

    def _receive(self) -> tuple[tuple[bool, object], list[tuple[str, int, str]], float] | None:
        try:
            header = _read_exactly(self._fd, _HEADER.size)
            data = None if header is None else _read_exactly(self._fd, _HEADER.unpack(header)[0])
        finally:
            os.close(self._fd)
            self._fd = -1
            os.waitpid(self._pid, 0)
        return None if data is None else pickle.loads(data)

    def cancel(self) -> None:
        """Stop the child if it still runs; the result is not collected."""
        if self._done or self._fd < 0:
            return
        self._done = True
        try:
            os.kill(self._pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        os.close(self._fd)
        self._fd = -1
        os.waitpid(self._pid, 0)

    def __enter__(self) -> Pending[T]:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.cancel()


def start(fn: Callable[..., T], *args: object) -> Pending[T]:
    """Begin ``fn(*args)`` in a forked child (or run it now, see the module notes)."""
    return Pending(fn, args)
