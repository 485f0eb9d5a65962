"""The IMU clock's rate against the LiDAR's from the bag alone: each topic's header stamps
against the recorder's record times (``licalib_cli.io.clock_rate``), told before any fit by
``info`` and the reader, and kept in the result's recording section."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.config import load_config
from licalib_cli.errors import ConfigError
from licalib_cli.inspection import inspect_bag
from licalib_cli.io.clock_rate import (
    MATERIAL_MOVE_S,
    ClockRate,
    clock_rate,
    stamp_rate,
)
from licalib_cli.io.reader import read_segment
from licalib_cli.pipeline.assemble import recording_section
from licalib_cli.pipeline.checks import drift_against_stamps
from licalib_cli.simulation import SimulationSpec, simulate

NS = 1_000_000_000


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261204)


def _topic(
    rng: np.random.Generator, rate_hz: float, seconds: float, clock_ppm: float, host_ppm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Stamps on a sensor clock running ``clock_ppm`` fast and record times on a recorder
    clock running ``host_ppm`` fast, with transport delays (a few ms, some long queues)."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    stamps = 5 * NS + np.round(t * (1.0 + 1e-6 * clock_ppm) * NS).astype(np.int64)
    delay = rng.exponential(2e-3, t.size) + np.where(rng.random(t.size) < 0.02, 0.05, 0.0)
    records = 9 * NS + np.round((t + delay) * (1.0 + 1e-6 * host_ppm) * NS).astype(np.int64)
    return stamps, records


def test_a_topics_clock_rate_is_found_under_varying_delays(rng: np.random.Generator) -> None:
    stamps, records = _topic(rng, 400.0, 20.0, 250.0, 0.0)
    found = stamp_rate(stamps, records, (int(records.min()), int(records.max())))
    assert found is not None
    rate, sigma = found
    assert 0.0 < sigma < 4e-6
    assert abs(rate - 250e-6) < 3 * sigma + 1e-6


def test_the_recorders_own_rate_cancels_between_the_topics(rng: np.random.Generator) -> None:
    """The recorder running 80 ppm slow moves both topics' ``stamp - record`` alike: the
    difference is the IMU clock's rate against the LiDAR's alone (a 10 Hz LiDAR's few clouds
    limit the precision to about 8 ppm over 30 s)."""
    imu = _topic(rng, 200.0, 30.0, 90.0, -80.0)
    lidar = _topic(rng, 10.0, 30.0, -10.0, -80.0)
    rate = clock_rate(*imu, *lidar)
    assert rate is not None
    assert abs(rate.rate - 100e-6) < 3 * rate.sigma + 1e-6
    assert rate.sigma < 15e-6
    assert rate.span_s == pytest.approx(30.0, abs=0.2)
    assert rate.material  # 100 ppm over 30 s: 3 ms
    assert rate.moves_s == pytest.approx(abs(rate.rate) * rate.span_s)


def test_too_few_messages_or_copied_record_times_give_no_rate() -> None:
    stamps = np.arange(5, dtype=np.int64) * NS
    assert stamp_rate(stamps, stamps, (0, 4 * NS)) is None
    assert clock_rate(stamps, stamps, [], []) is None
    # a bag rewritten with each message's stamp as its record time: nothing to measure (one
    # topic recorded at its stamps, as the simulator's IMU, still measures)
    imu = np.arange(400, dtype=np.int64) * (NS // 40)
    lidar = np.arange(100, dtype=np.int64) * (NS // 10)
    assert clock_rate(imu, imu, lidar, lidar) is None
    rate = clock_rate(imu, imu, lidar, lidar + NS // 10)
    assert rate is not None and rate.rate == 0.0 and not rate.material


def test_a_rate_is_told_only_when_significant_and_material() -> None:
    span = 10.0
    small = ClockRate(rate=0.5 * MATERIAL_MOVE_S / span, sigma=1e-9, span_s=span)
    noisy = ClockRate(rate=50e-6, sigma=20e-6, span_s=span)
    told = ClockRate(rate=-50e-6, sigma=1e-6, span_s=span)
    assert not small.material and not noisy.material and told.material
    assert "-50.0 +/- 1.0 ppm" in told.text(False) and "0.50 ms" in told.text(False)
    assert "Add clock_drift to model.imu" in told.text(False)
    assert "the model estimates it" in told.text(True) and "as its prior" in told.text(True)


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("clock_rate")
    out = {}
    for name, ppm, delay_ms in (("drift", 200.0, 0.0), ("clean", 0.0, 0.0), ("late", 300.0, 0.2)):
        spec = SimulationSpec(
            duration_s=6.0 if delay_ms else 4.0,
            seed=3,
            imu_clock_drift_ppm=ppm,
            record_delay_ms=delay_ms,
        )
        out[name] = simulate(spec, root / name, force=True).bag_path
    return out


def test_transport_delays_leave_the_rate_within_its_sigma(bags: dict[str, Path]) -> None:
    """``simulate --record-delay-ms``: record times late by exponential delays (0.2 ms mean),
    in order per topic; the rate is still found, within its sigma, and told."""
    rec = read_segment(bags["late"], load_config(None, {}))
    rate = rec.clock_rate
    assert rate is not None and 0.0 < rate.sigma < 30e-6
    assert abs(rate.rate - 300e-6) < 3 * rate.sigma + 1e-6
    assert rate.material and any("ppm against the LiDAR's" in w for w in rec.warnings)
    truth = yaml.safe_load((bags["late"].parent / "truth.yaml").read_text())
    assert truth["simulation"]["clock"]["record_delay_ms"] == 0.2


def test_the_reader_tells_a_drifting_imu_clock_and_the_result_keeps_it(
    bags: dict[str, Path],
) -> None:
    rec = read_segment(bags["drift"], load_config(None, {}))
    assert rec.clock_rate is not None
    assert rec.clock_rate.rate == pytest.approx(200e-6, abs=1e-6)
    (told,) = [w for w in rec.warnings if "ppm against the LiDAR's" in w]
    assert "+200.0" in told and "Add clock_drift to model.imu" in told
    section = recording_section(bags["drift"], rec)
    assert section.clock_rate_ppm == pytest.approx(200.0, abs=1.0)
    assert section.clock_rate_sigma_ppm is not None
    # with the drift in the model the sentence says it is estimated
    cfg = load_config(None, {"model": {"imu": ["clock_drift"]}})
    again = read_segment(bags["drift"], cfg)
    assert any("the model estimates it" in w for w in again.warnings)


def test_a_steady_clock_is_measured_and_not_told(bags: dict[str, Path]) -> None:
    rec = read_segment(bags["clean"], load_config(None, {}))
    assert rec.clock_rate is not None and abs(rec.clock_rate.rate) < 1e-6
    assert not any("ppm against the LiDAR's" in w for w in rec.warnings)


def test_info_reports_the_clock_rate(bags: dict[str, Path]) -> None:
    report = inspect_bag(bags["drift"], load_config(None, {}))
    d = report.to_dict()
    assert d["clock_rate_ppm"] == pytest.approx(200.0, abs=1.0)
    assert d["clock_rate_sigma_ppm"] is not None
    assert any("ppm against the LiDAR's" in p["message"] for p in d["problems"])
    assert all(p["severity"] == "warning" for p in d["problems"])
    assert report.usable


def test_an_estimated_drift_that_differs_from_the_stamps_rate_is_said() -> None:
    """The fit's clock drift and the stamps' rate measure the same relation: a difference
    beyond five combined sigmas that moves the offset by 0.1 ms or more over the segment says
    the drift stands in for something else."""
    stamps = ClockRate(rate=250e-6, sigma=2e-6, span_s=20.0)
    assert drift_against_stamps(251.9e-6, 1.2e-6, stamps) is None  # 3428: 0.8 sigmas
    said = drift_against_stamps(300e-6, 1.2e-6, stamps)
    assert said is not None and "+300.0 +/- 1.2 ppm" in said and "21 sigmas" in said
    # beyond its sigmas but moving the offset by under 0.1 ms over the segment
    exact = ClockRate(rate=250e-6, sigma=0.1e-6, span_s=20.0)
    assert drift_against_stamps(254e-6, 0.1e-6, exact) is None  # 28 sigmas, 0.08 ms
    assert drift_against_stamps(256e-6, 0.1e-6, exact) is not None  # 0.12 ms
    # a drift the data did not determine
    assert drift_against_stamps(300e-6, float("inf"), stamps) is None


@pytest.mark.parametrize("delay_ms", [-1.0, 50.0])
def test_a_record_delay_outside_its_range_is_refused(delay_ms: float) -> None:
    with pytest.raises(ConfigError, match="--record-delay-ms"):
        SimulationSpec(record_delay_ms=delay_ms)
