"""The range noise the map planes' correction subtracts: measured per beam, not configured."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import NoiseModel
from licalib_cli.pipeline.settings import (
    NoiseLevels,
    association_distance,
    narrow_association,
    noise_model,
    surfel_config,
)


def _levels(per_beam: np.ndarray, measured: float, configured: float = 0.01) -> NoiseLevels:
    gyro, accel = np.full(3, 1e-3), np.full(3, 1e-2)
    return NoiseLevels(
        gyro, accel, configured, "config", "config", "config", per_beam, gyro, accel, measured
    )


def test_the_weights_keep_the_configured_sigma_and_the_correction_gets_the_measured_noise() -> None:
    per_beam = np.array([0.002, np.nan, 0.003, 0.0])
    model = noise_model(CalibConfig(), _levels(per_beam, measured=0.0025))
    assert model.range_sigma == 0.01  # weighting: the config's figure
    # a beam too sparse to measure gets the beams' median; a noise-free beam keeps its zero
    np.testing.assert_allclose(model.range_noise([0, 1, 2, 3, 3]), [0.002, 0.0025, 0.003, 0, 0])
    # nothing measured at all: the weighting sigma
    none = noise_model(CalibConfig(), _levels(np.full(4, np.nan), measured=float("nan")))
    np.testing.assert_allclose(none.range_noise([0, 3]), [0.01, 0.01])


def test_range_noise_without_a_measurement_or_beyond_the_beams_is_the_weighting_sigma() -> None:
    assert np.all(NoiseModel(range_sigma=0.02).range_noise([0, 5, 7]) == 0.02)
    model = NoiseModel(range_sigma=0.02, range_noise_per_beam=np.array([0.001, 0.004]))
    np.testing.assert_allclose(model.range_noise([1, 0, 2, -1]), [0.004, 0.001, 0.02, 0.02])
    assert model.range_noise(np.zeros(0, dtype=np.int64)).shape == (0,)


def test_the_default_thickness_cut_has_a_floor_for_nearly_noise_free_ranges() -> None:
    """A measured 0.1 mm of range noise would cut every surfel thicker than 0.15 mm, which no
    map blurred by its estimate has: the default cut is at least 5 mm; a configured one stays."""
    from licalib_cli.pipeline.settings import MIN_THICKNESS_M, surfel_config

    cfg = CalibConfig()
    base = association_distance(cfg, _levels(np.full(4, 0.01), measured=0.01, configured=0.01))
    quiet = _levels(np.full(4, 1e-4), measured=1e-4, configured=1e-4)
    assert surfel_config(cfg, quiet, base).max_thickness_m == MIN_THICKNESS_M == 0.005
    noisy = _levels(np.full(4, 0.01), measured=0.01, configured=0.01)
    assert surfel_config(cfg, noisy, base).max_thickness_m == 0.015
    set_cfg = CalibConfig.model_validate({"surfels": {"max_thickness_m": 0.002}})
    assert surfel_config(set_cfg, quiet, base).max_thickness_m == 0.002


def test_a_loose_association_allows_surfels_as_thick_as_half_its_looseness() -> None:
    """The first rounds' map is blurred by how far the points may still be off, not by the range
    noise: with a nearly noise-free LiDAR the default cut is at least half the association
    distance beyond the configured one; a noisy LiDAR's and a configured cut scale as before."""
    from licalib_cli.pipeline.settings import LOOSE_BLUR_SHARE, MIN_THICKNESS_M, surfel_config

    cfg = CalibConfig()
    base = association_distance(cfg, _levels(np.full(4, 0.01), measured=0.01, configured=0.01))
    quiet = _levels(np.full(4, 1e-4), measured=1e-4, configured=1e-4)
    assert surfel_config(cfg, quiet, 3 * base).max_thickness_m == pytest.approx(
        LOOSE_BLUR_SHARE * 2 * base
    )
    assert surfel_config(cfg, quiet, 3 * base).max_thickness_m > 3 * MIN_THICKNESS_M
    assert surfel_config(cfg, quiet, base).max_thickness_m == MIN_THICKNESS_M
    noisy = _levels(np.full(4, 0.01), measured=0.01, configured=0.01)
    assert surfel_config(cfg, noisy, 3 * base).max_thickness_m == pytest.approx(0.045)
    set_cfg = CalibConfig.model_validate({"surfels": {"max_thickness_m": 0.002}})
    assert surfel_config(set_cfg, quiet, 3 * base).max_thickness_m == pytest.approx(0.006)


def test_the_second_surface_limit_follows_the_thickness_cut() -> None:
    """A cell is left to the finer cells once a point lies six thickness limits off its plane
    (9 range-noise sigmas by default), in every round: both limits widen with the association
    distance."""
    from licalib_cli.pipeline.settings import SECOND_SURFACE_FACTOR, surfel_config

    cfg = CalibConfig()
    base = association_distance(cfg, _levels(np.full(4, 0.01), measured=0.01, configured=0.01))
    noisy = _levels(np.full(4, 0.01), measured=0.01, configured=0.01)
    for distance in (base, 4 * base):
        sc = surfel_config(cfg, noisy, distance)
        assert sc.max_thickness_m is not None and sc.max_point_distance_m is not None
        assert sc.max_point_distance_m == pytest.approx(SECOND_SURFACE_FACTOR * sc.max_thickness_m)
    assert surfel_config(cfg, noisy, 4 * base).max_point_distance_m == pytest.approx(0.36)


def test_the_default_association_distance_follows_the_range_noise_in_the_data() -> None:
    """3 cm up to 1.5 cm of noise, twice the noise beyond; the noise measured in the bag counts
    where it exceeds the configured weighting sigma; a configured distance stays."""
    cfg = CalibConfig()
    assert association_distance(cfg, _levels(np.full(4, 0.01), 0.01, 0.01)) == 0.03
    assert association_distance(cfg, _levels(np.full(4, 0.015), 0.015, 0.01)) == 0.03
    assert association_distance(cfg, _levels(np.full(4, 0.04), 0.04, 0.01)) == pytest.approx(0.08)
    assert association_distance(cfg, _levels(np.full(4, 0.01), 0.01, 0.05)) == pytest.approx(0.1)
    nothing = _levels(np.full(4, np.nan), float("nan"), 0.02)
    assert association_distance(cfg, nothing) == pytest.approx(0.04)
    noisy = _levels(np.full(4, 0.04), 0.04, 0.01)
    # the settled rounds' surfels of the noisy LiDAR: the thickness cut follows the noise in
    # the data too, not the configured weighting sigma (1.5 x 4 cm)
    assert surfel_config(cfg, noisy, 0.08).max_distance_m == pytest.approx(0.08)
    assert surfel_config(cfg, noisy, 0.08).max_thickness_m == pytest.approx(0.06)
    set_cfg = CalibConfig.model_validate({"surfels": {"max_distance_m": 0.03}})
    assert association_distance(set_cfg, noisy) == 0.03


def test_a_configured_association_distance_under_twice_the_noise_is_warned_about() -> None:
    set_cfg = CalibConfig.model_validate({"surfels": {"max_distance_m": 0.03}})
    noisy = _levels(np.full(4, 0.04), 0.04, 0.01)
    text = narrow_association(set_cfg, noisy)
    assert text is not None
    assert text.startswith("surfels.max_distance_m = 3.0 cm is under twice the LiDAR's range ")
    assert "(4.0 cm)" in text and "at least 8.0 cm" in text and "leave it unset" in text
    assert narrow_association(set_cfg, _levels(np.full(4, 0.015), 0.015, 0.01)) is None
    assert narrow_association(CalibConfig(), noisy) is None
