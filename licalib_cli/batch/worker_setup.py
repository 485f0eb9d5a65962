"""Preload of the local cluster's worker processes (``dask_setup`` runs in each at its start).

Ctrl-C at a terminal goes to every process of the foreground group, the workers included; the
client alone handles it (it writes what is finished and closes the cluster), so a worker
ignores it instead of printing its own traceback.
"""

from __future__ import annotations

import signal
import threading
from typing import Any


def dask_setup(worker: Any) -> None:
    """Ignore SIGINT in this worker process."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
