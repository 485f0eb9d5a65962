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
