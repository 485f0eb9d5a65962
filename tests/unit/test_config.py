"""Configuration tree: defaults, overrides, unknown keys, bad values."""

from __future__ import annotations

import pytest
import yaml

from licalib_cli.config import dump_config, load_config
from licalib_cli.errors import ConfigError


def test_defaults_and_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("imu:\n  topic: /imu/data\nlidar:\n  time_unit: ns\n")
    cfg = load_config(path, {"lidar.topic": "/points", "imu.topic": None})
    assert cfg.imu.topic == "/imu/data"  # None overrides are ignored
    assert cfg.lidar.topic == "/points"
    assert cfg.lidar.time_unit == "ns"
    # The dump is valid YAML that loads back to the same tree.
    again = tmp_path / "again.yaml"
    again.write_text(dump_config(cfg))
    assert load_config(again) == cfg


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("imu:\n  topik: /x\n", "imu.topik"),
        ("lidar:\n  time_unit: fortnights\n", "lidar.time_unit"),
        ("bag:\n  duration_s: -3\n", "bag.duration_s"),
        ("- a\n- b\n", "must be a YAML mapping"),
        ("imu: [1, 2\n", "not valid YAML"),
    ],
)
def test_bad_config_files_name_the_problem(tmp_path, text, fragment):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=fragment.replace(".", r"\.")) as info:
        load_config(path)
    assert "\n" not in str(info.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")


def test_dump_is_complete():
    d = yaml.safe_load(dump_config(load_config(None)))
    assert set(d) >= {"bag", "imu", "lidar"}


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("bag:\n  max_duration_s: .inf\n", "'bag.max_duration_s'.*finite number"),
        ("bag:\n  start_s: .nan\n", "'bag.start_s'.*finite number"),
        ("lidar:\n  nominal_elevation_deg: []\n", "'lidar.nominal_elevation_deg'.*at least 1"),
        ("lidar:\n  nominal_elevation_deg: [95.0]\n", "less than or equal to 90"),
        (
            "lidar:\n  num_beams: 16\n  nominal_elevation_deg: [-15, 15]\n",
            "lists 2 beams but num_beams is 16",
        ),
        ("lidar:\n  max_skipped_fraction: 2\n", "'lidar.max_skipped_fraction'"),
        ("model:\n  bias_walk_piece_s: -1\n", "'model.bias_walk_piece_s'.*greater than 0"),
        ("model:\n  bias_walk_piece_s: abc\n", "'model.bias_walk_piece_s'.*valid number"),
    ],
)
def test_values_a_run_cannot_use_are_refused_at_load_time(tmp_path, text, fragment):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=fragment) as info:
        load_config(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("key", "value", "option"),
    [
        ("bag.start_s", float("inf"), "--start"),
        ("bag.duration_s", float("inf"), "--duration"),
        ("bag.start_s", float("nan"), "--start"),
    ],
)
def test_non_finite_options_name_the_option(key, value, option):
    with pytest.raises(ConfigError, match=f"Invalid value {value!r} for {option} \\({key}\\)"):
        load_config(None, {key: value})


def test_config_that_is_not_a_text_file_or_is_a_folder(tmp_path):
    binary = tmp_path / "c.yaml"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ConfigError, match=r"is not a text file \(byte \d+ is not UTF-8\)"):
        load_config(binary)
    with pytest.raises(ConfigError, match="is a folder; pass a YAML file"):
        load_config(tmp_path)
    control = tmp_path / "ctl.yaml"
    control.write_bytes(b"bag:\n  start_s: \x07\n")
    with pytest.raises(ConfigError, match=r"not valid YAML .*non-text character"):
        load_config(control)


