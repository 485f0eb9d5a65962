"""Findings on each sensor's residuals: too large for their noise warns; far below a configured
noise is a note that the config states the sensor noisier than it is (sigmas too wide)."""

from __future__ import annotations

from licalib_cli.pipeline.checks import _sensors, judge
from licalib_cli.pipeline.fitcheck import CHI2_EXCESS, CHI2_QUIET
from licalib_cli.sections import SensorCheck


def _gyro(chi2: float, source: str = "config", noise: float = 0.007) -> SensorCheck:
    return SensorCheck(
        sensor="gyro",
        unit="rad/s",
        noise=(noise, noise, noise),
        noise_source=source,
        chi2_per_sample=chi2,
        rms=noise * chi2**0.5,
        samples=24_000,
        status="excess" if chi2 > CHI2_EXCESS else "ok",
    )


def test_a_configured_noise_far_above_the_residuals_is_a_note_naming_its_key() -> None:
    # the gyro noise configured at twice the simulator's: chi-square 0.22 per sample
    (note,) = _sensors((_gyro(0.22),))
    assert note.severity == "note"
    assert "noise.gyro_noise_density" in note.text
    assert "0.47 of their noise" in note.text and "wider than the data support" in note.text
    verdict, status = judge([note])
    assert verdict.status == "pass" and verdict.reasons == () and status == "ok"


def test_no_note_for_a_fit_that_explains_the_data_or_a_measured_noise() -> None:
    assert _sensors((_gyro(0.88),)) == []  # what a fit that explains the data leaves
    assert _sensors((_gyro(CHI2_QUIET),)) == []  # at the limit
    # a noise measured from the data is what the data show, whatever the chi-square
    assert _sensors((_gyro(0.22, source="data"),)) == []


def test_a_configured_noise_below_the_residuals_warns() -> None:
    (warn,) = _sensors((_gyro(2.0),))
    assert warn.severity == "warn"
    assert not warn.information  # about the fit: a joint over segments keeps it
    assert "check noise.gyro_noise_density in the config" in warn.text


def test_the_lidar_note_gives_millimetres() -> None:
    lidar = SensorCheck(
        sensor="lidar",
        unit="m",
        noise=(0.02,),
        noise_source="config",
        chi2_per_sample=0.25,
        rms=0.01,
        samples=90_000,
        status="ok",
    )
    (note,) = _sensors((lidar,))
    assert "RMS 10.0 mm against 20.0 mm" in note.text
    assert "noise.range_sigma_m" in note.text
