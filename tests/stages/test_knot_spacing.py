"""The trajectory's knot spacing chosen from the IMU's signals: coarse for smooth motion, the
finest for a shake, the config's when it gives one."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.config import CalibConfig, load_config
from licalib_cli.errors import ConfigError
from licalib_cli.measurements import ImuSamples
from licalib_cli.pipeline.knot_spacing import (
    EXCESS,
    STEP,
    candidate_spacings,
    choose_knot_spacing,
    with_knot_spacing,
)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def _imu(rng: np.random.Generator, freq_hz: float, rate_hz: float = 400.0) -> ImuSamples:
    """12 s of readings: sines at ``freq_hz`` on every axis (rotation rate 1 rad/s, specific
    force 2 m/s^2 around gravity) plus white noise of an MTi-class IMU."""
    t = np.arange(0.0, 12.0, 1.0 / rate_hz)
    phase = np.array([0.0, 1.0, 2.0])
    wave = np.sin(2 * np.pi * freq_hz * t[:, None] + phase)
    gyro = 1.0 * wave + 0.0035 * rng.standard_normal((t.size, 3))
    accel = 2.0 * wave + np.array([0, 0, 9.81]) + 0.0118 * rng.standard_normal((t.size, 3))
    return ImuSamples((t * 1e9).astype(np.int64), gyro, accel)


def test_smooth_motion_gets_the_coarsest_spacing_and_a_shake_keeps_the_finest(rng) -> None:
    cfg = CalibConfig()
    slow = choose_knot_spacing(_imu(rng, 0.5), cfg)
    assert slow.chosen and slow.spacing_s == cfg.spline.max_knot_spacing_s == 0.05
    assert max(slow.excess) <= EXCESS
    # 6 Hz: a linear piece every 25 ms cannot follow the accelerometer within the noise
    fast = choose_knot_spacing(_imu(rng, 6.0), cfg)
    assert fast.chosen and fast.spacing_s == cfg.spline.min_knot_spacing_s == 0.02
    assert fast.excess[-1] > EXCESS  # the search stopped at the first candidate too coarse
    assert "20 ms" in fast.describe()


def test_the_spacing_grows_as_the_motion_slows(rng) -> None:
    spacings = [choose_knot_spacing(_imu(rng, f), CalibConfig()).spacing_s for f in (4, 2.5, 1)]
    assert spacings == sorted(spacings)
    assert spacings[0] < spacings[-1]


def test_a_configured_spacing_is_kept_and_the_resolved_config_names_the_chosen_one(rng) -> None:
    cfg = CalibConfig.model_validate({"spline": {"knot_spacing_s": 0.03}})
    fixed = choose_knot_spacing(_imu(rng, 0.5), cfg)
    assert not fixed.chosen and fixed.spacing_s == 0.03
    assert "spline.knot_spacing_s" in fixed.describe()
    assert CalibConfig().spline.spacing_s == 0.02  # unresolved: the finest
    resolved = with_knot_spacing(CalibConfig(), 0.04)
    assert resolved.spline.knot_spacing_s == resolved.spline.spacing_s == 0.04
    assert with_knot_spacing(resolved, 0.04) is resolved


def test_candidates_step_from_the_finest_to_the_coarsest() -> None:
    c = candidate_spacings(0.02, 0.05)
    assert c[0] == 0.02 and c[-1] == 0.05
    ratios = np.diff(np.log(c))
    assert np.all(ratios > 0) and np.all(ratios <= np.log(STEP) * 1.5)
    assert candidate_spacings(0.03, 0.03) == (0.03,)


def test_a_range_with_min_above_max_is_refused_in_one_sentence(tmp_path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("spline:\n  min_knot_spacing_s: 0.06\n  max_knot_spacing_s: 0.05\n")
    with pytest.raises(ConfigError, match="min_knot_spacing_s"):
        load_config(path)