def test_duplicated_keys_are_an_error(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("bag:\n  start_s: 1\nimu:\n  topic: /a\nbag:\n  duration_s: 20\n")
    with pytest.raises(ConfigError, match=r"gives the key 'bag' twice \(line 5\); keep one"):
        load_config(path)
    path.write_text("bag:\n  start_s: 1\n  start_s: 2\n")
    with pytest.raises(ConfigError, match="gives the key 'start_s' twice"):
        load_config(path)


def test_override_into_a_section_given_as_a_scalar(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("bag: 3\n")
    with pytest.raises(ConfigError, match="'bag'"):
        load_config(path, {"bag.start_s": 1.0})


def test_imu_prior_defaults_units_and_limits(tmp_path):
    prior = load_config(None).model.imu_prior
    assert prior.accel_scale == 1e-3 and prior.g_sensitivity == 0.0
    assert prior.sigma_of("gyro_rotation") == pytest.approx(0.05 * 3.141592653589793 / 180)
    assert prior.sigma_of("accel_scale") == 1e-3
    assert prior.sigma_of("imu_clock_drift") == 0.0  # not an IMU intrinsic: no prior
    path = tmp_path / "c.yaml"
    path.write_text("model:\n  imu_prior:\n    accel_scale: 0.0\n    gyro_rotation_deg: 0.2\n")
    cfg = load_config(path)
    assert cfg.model.imu_prior.accel_scale == 0.0  # known exactly
    assert cfg.model.imu_prior.gyro_rotation_deg == 0.2
    path.write_text("model:\n  imu_prior:\n    accel_scale: -0.001\n")
    with pytest.raises(ConfigError, match="accel_scale"):
        load_config(path)


def test_lidar_prior_defaults_to_exact_and_takes_the_lidar_s_units(tmp_path):
    """``model.lidar_prior``: 0 (taken as exact) by default; degrees for the angles; the
    model's ``held_prior`` asks the prior of each sensor's effects by the checks' names."""
    import math

    model = load_config(None).model
    assert all(model.held_prior(f"lidar_{b}") == 0.0 for b in ("azimuth", "point_time"))
    assert model.held_prior("accel_scale") == 1e-3  # the IMU's
    path = tmp_path / "c.yaml"
    path.write_text(
        "model:\n  lidar_prior:\n    azimuth_deg: 0.01\n    range_offset: 0.002\n"
        "    point_time: 1.0e-3\n"
    )
    model = load_config(path).model
    assert model.held_prior("lidar_azimuth") == pytest.approx(math.radians(0.01))
    assert model.held_prior("lidar_range_offset") == 0.002
    assert model.held_prior("lidar_point_time") == 1e-3
    assert model.held_prior("lidar_elevation") == 0.0 and model.held_prior("g_sensitivity") == 0.0
    path.write_text("model:\n  lidar_prior:\n    range_offset: -0.001\n")
    with pytest.raises(ConfigError, match="range_offset"):
        load_config(path)
    path.write_text("model:\n  lidar_prior:\n    azimuth: 0.01\n")  # the key is azimuth_deg
    with pytest.raises(ConfigError, match="azimuth"):
        load_config(path)


def test_lidar_spread_units_limits_and_the_priors_it_sets(tmp_path):
    """``model.lidar_spread``: unset by default (the weak prior); degrees for the angles; set,
    the prior of that per-beam intrinsic, and only while the model estimates it."""
    import math
    from types import SimpleNamespace

    from licalib_cli.models.lidar import INTRINSIC_NAMES
    from licalib_cli.pipeline.settings import (
        INTRINSIC_PRIOR_SIGMA,
        free_parameters,
        model_priors,
    )

    spread = load_config(None).model.lidar_spread
    assert all(getattr(spread, name) is None for name in type(spread).model_fields)
    assert spread.sigma_of("range_scale") is None
    path = tmp_path / "c.yaml"
    path.write_text(
        "model:\n  lidar: [range_scale, elevation]\n  lidar_spread:\n"
        "    range_scale: 1.5e-4\n    elevation_deg: 0.02\n    range_offset: 0.004\n"
    )
    cfg = load_config(path)
    assert cfg.model.lidar_spread.sigma_of("elevation") == pytest.approx(math.radians(0.02))
    assert cfg.model.lidar_spread.with_sigma("azimuth", math.radians(0.3)).azimuth_deg == (
        pytest.approx(0.3)
    )
    free = free_parameters(cfg, True)
    # range_offset is not estimated: its spread sets nothing
    assert dict(free.lidar_spread) == pytest.approx({"s": 1.5e-4, "dphi": math.radians(0.02)})
    state = SimpleNamespace(lidar_intrinsics=SimpleNamespace(num_beams=16))
    (prior,) = [p for p in model_priors(state, free) if p.block == "lidar.intrinsics"]
    sigma = 1.0 / prior.inv_sigma
    assert sigma.shape == (16, 6)
    default = INTRINSIC_PRIOR_SIGMA["lidar.intrinsics"]
    for j, name in enumerate(INTRINSIC_NAMES):
        expected = {"s": 1.5e-4, "dphi": math.radians(0.02)}.get(name, default[j])
        assert sigma[:, j] == pytest.approx(expected)
    assert "lidar_spread" in dump_config(cfg)
    for bad in ("range_scale: -1.0e-4", "elevation_deg: 0.0", "vertical_offset: 2.0"):
        path.write_text(f"model:\n  lidar_spread:\n    {bad}\n")
        with pytest.raises(ConfigError, match=bad.split(":")[0]):
            load_config(path)


def test_the_weak_floor_reaches_the_solver_and_is_checked(tmp_path):
    """``solver.weak_floor``: the fraction of the threshold above which an extrinsic direction
    is weakly determined (0.1 by default; 0 turns it off), passed to every round's solver."""
    from licalib_cli.pipeline.settings import lm_params

    assert lm_params(load_config(None)).weak_floor == 0.1
    assert lm_params(load_config(None, {"solver.weak_floor": 0.0})).weak_floor == 0.0
    path = tmp_path / "c.yaml"
    path.write_text("solver:\n  weak_floor: 0.25\n")
    assert lm_params(load_config(path)).weak_floor == 0.25
    path.write_text("solver:\n  weak_floor: 1.5\n")
    with pytest.raises(ConfigError, match=r"solver\.weak_floor") as info:
        load_config(path)
    assert "\n" not in str(info.value)
