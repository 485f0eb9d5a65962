"""The configuration of the heavier end-to-end tests: ``configs/vlp16.yaml`` with a lighter
denser final round.

Those tests check what the checks, the verdict, ``diagnose`` and the intrinsics report, not the
last tenths of a millimetre that the default's 6000 points a sweep in the final round buy over
3000; on their 8 s bags the lighter round takes about a fifth off each calibration (the
default's own accuracy is the benchmarks' business, and ``test_calibrate_e2e`` keeps it).
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import yaml

VLP16 = Path(__file__).resolve().parents[1] / "configs" / "vlp16.yaml"

FINAL_POINTS_PER_SCAN = 3000
"""Points per sweep of the tests' final round (the default config: 6000)."""


def _write() -> Path:
    """``configs/vlp16.yaml`` with ``surfels.final_points_per_scan`` lowered, written once per
    process into a folder removed at exit."""
    tree = yaml.safe_load(VLP16.read_text())
    tree.setdefault("surfels", {})["final_points_per_scan"] = FINAL_POINTS_PER_SCAN
    folder = Path(tempfile.mkdtemp(prefix="licalib-tests-config-"))
    atexit.register(shutil.rmtree, folder, True)
    path = folder / "vlp16.yaml"
    path.write_text(yaml.safe_dump(tree, sort_keys=False))
    return path


LIGHT_VLP16 = _write()
"""The lighter configuration's file."""
