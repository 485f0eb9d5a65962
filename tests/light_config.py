"""The configuration of the heavier end-to-end tests: ``configs/vlp16.yaml`` with a lighter
denser final round.

Those tests check what the checks, the verdict, ``diagnose`` and the intrinsics report, not the
last tenths of a millimetre that the default's 6000 points a sweep in the final round buy over
3000; on their 8 s bags the lighter round takes about a fifth off each calibration (the
default's own accuracy is the benchmarks' business, and ``test_calibrate_e2e`` keeps it).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import yaml

VLP16 = Path(__file__).resolve().parents[1] / "configs" / "vlp16.yaml"

FINAL_POINTS_PER_SCAN = 3000
"""Points per sweep of the tests' final round (the default config: 6000)."""


def _write() -> Path:
    """``configs/vlp16.yaml`` with ``surfels.final_points_per_scan`` lowered, in a folder of the
    temporary directory named after its content.

    Every process of a run finds the same file and the next run reuses it: one folder in all.
    A folder per process, removed at exit, was left behind by the batch tests' cluster workers,
    which import the test modules and are stopped without running ``atexit`` handlers. The file
    is written atomically, so processes writing it at once write the same bytes in turn."""
    tree = yaml.safe_load(VLP16.read_text())
    tree.setdefault("surfels", {})["final_points_per_scan"] = FINAL_POINTS_PER_SCAN
    text = yaml.safe_dump(tree, sort_keys=False)
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    folder = Path(tempfile.gettempdir()) / f"licalib-tests-config-{digest}"
    path = folder / "vlp16.yaml"
    if not (path.is_file() and path.read_text() == text):
        folder.mkdir(exist_ok=True)
        part = folder / f".vlp16.{os.getpid()}.yaml"
        part.write_text(text)
        os.replace(part, path)
    return path


LIGHT_VLP16 = _write()
"""The lighter configuration's file."""
