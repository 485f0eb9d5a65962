"""``python -m licalib_cli`` and the ``licalib`` console script.

This module imports nothing heavy before it can catch Ctrl-C: loading the command line
(typer, numpy, rosbags, ...) takes a noticeable moment, and an interrupt then ends with
"Interrupted." and exit code 130 like one later on (:func:`licalib_cli.cli.main`), not with
a traceback.
"""

from __future__ import annotations

import sys


def run() -> None:
    """Load the command line and run it on ``sys.argv``."""
    try:
        from licalib_cli.cli import main
    except KeyboardInterrupt:
        sys.stderr.write("Interrupted.\n")
        sys.exit(130)
    main()


if __name__ == "__main__":
    run()
