"""Estimates no rig can have: the rounds settled in a wrong minimum, whatever the residuals say.

Residual checks judge how well the model explains the data; a wrong minimum can explain them
about as well, with the calibration and the IMU's own parameters bent to fit. Some of its
numbers give it away by being impossible for hardware:

* a lever arm beyond :data:`~licalib_cli.config.MAX_LEVER_ARM_M`;
* a rotation far from the trusted hand-eye rotation the rounds started from
  (:mod:`~licalib_cli.pipeline.start_agreement`);
* an IMU bias beyond any part's: :data:`MAX_ACCEL_BIAS_MS2`, :data:`MAX_GYRO_BIAS_RADS`. On a
  simulated Avia-like rosette whose initialisation went astray the fit ended 1.2 m and 9 deg off
  with an accelerometer bias of 4.3 m/s^2 (the simulated IMU had none), every residual check but
  the LiDAR's passing, and the sigmas a fifth of the error.

Each is a failure of the verdict, one sentence with the fix.
"""

from __future__ import annotations

import numpy as np

from licalib_cli.config import MAX_LEVER_ARM_M, CalibConfig
from licalib_cli.io.imu_units import GRAVITY
from licalib_cli.pipeline.initialise import InitialGuess
from licalib_cli.pipeline.schedule import Fit
from licalib_cli.pipeline.start_agreement import hand_eye_disagreement, trusted

__all__ = ["MAX_ACCEL_BIAS_MS2", "MAX_GYRO_BIAS_RADS", "implausible_estimates"]

MAX_ACCEL_BIAS_MS2 = 2.0
"""The largest accelerometer bias (any axis) an IMU has, m/s^2: about 0.2 g, where MEMS
datasheets give zero-g offsets of at most 0.08 g (the MPU-6050's z axis)."""

MAX_GYRO_BIAS_RADS = 0.5
"""The largest gyro bias (any axis) an IMU has, rad/s: about 29 deg/s, where MEMS datasheets give
zero-rate offsets of at most 20 deg/s (the MPU-6050)."""

_ADVICE = (
    "so the result is not trustworthy; give initialization.rotation_rpy_deg and "
    "translation_m near the rig's (a drawing is enough) and calibrate again."
)


def implausible_estimates(fit: Fit, guess: InitialGuess, cfg: CalibConfig) -> tuple[str, ...]:
    """One sentence per estimate no rig can have (see the module docstring); empty when none."""
    out = []
    lever = float(np.linalg.norm(fit.state.t_imu_lidar))
    if lever > MAX_LEVER_ARM_M:
        out.append(
            f"The estimated lever arm puts the LiDAR {lever:.3g} m from the IMU, farther than "
            f"any rig's ({MAX_LEVER_ARM_M:g} m): the rounds settled in a wrong minimum, {_ADVICE}"
        )
    if trusted(guess.hand_eye, cfg.initialization.max_hand_eye_residual_deg):
        assert guess.hand_eye is not None
        apart = hand_eye_disagreement(
            fit.state.R_imu_lidar, guess.hand_eye, "The estimated rotation"
        )
        if apart is not None:
            out.append(f"{apart}: the rounds settled in a wrong minimum, {_ADVICE}")
    accel = float(np.max(np.abs(fit.state.accel_bias)))
    if accel > MAX_ACCEL_BIAS_MS2:
        out.append(
            f"The estimated accelerometer bias reaches {accel:.2f} m/s^2 ({accel / GRAVITY:.2f} "
            f"g), more than any accelerometer's ({MAX_ACCEL_BIAS_MS2:g} m/s^2): the fit bent the "
            f"IMU to a wrong calibration, {_ADVICE}"
        )
    gyro = float(np.max(np.abs(fit.state.gyro_bias)))
    if gyro > MAX_GYRO_BIAS_RADS:
        out.append(
            f"The estimated gyro bias reaches {np.degrees(gyro):.1f} deg/s, more than any "
            f"gyro's ({np.degrees(MAX_GYRO_BIAS_RADS):.0f} deg/s): the fit bent the IMU to a "
            f"wrong calibration, {_ADVICE}"
        )
    return tuple(out)
