"""End to end: ``calibrate --segments`` with the IMU intrinsics estimated, on segments each too
short to determine them alone.

A 12 s hand-held shake tilted by 30 deg (VLP-16, ideal sensors, seed 2801), the IMU intrinsics
estimated, two 6 s segments. Each segment alone leaves the accelerometer's misalignment and the
extrinsic rotation partly undetermined and warns for that alone; together they determine them.
The joint verdict is judged on what the segments determine together: PASS, within its sigmas of
the truth, each segment's warning listed without lowering it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.results import CalibrationResult
from licalib_cli.simulation import SimulationSpec, simulate
from licalib_cli.truth import Truth

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "vlp16.yaml"

pytestmark = pytest.mark.slow


def test_segments_short_only_of_information_pass_together(tmp_path: Path, capsys) -> None:
    spec = SimulationSpec(
        scenario="shake",
        duration_s=12.0,
        seed=2801,
        intrinsics="none",
        azimuth_resolution_deg=0.4,
        tilt_deg=30.0,
    )
    bag = simulate(spec, tmp_path / "bag").bag_path
    out = tmp_path / "joint.yaml"
    args = ["calibrate", str(bag), "-c", str(CONFIG), "--intrinsics", "imu"]
    main([*args, "--segments", "0-6,6-12", "-o", str(out)])
    capsys.readouterr()
    raw = yaml.safe_load(out.read_text())
    segments = raw["segments"]["segments"]
    assert [s["verdict"] for s in segments] != ["pass", "pass"]  # the premise
    reasons = raw["verdict"]["reasons"]
    for s in segments:
        if s["verdict"] != "pass":
            window = f"Segment {s['start_s']:g}-{s['end_s']:g} s alone: verdict {s['verdict']}"
            (said,) = [r for r in reasons if r.startswith(window)]
            assert "for what it does not determine on its own" in said
    assert raw["verdict"]["status"] == "pass", reasons
    result = CalibrationResult.load(out)
    truth = Truth.load(bag.parent / "truth.yaml")
    moved = truth.extrinsic_for(result).moved_to(result.extrinsic)
    unc = result.uncertainty
    sigma = np.concatenate(
        [unc.translation_std_m, np.radians(unc.rotation_std_deg), [unc.time_offset_std_s]]
    )
    assert np.all(np.abs(moved) < 3 * sigma), (moved, sigma)
