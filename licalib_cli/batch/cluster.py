"""The Dask cluster a batch runs on: a local one sized to the machine, or an existing one.

The only module that starts or connects to Dask. A local cluster runs one single-threaded
worker process per core (the calibration is single-threaded numpy; processes keep the
interpreter lock out of the way), its scheduler in this process, no dashboard and no profiler.
Its scheduler gives up on a task at the first worker death (``allowed-failures`` 0): the
batch's own ``--retries`` decide what happens next (and :mod:`~licalib_cli.batch.run` hands a
worker one task at a time, so that a death costs one bag). Its workers leave Ctrl-C to the
client (:mod:`~licalib_cli.batch.worker_setup`) and run without Dask's default
``MALLOC_TRIM_THRESHOLD_``, which slows the solver down threefold.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import TYPE_CHECKING, Any

from licalib_cli.errors import ClusterError, ConfigError
from licalib_cli.parallel.threads import usable_cores

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["connect", "default_workers"]

logger = logging.getLogger(__name__)

_DASK_LOGGERS = ("distributed", "tornado", "bokeh")
_WORKER_ENVIRON = {
    "OMP_NUM_THREADS": 1,
    "MKL_NUM_THREADS": 1,
    "OPENBLAS_NUM_THREADS": 1,
    "LICALIB_THREADS": 1,
}
"""Environment of the local workers: Dask's default less ``MALLOC_TRIM_THRESHOLD_=65536``,
which makes the solver's many short-lived arrays about three times slower to allocate; one
worker per core, so the spline evaluation runs on one thread in each
(:mod:`licalib_cli.parallel.threads`)."""
_WORKER_SETUP = "licalib_cli.batch.worker_setup"
"""Preload of the local workers: they leave Ctrl-C to the client."""


def default_workers() -> int:
    """Worker processes of a local cluster: the cores this process may use."""
    return usable_cores()


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError as err:
        msg = (
            "licalib batch needs Dask distributed, which is not installed; install the batch "
            "extra: pip install 'licalib_cli[batch]' (scripts/setup.sh does)."
        )
        raise ClusterError(msg) from err
    return distributed


@contextmanager
def _quiet_dask(quiet: bool) -> Iterator[None]:
    """Dask's own log lines (a restarted worker, a lost task) off unless asked for: the batch
    reports what happened to each bag itself."""
    if not quiet:
        yield
        return
    saved = {name: logging.getLogger(name).level for name in _DASK_LOGGERS}
    for name in _DASK_LOGGERS:
        logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def _scheduler_address(address: str) -> str:
    """``host:port`` or ``tcp://host:port`` checked, as Dask expects it."""
    text = address.strip()
    if "://" not in text:
        text = "tcp://" + text
    protocol, _, location = text.partition("://")
    host, sep, port = location.rpartition(":")
    if protocol not in ("tcp", "tls", "ucx", "inproc", "ws", "wss") or not location:
        ok = False
    elif protocol == "inproc":
        ok = True
    else:
        ok = bool(sep and host and port.isdigit() and 0 < int(port) < 65536)
    if not ok:
        msg = (
            f"The scheduler address {address!r} is not a Dask scheduler address; give "
            "tcp://HOST:PORT, e.g. --scheduler tcp://10.0.0.5:8786."
        )
        raise ClusterError(msg)
    return text


@contextmanager
def connect(
    scheduler: str | None = None,
    workers: int | None = None,
    *,
    timeout_s: float = 10.0,
    quiet: bool = True,
) -> Iterator[Client]:
    """A Dask client on a new local cluster, or on the scheduler at ``scheduler``.

    Args:
        scheduler: ``tcp://host:port`` of a running scheduler; None starts a local cluster.
        workers: worker processes of the local cluster (default: one per core); not with
            ``scheduler``.
        timeout_s: how long to wait for the scheduler, and for a first worker.
        quiet: keep Dask's own log lines off (the batch reports each bag itself).

    Yields:
        The client; on leaving, it is closed, and a local cluster with it.

    Raises:
        ClusterError: Dask is not installed, the address is not one, the scheduler cannot be
            reached or has no worker within ``timeout_s``.
        ConfigError: ``workers`` below 1, or given with ``scheduler``.
    """
    distributed = _import_distributed()
    import dask

    if scheduler is not None and workers is not None:
        msg = (
            "--workers sizes the local cluster; with --scheduler the cluster's own workers run "
            "the bags, drop --workers."
        )
        raise ConfigError(msg)
    if workers is not None and workers < 1:
        msg = f"--workers {workers} is not a number of workers; give 1 or more."
        raise ConfigError(msg)
    with _quiet_dask(quiet):
        if scheduler is None:
            n = workers or default_workers()
            settings = {
                "distributed.scheduler.allowed-failures": 0,
                "distributed.scheduler.worker-saturation": 1.0,
                "distributed.worker.profile.enabled": False,
                "distributed.nanny.pre-spawn-environ": dict(_WORKER_ENVIRON),
            }
            if quiet:
                settings["logging"] = {"distributed": "critical", "tornado": "critical"}
            cluster = client = None
            try:
                with dask.config.set(settings):
                    cluster = distributed.LocalCluster(
                        n_workers=n,
                        threads_per_worker=1,
                        processes=True,
                        dashboard_address=None,
                        host="127.0.0.1",
                        silence_logs=logging.CRITICAL if quiet else logging.WARNING,
                        preload=[_WORKER_SETUP],
                    )
                    client = distributed.Client(cluster, set_as_default=False)
                logger.debug("local Dask cluster of %d workers at %s", n, cluster.scheduler_address)
                yield client
            finally:
                if client is not None:
                    with suppress(Exception):
                        client.close()
                if cluster is not None:
                    with suppress(Exception):
                        cluster.close()
            return
        address = _scheduler_address(scheduler)
        try:
            client = distributed.Client(address, timeout=timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as err:
            msg = (
                f"Cannot reach the Dask scheduler at {address} within {timeout_s:g} s ({err}); "
                "check --scheduler and that the scheduler runs (dask scheduler)."
            )
            raise ClusterError(msg) from err
        try:
            try:
                client.wait_for_workers(1, timeout=timeout_s)
            except (OSError, TimeoutError) as err:
                msg = (
                    f"The Dask scheduler at {address} has no workers (none joined within "
                    f"{timeout_s:g} s); start some with: dask worker {address}."
                )
                raise ClusterError(msg) from err
            logger.debug(
                "Dask scheduler %s with %d threads", address, sum(client.nthreads().values())
            )
            yield client
        finally:
            with suppress(Exception):
                client.close()
