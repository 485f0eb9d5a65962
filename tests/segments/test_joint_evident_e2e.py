"""End to end: ``calibrate --segments`` estimates in every segment the effects a segment shows
beyond doubt (``licalib_cli.pipeline.segments_evident``).

Per-beam range offsets of 2 cm, left out of the configured model, bias a shake's translation by
about 16 mm. The windows are first calibrated with the configured model (the joint problem
needs one model for all); they show the offsets beyond doubt, every window is refitted with them
estimated (their close rival, a per-beam range scale, refitted in their place and found worse),
and the joint calibration estimates them: its extrinsic lands near the truth, the result's
``model.added`` names them and the configuration it returns estimates them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from light_config import LIGHT_VLP16

from licalib_cli.config import load_config
from licalib_cli.models.intrinsics import LidarIntrinsics
from licalib_cli.pipeline.joint import calibrate_segments
from licalib_cli.results import CalibrationResult
from licalib_cli.simulation import SimulationSpec, simulate

CONFIG = LIGHT_VLP16  # configs/vlp16.yaml with a lighter final round
VLP16_ELEVATION = np.radians(np.arange(-15.0, 16.0, 2.0))

pytestmark = pytest.mark.slow


def test_an_effect_a_segment_shows_beyond_doubt_is_estimated_in_every_segment(
    tmp_path: Path,
) -> None:
    rng = np.random.default_rng(3)
    offsets = np.concatenate([[0.0], rng.normal(0.0, 0.02, 15)])
    lidar = LidarIntrinsics.nominal(VLP16_ELEVATION).with_(range_offset=offsets)
    intrinsics = tmp_path / "intrinsics.yaml"
    CalibrationResult(lidar_intrinsics=lidar).save(intrinsics)
    spec = SimulationSpec(
        scenario="shake",
        lidar="vlp16",
        duration_s=10.0,
        seed=3,
        time_offset_s=0.004,
        intrinsics="none",
        intrinsics_file=intrinsics,
        azimuth_resolution_deg=0.4,
    )
    sim = simulate(spec, tmp_path / "sim")
    run = calibrate_segments(sim.bag_path, load_config(CONFIG), "0-5,5-10")
    result = run.result
    assert result.model is not None and result.model.lidar == ("range_offset",)
    (added,) = result.model.added
    assert added.effect == "lidar_range_offset" and added.delta_bic < 0
    assert added.statistic > 100 * added.dof and added.moved_translation_m > 0.005
    # a per-beam range scale explains most of the offsets' score: refitted in their place in
    # every segment, it fit the same data worse, and the segments tell the two apart
    assert (added.rival, added.not_told_apart) == ("lidar_range_scale", ())
    assert added.rival_delta_bic < -100.0
    assert run.config is not None and run.config.model.lidar == ["range_offset"]
    assert "effects shown beyond doubt" in run.timings
    truth = sim.truth.extrinsic_for(result)
    assert result.extrinsic.error_to(truth)["translation_m"] < 0.004
    assert result.lidar_intrinsics is not None
    estimated = result.lidar_intrinsics.range_offset
    assert np.abs((estimated - estimated[0]) - (offsets - offsets[0])).max() < 0.003
    # each segment's own calibration estimated them too
    assert all(r.result.model is not None and r.result.model.lidar for r in run.runs)
