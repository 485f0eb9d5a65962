"""Whether the fit ended where an independent measurement of its start says it can be.

The rounds refine the initial guess; far from it they can settle in a wrong minimum whose
residuals look like a right one's: a VLP-16 sinusoid started 90 degrees off in yaw ended 99.8 deg
and 3.7 m off with every residual check passing and the two halves agreeing, only the map's
planar fraction low. Hand-eye on the LiDAR-only odometry measures the rotation to about a degree
without the rounds; an estimate that ends tens of degrees from a trusted hand-eye rotation came
from a wrong minimum, whatever its residuals say.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry import so3
from licalib_cli.initialization.rotation import HandEyeRotation
from licalib_cli.results import rpy_deg_from_matrix

__all__ = ["ROTATION_TOLERANCE_DEG", "hand_eye_disagreement", "trusted"]

F64 = npt.NDArray[np.float64]

ROTATION_TOLERANCE_DEG = 10.0
"""The farthest a rotation may lie from a trusted hand-eye rotation: hand-eye is about a degree
off on motion it trusts, a guess from a drawing a few degrees; an axis swapped or turned is
tens."""


def trusted(hand_eye: HandEyeRotation | None, max_residual_deg: float) -> bool:
    """Whether hand-eye measured the rotation: it ran, and its residual is within
    ``max_residual_deg`` (``initialization.max_hand_eye_residual_deg``)."""
    return hand_eye is not None and hand_eye.residual_rms_deg <= max_residual_deg


def hand_eye_disagreement(rotation: F64, hand_eye: HandEyeRotation, what: str) -> str | None:
    """A sentence when ``rotation`` (R_imu_lidar) lies more than :data:`ROTATION_TOLERANCE_DEG`
    from hand-eye's, beginning with ``what`` (the rotation's name); else None."""
    apart = float(np.degrees(np.linalg.norm(so3.log(rotation.T @ hand_eye.R_imu_lidar))))
    if apart <= ROTATION_TOLERANCE_DEG:
        return None
    shown = ", ".join(f"{v:.1f}" for v in rpy_deg_from_matrix(hand_eye.R_imu_lidar))
    return (
        f"{what} lies {apart:.1f} deg from the rotation the LiDAR odometry and the gyro show "
        f"(hand-eye: [{shown}] deg, residual {hand_eye.residual_rms_deg:.2f} deg)"
    )
