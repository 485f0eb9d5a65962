"""The read stage's warning before the fit: the model estimates the accelerometer's frame on a
recording whose gravity hardly turned in the IMU frame."""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation

from licalib_cli.measurements import ImuSamples
from licalib_cli.pipeline.read import tilt_warning


def _rocking(amplitude_deg: float) -> ImuSamples:
    """An IMU rocking slowly (0.2 Hz) about its x axis by ``amplitude_deg`` for 10 s."""
    t = np.arange(0.0, 10.0, 0.005)
    a, w = np.radians(amplitude_deg), 2 * np.pi * 0.2
    r = Rotation.from_rotvec(np.outer(a * np.sin(w * t), [1.0, 0.0, 0.0])).as_matrix()
    gyro = np.outer(a * w * np.cos(w * t), [1.0, 0.0, 0.0])
    accel = np.einsum("nji,j->ni", r, [0.0, 0.0, 9.81])
    return ImuSamples((t * 1e9).astype(np.int64), gyro, accel)


def test_a_small_tilt_is_warned_of_only_when_the_model_estimates_the_accelerometer_frame() -> None:
    calm = _rocking(8.0)  # 5.6 deg RMS
    text = tilt_warning(calm, ["gyro_scale", "gyro_rotation", "accel_misalignment"])
    assert text is not None and text.startswith("Gravity turned only 6 deg RMS")
    assert "gyro_rotation and accel_misalignment estimated" in text
    assert "tilted by tens of degrees" in text and text.count(". ") == 0
    assert text.endswith("covers them.")
    one = tilt_warning(calm, ["accel_misalignment"]) or ""
    assert "accel_misalignment estimated" in one and one.endswith("covers it.")
    # the scales alone do not turn the accelerometer's frame; nothing estimated, nothing said
    assert tilt_warning(calm, ["gyro_scale", "accel_scale"]) is None
    assert tilt_warning(calm, []) is None
    # tilted by tens of degrees: enough
    assert tilt_warning(_rocking(30.0), ["gyro_rotation", "accel_misalignment"]) is None


def test_the_read_stage_logs_the_warning(tmp_path, caplog) -> None:
    """End to end through the read stage of a simulated plain shake (gravity about 10 deg)."""
    from licalib_cli.config import load_config
    from licalib_cli.pipeline.read import read
    from licalib_cli.simulation import SimulationSpec, simulate

    spec = SimulationSpec(
        scenario="shake", duration_s=4.0, seed=809, azimuth_resolution_deg=4.0, intrinsics="none"
    )
    out = simulate(spec, tmp_path / "sim")
    caplog.set_level(logging.WARNING, logger="licalib_cli")
    read(out.bag_path, load_config(None, {"model.imu": ["gyro_rotation"]}))
    warned = [r.getMessage() for r in caplog.records if "Gravity turned only" in r.getMessage()]
    assert len(warned) == 1 and "gyro_rotation estimated" in warned[0]
    caplog.clear()
    read(out.bag_path, load_config(None, {}))
    assert not [r for r in caplog.records if "Gravity turned" in r.getMessage()]


def test_the_blocks_warned_of_are_those_the_checks_name() -> None:
    from licalib_cli.inspection import ACCELEROMETER_FRAME_MODEL
    from licalib_cli.pipeline.checks import ACCELEROMETER_FRAME_BLOCKS

    assert set(ACCELEROMETER_FRAME_MODEL) == {m for _, m in ACCELEROMETER_FRAME_BLOCKS.values()}
