"""The result file's layout, pinned by a golden file (``pytest --update-golden`` rewrites it)."""

from __future__ import annotations

import numpy as np

from licalib_cli.models.intrinsics import ImuIntrinsics
from licalib_cli.pipeline.split import COORDINATES
from licalib_cli.results import CalibrationResult, Extrinsic, matrix_from_rpy_deg
from licalib_cli.sections import (
    Consistency,
    EffectCheck,
    FitSection,
    InitializationSection,
    Observability,
    PatternCheck,
    Provenance,
    RecordingSection,
    SensorCheck,
    SplitHalf,
    Uncertainty,
    UncheckedPriorCheck,
    VerdictSection,
)


def _result() -> CalibrationResult:
    return CalibrationResult(
        extrinsic=Extrinsic(
            matrix_from_rpy_deg([1.0, 2.0, 5.0]), np.array([0.3, 0.15, 0.05]), 0.005
        ),
        imu_intrinsics=ImuIntrinsics(gyro_bias=np.array([1e-4, -2e-4, 3e-4])),
        gravity_G=(0.0, -3.82, -9.035),
        uncertainty=Uncertainty((0.001, 0.0007, 0.0002), (0.0037, 0.0032, 0.0048), 6.4e-5),
        observability=Observability(
            "translation 0.01 m, rotation 0.001 rad, time offset 0.001 s",
            1.0,
            (512.3, 88.1, 7.25),
            (),
        ),
        verdict=VerdictSection("pass"),
        consistency=Consistency(
            sensors=(
                SensorCheck(
                    "gyro",
                    "rad/s",
                    (0.0035, 0.0035, 0.0035),
                    "config",
                    0.877,
                    0.0033,
                    12003,
                    "ok",
                    (PatternCheck("angular rate", 0.0014, 0.06, 0.00012),),
                ),
            ),
            effects=(
                EffectCheck(
                    "gyro_scale", "imu", 5.2, 3, 0.16, (1e-4, 0.0, 0.0), (0.001, 0.0, 0.0), 0.0
                ),
            ),
            split_half=SplitHalf(
                "agree",
                halves_s=5.0,
                max_z=1.3,
                chi2=3.1,
                dof=7,
                p_value=0.87,
                difference_translation_m=(0.0001, 0.0, 0.0),
                difference_rotation_deg=(0.001, 0.0, 0.0),
                difference_time_offset_s=1e-5,
                compared=COORDINATES,
            ),
            inflation=(),
            unchecked_priors=(
                UncheckedPriorCheck(
                    name="accel_misalignment",
                    unit="deg",
                    prior=0.0573,
                    detectable=0.19,
                    coordinate="roll",
                    hidden_shift_sigmas=4.43,
                    warns=True,
                ),
            ),
        ),
        initialization=InitializationSection(
            "hand-eye",
            "cross-correlation",
            0.0073,
            0.9999,
            0.00827,
            "odometry + accelerometer",
            (0.279, 0.159, 0.051),
        ),
        fit=FitSection(5, True, 0.0004, 0.0007, 7e-6, 57376, 498, 0.008, 0.89),
        recording=RecordingSection(
            "bag.bag",
            "/imu/data",
            "/points_raw",
            4001,
            100,
            10.0,
            1700000000000000000,
            -0.000012345,
            -1000000.25,
            imu_frame="imu_link",
            lidar_frame="velodyne",
            gravity_turn_deg=27.365,
            clock_rate_ppm=-12.5,
            clock_rate_sigma_ppm=0.8,
        ),
        provenance=Provenance(
            "0.1.0", "0123456789abcdef", "2026-11-24T07:00:00Z", "fedcba9876543210"
        ),
    )


def test_result_yaml_matches_the_golden_file(golden) -> None:
    golden("result_v1.yaml", _result().to_yaml())


def test_every_typed_section_round_trips() -> None:
    r = _result()
    back = CalibrationResult.from_dict(r.to_dict())
    for name in (
        "uncertainty",
        "observability",
        "verdict",
        "consistency",
        "initialization",
        "fit",
        "recording",
        "provenance",
    ):
        assert getattr(back, name) == getattr(r, name), name
    assert back.gravity_G == r.gravity_G
    assert back.recording is not None and back.recording.lidar_clock_shift_s == -1000000.25
