"""Test factory: a step of the model selection (``DiagnosisStep``) with neutral defaults."""

from __future__ import annotations

from typing import Any

from licalib_cli.pipeline.diagnosis_step import DiagnosisStep, Gap


def diagnosis_step(**overrides: Any) -> DiagnosisStep:
    """A per-beam range scale tried on a LiDAR gap of 1.02 (noise 0.008) that did not pay
    (BIC +600 on 64 degrees of freedom, ``ln n`` 12), the extrinsic moved 0.8 mm / 0.004 deg /
    0.02 ms; any field can be given instead."""
    gap = Gap("lidar", 1.02, 1.0, 0.008)
    values: dict[str, Any] = {
        "effect": "lidar_range_scale",
        "statistic": 192.5,
        "dof": 64,
        "p_value": 9e-15,
        "delta_bic": 600.0,
        "kept": False,
        "estimate": {f"lidar.intrinsics[{i}].s": (1.0, 1e-4) for i in range(64)},
        "gap_before": gap,
        "gap_after": gap,
        "moved_translation_m": 8e-4,
        "moved_rotation_deg": 0.004,
        "moved_time_offset_s": 2e-5,
        "bic_log_n": 12.0,
    }
    values.update(overrides)
    return DiagnosisStep(**values)
