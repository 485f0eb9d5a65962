"""The model of a calibration over several segments chosen from the windows' diagnoses: every
effect any window kept, in the order first kept, with the first spread across beams kept."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from licalib_cli.config import CalibConfig, LidarSpreadSection, load_config
from licalib_cli.pipeline.segments_model import union_config


@dataclass(frozen=True)
class _Found:
    """What ``union_config`` reads of a diagnosis."""

    effects_found: tuple[str, ...]
    config: CalibConfig | None = None


def _spread(cfg: CalibConfig, block: str, sigma: float) -> CalibConfig:
    spread = LidarSpreadSection().with_sigma(block, sigma)
    return cfg.model_copy(update={"model": cfg.model.model_copy(update={"lidar_spread": spread})})


def test_the_union_keeps_every_effect_once_in_the_order_first_kept() -> None:
    cfg = load_config(None, {"model.imu": ["accel_scale"], "model.lidar": ["elevation"]})
    found = [
        _Found(("gyro_scale", "lidar_range_offset")),
        _Found(()),
        _Found(("lidar_range_offset", "imu_clock_drift", "gyro_scale")),
    ]
    effects, out = union_config(cfg, found)  # type: ignore[arg-type]
    assert effects == ("gyro_scale", "lidar_range_offset", "imu_clock_drift")
    # the config's own model is replaced, not added to
    assert out.model.imu == ["gyro_scale", "clock_drift"]
    assert out.model.lidar == ["range_offset"]
    assert cfg.model.imu == ["accel_scale"]  # the input is not changed


def test_no_effect_anywhere_is_the_base_model() -> None:
    cfg = load_config(None, {"model.imu": ["gyro_scale"]})
    effects, out = union_config(cfg, [_Found(()), _Found(())])  # type: ignore[arg-type]
    assert effects == ()
    assert out.model.imu == [] and out.model.lidar == []


def test_a_spread_across_beams_comes_from_the_first_window_that_kept_it() -> None:
    cfg = load_config(None)
    first = _Found(("lidar_range_offset",), _spread(cfg, "range_offset", 0.002))
    second = _Found(("lidar_range_offset",), _spread(cfg, "range_offset", 0.005))
    plain = _Found(("lidar_elevation",), cfg)
    _, out = union_config(cfg, [plain, first, second])  # type: ignore[arg-type]
    assert out.model.lidar_spread.sigma_of("range_offset") == pytest.approx(0.002)
    assert out.model.lidar_spread.sigma_of("elevation") is None


def test_a_bias_walk_in_pieces_takes_the_shortest_pieces_any_window_chose() -> None:
    cfg = load_config(None)

    def pieces(piece_s: float | None) -> CalibConfig:
        return load_config(None, {"model.bias_walk_piece_s": piece_s} if piece_s else None)

    found = [
        _Found(("gyro_bias_walk",), pieces(5.0)),
        _Found(("gyro_bias_walk",), pieces(2.5)),
        _Found(("gyro_bias_walk",), pieces(None)),
    ]
    _, out = union_config(cfg, found)  # type: ignore[arg-type]
    assert out.model.imu == ["gyro_bias_walk"]
    assert out.model.bias_walk_piece_s == pytest.approx(2.5)
    _, linear = union_config(cfg, found[2:])  # type: ignore[arg-type]
    assert linear.model.bias_walk_piece_s is None
