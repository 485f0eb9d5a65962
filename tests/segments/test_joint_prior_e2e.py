"""End to end: ``calibrate --segments`` of a planar vehicle with a measured lever arm that is
wrong.

A 12 s figure-8 (rotation about the vertical only) in two 6 s segments; the lever arm is given
as measured to 2 mm but is 30 mm off along y. The joint estimate must name the vertical as
resting on the measurement, find that the segments' data contradict the measurement along y,
warn, and report translation sigmas that cover the error the measurement's pull leaves.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from light_config import LIGHT_VLP16

from licalib_cli.cli import main
from licalib_cli.simulation import SimulationSpec, simulate

CONFIG = LIGHT_VLP16  # configs/vlp16.yaml with a lighter final round

pytestmark = pytest.mark.slow


def test_a_wrong_measured_lever_arm_is_found_by_the_joint_estimate(tmp_path: Path, capsys) -> None:
    spec = SimulationSpec(
        scenario="figure8",
        lidar="vlp16",
        fmt="ros1",
        duration_s=12.0,
        seed=3,
        time_offset_s=0.005,
        intrinsics="none",
        azimuth_resolution_deg=0.4,
    )
    bag = simulate(spec, tmp_path / "bag").bag_path
    truth = yaml.safe_load((bag.parent / "truth.yaml").read_text())["extrinsic"]["translation"]
    measured = [v + d for v, d in zip(truth, (0.0, 0.03, 0.002), strict=True)]
    config = yaml.safe_load(CONFIG.read_text())
    config.setdefault("initialization", {}).update(
        translation_m=measured, translation_sigma_m=0.002
    )
    config_path = tmp_path / "measured.yaml"
    config_path.write_text(yaml.safe_dump(config))
    out = tmp_path / "joint.yaml"
    main(["calibrate", str(bag), "-c", str(config_path), "--segments", "0-6,6-12", "-o", str(out)])
    printed = capsys.readouterr().out
    result = yaml.safe_load(out.read_text())
    assert result["verdict"]["status"] == "warn"
    reasons = result["verdict"]["reasons"]
    conflict = [r for r in reasons if r.startswith("Joint estimate: The measured lever arm")]
    assert len(conflict) == 1 and "disagrees with the data" in conflict[0]
    assert any(
        r.startswith("Rests on the prior (joint estimate): ext.translation along [")
        and "taken from initialization.translation_m" in r
        for r in reasons
    )
    assert "disagrees with the data" in printed.replace("\n", " ")
    estimate = result["extrinsic"]["translation"]
    sigma = result["uncertainty"]["translation_std_m"]
    for axis in range(3):
        assert abs(estimate[axis] - truth[axis]) < 3 * sigma[axis], (axis, estimate, sigma)
    # the vertical rests on the measurement (2 mm off, its sigma): from it, not the data
    assert abs(estimate[2] - measured[2]) < 0.002 and 0.0019 < sigma[2] < 0.004
