"""Intrinsic parameter sets of the IMU and LiDAR models (the models are in :mod:`.imu` and
:mod:`.lidar`).

IMU model (method.md section 3)::

    w_m = S_w M_w R_wI w_I + A_w a_I + b_w
    a_m = S_a M_a a_I + b_a

``S`` diagonal scale, ``M`` upper-unit-triangular misalignment ``[[1, m0, m1], [0, 1, m2],
[0, 0, 1]]``, ``R_wI`` rotates IMU-frame vectors into the gyro frame, ``A_w`` g-sensitivity.

LiDAR model (method.md section 4), per beam ``i`` with nominal elevation ``phi_i``::

    rho_bar = s_i rho + drho_i,  phi_bar = phi_i + dphi_i,  theta_bar = theta + dtheta_i
    p_L = [rho_bar cos(phi_bar) cos(theta_bar) + H_i sin(theta_bar),
           rho_bar cos(phi_bar) sin(theta_bar) - H_i cos(theta_bar),
           rho_bar sin(phi_bar) + V_i]

A driver publishes the *nominal* conversion ``rho [cos phi_i cos theta, cos phi_i sin theta,
sin phi_i]`` of the raw range ``rho`` and azimuth ``theta``
(:func:`licalib_cli.models.lidar.nominal_point`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


def _ones3() -> F64:
    return np.ones(3)


def _zeros3() -> F64:
    return np.zeros(3)


def misalignment_matrix(m: F64) -> F64:
    """Upper-unit-triangular ``M`` from its three off-diagonal entries ``[m0, m1, m2]``."""
    out = np.eye(3)
    out[0, 1], out[0, 2], out[1, 2] = m
    return out


@dataclass(frozen=True)
class ImuIntrinsics:
    """IMU intrinsics and biases; identity/zero by default.

    Attributes:
        gyro_scale: (3,) diagonal of ``S_w``.
        gyro_misalignment: (3,) ``[m0, m1, m2]`` of ``M_w``.
        gyro_rotation: (4,) quaternion ``[x, y, z, w]`` of ``R_wI`` (IMU frame -> gyro frame).
        accel_scale: (3,) diagonal of ``S_a``.
        accel_misalignment: (3,) off-diagonal entries of ``M_a``.
        gyro_g_sensitivity: (3, 3) ``A_w``, rad/s per m/s^2.
        gyro_bias: (3,) rad/s.
        accel_bias: (3,) m/s^2.
    """

    gyro_scale: F64 = field(default_factory=_ones3)
    gyro_misalignment: F64 = field(default_factory=_zeros3)
    gyro_rotation: F64 = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    accel_scale: F64 = field(default_factory=_ones3)
    accel_misalignment: F64 = field(default_factory=_zeros3)
    gyro_g_sensitivity: F64 = field(default_factory=lambda: np.zeros((3, 3)))
    gyro_bias: F64 = field(default_factory=_zeros3)
    accel_bias: F64 = field(default_factory=_zeros3)

    def with_(self, **changes: F64) -> ImuIntrinsics:
        """Copy with some fields replaced."""
        return replace(self, **changes)


@dataclass(frozen=True)
class LidarIntrinsics:
    """Per-beam LiDAR intrinsics (method.md section 4); all arrays (B,).

    Attributes:
        nominal_elevation: ``phi_i``, rad (not estimated).
        elevation_correction: ``dphi_i``, rad.
        azimuth_correction: ``dtheta_i``, rad.
        vertical_offset: ``V_i``, m.
        horizontal_offset: ``H_i``, m.
        range_scale: ``s_i``.
        range_offset: ``drho_i``, m.
    """

    nominal_elevation: F64
    elevation_correction: F64
    azimuth_correction: F64
    vertical_offset: F64
    horizontal_offset: F64
    range_scale: F64
    range_offset: F64

    @classmethod
    def nominal(cls, nominal_elevation: npt.ArrayLike) -> LidarIntrinsics:
        """Ideal beams at the given elevations (rad)."""
        phi = np.asarray(nominal_elevation, dtype=np.float64)
        z = np.zeros_like(phi)
        return cls(phi, z, z.copy(), z.copy(), z.copy(), np.ones_like(phi), z.copy())

    @property
    def num_beams(self) -> int:
        """Number of beams (rings) ``B``, the length of every per-beam array.

        Beam ``i`` is the ring index of the driver's points; ``nominal_elevation[i]`` is its
        elevation ``phi_i``.
        """
        return int(self.nominal_elevation.shape[0])

    def with_(self, **changes: F64) -> LidarIntrinsics:
        """Copy with some fields replaced."""
        return replace(self, **changes)
