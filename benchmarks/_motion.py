"""The ``--tilt-deg`` option the benchmarks share: a slow tilt added to their shake cases.

``simulate --tilt-deg`` adds to the shake a tilt about each horizontal axis, so the accelerometer
sees gravity from attitudes tens of degrees apart; the other motions keep their own attitude.
"""

from __future__ import annotations

import argparse


def add_tilt_option(p: argparse.ArgumentParser) -> None:
    """Add ``--tilt-deg`` to a benchmark's parser."""
    p.add_argument(
        "--tilt-deg",
        type=float,
        default=0.0,
        help="shake cases: add a slow tilt of this amplitude about each horizontal axis "
        "(simulate --tilt-deg); default none",
    )


def tilt_spec_kwargs(case: dict) -> dict:
    """The ``SimulationSpec`` keywords of a case's tilt (shake cases only)."""
    return {"tilt_deg": case.get("tilt_deg", 0.0)} if case["scenario"] == "shake" else {}
