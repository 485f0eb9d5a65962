"""``python -m licalib_cli`` and the ``licalib`` console script.

This module imports nothing heavy before it can catch Ctrl-C: loading the command line
(typer, numpy, rosbags, ...) takes a noticeable moment, and an interrupt then ends with
"Interrupted." and exit code 130 like one later on (:func:`licalib_cli.cli.main`), not with
a traceback.

The objects left when the command returns are frozen out of the garbage collector
(``gc.freeze``): the collection at interpreter shutdown otherwise traverses them all (0.13 s of
the 0.2 s a calibration took to exit), for nothing the process still needs. Memory, files and
the ``atexit`` handlers (the log's flush) are released as before.
"""

from __future__ import annotations

import gc
import sys


def run() -> None:
    """Load the command line and run it on ``sys.argv``."""
    try:
        from licalib_cli.cli import main
    except KeyboardInterrupt:
        sys.stderr.write("Interrupted.\n")
        sys.exit(130)
    try:
        main()
    finally:
        gc.freeze()


if __name__ == "__main__":
    run()
