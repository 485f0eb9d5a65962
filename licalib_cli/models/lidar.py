"""Per-beam LiDAR point model with analytic Jacobians (method.md section 4).

Conventions:

* A raw measurement is ``(beam i, range rho (m), azimuth theta (rad))``; the point in the LiDAR
  frame ``{L}`` is (see :func:`licalib_cli.models.intrinsics.lidar_point`)::

      rho_bar = s_i rho + drho_i,  phi_bar = phi_i + dphi_i,  theta_bar = theta + dtheta_i
      p_L = [rho_bar cos(phi_bar) cos(theta_bar) + H_i sin(theta_bar),
             rho_bar cos(phi_bar) sin(theta_bar) - H_i cos(theta_bar),
             rho_bar sin(phi_bar) + V_i]

* The six estimated intrinsics of a beam are stored as one row, in the order
  :data:`INTRINSIC_NAMES` = ``[dphi (rad), dtheta (rad), V (m), H (m), s (-), drho (m)]``; the
  columns are named by :class:`BeamIntrinsic`. The nominal elevation ``phi_i`` is not estimated.
* :func:`lidar_point_terms` is the one forward model; :func:`lidar_point` applies it to a
  :class:`~licalib_cli.models.intrinsics.LidarIntrinsics`, and :func:`nominal_point` is what a
  driver publishes (the model with nominal intrinsics).
* Point-to-plane geometry (:func:`point_to_plane`): a point ``p_L`` seen at IMU time ``t`` maps to
  ``p_G = R(t) (R_IL p_L + t_IL) + p(t)`` with ``R(t) = R_G_I(t)``, ``p(t) = G p_I(t)`` and
  ``T_imu_lidar = (R_IL, t_IL)``; its signed distance to the plane ``n^T x + d = 0`` (``{G}``,
  unit ``n``) is ``n^T p_G + d``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry.vectors import cross_rows
from licalib_cli.models.intrinsics import LidarIntrinsics

__all__ = [
    "GAUGE_COLUMNS",
    "INTRINSIC_NAMES",
    "NUM_BEAM_INTRINSICS",
    "BeamIntrinsic",
    "LidarPointTerms",
    "PointToPlaneGeometry",
    "intrinsics_from_array",
    "intrinsics_to_array",
    "lidar_point",
    "lidar_point_terms",
    "lidar_point_with_jacobian",
    "nominal_intrinsics_array",
    "nominal_point",
    "point_to_plane",
    "raw_from_nominal",
]

F64 = npt.NDArray[np.float64]


class BeamIntrinsic(IntEnum):
    """Column of a beam's intrinsics in the ``(B, 6)`` array."""

    ELEVATION = 0
    """``dphi``, elevation correction, rad."""
    AZIMUTH = 1
    """``dtheta``, azimuth correction, rad."""
    VERTICAL_OFFSET = 2
    """``V``, m."""
    HORIZONTAL_OFFSET = 3
    """``H``, m (perpendicular to the beam)."""
    RANGE_SCALE = 4
    """``s`` (nominal 1)."""
    RANGE_OFFSET = 5
    """``drho``, m."""


_E = BeamIntrinsic

#: Names of the per-beam intrinsic coordinates, in storage order.
INTRINSIC_NAMES: tuple[str, ...] = ("dphi", "dtheta", "V", "H", "s", "drho")
NUM_BEAM_INTRINSICS = len(BeamIntrinsic)

GAUGE_COLUMNS: tuple[BeamIntrinsic, ...] = (
    _E.ELEVATION,
    _E.AZIMUTH,
    _E.VERTICAL_OFFSET,
    _E.HORIZONTAL_OFFSET,
)
"""The intrinsics the gauge beam keeps (only its range scale and offset are free)."""


def nominal_intrinsics_array(num_beams: int) -> F64:
    """(B, 6) intrinsics of ideal beams: zero corrections and offsets, unit range scale."""
    out = np.zeros((num_beams, NUM_BEAM_INTRINSICS))
    out[:, _E.RANGE_SCALE] = 1.0
    return out


def intrinsics_to_array(intrinsics: LidarIntrinsics) -> F64:
    """Per-beam intrinsics as a (B, 6) array ``[dphi, dtheta, V, H, s, drho]``."""
    k = intrinsics
    return np.stack(
        [
            k.elevation_correction,
            k.azimuth_correction,
            k.vertical_offset,
            k.horizontal_offset,
            k.range_scale,
            k.range_offset,
        ],
        axis=-1,
    ).astype(np.float64)


def intrinsics_from_array(
    nominal_elevation: npt.ArrayLike, values: npt.ArrayLike
) -> LidarIntrinsics:
    """Inverse of :func:`intrinsics_to_array`.

    Args:
        nominal_elevation: (B,) nominal beam elevations ``phi_i``, rad.
        values: (B, 6) ``[dphi, dtheta, V, H, s, drho]`` per beam.

    Returns:
        The intrinsics (arrays are copies).
    """
    phi = np.array(nominal_elevation, dtype=np.float64)
    v = np.array(values, dtype=np.float64).reshape(phi.shape[0], NUM_BEAM_INTRINSICS)
    return LidarIntrinsics(
        nominal_elevation=phi,
        elevation_correction=v[:, _E.ELEVATION].copy(),
        azimuth_correction=v[:, _E.AZIMUTH].copy(),
        vertical_offset=v[:, _E.VERTICAL_OFFSET].copy(),
        horizontal_offset=v[:, _E.HORIZONTAL_OFFSET].copy(),
        range_scale=v[:, _E.RANGE_SCALE].copy(),
        range_offset=v[:, _E.RANGE_OFFSET].copy(),
    )


@dataclass(frozen=True)
class LidarPointTerms:
    """Points in ``{L}`` with the intermediate terms of the model, for cheap derivatives.

    Attributes:
        point: (N, 3) ``p_L``, m.
        rho: (N,) raw range, m.
        rho_bar: (N,) corrected range ``s rho + drho``, m.
        cos_phi: (N,) ``cos(phi_bar)``.
        sin_phi: (N,) ``sin(phi_bar)``.
        cos_theta: (N,) ``cos(theta_bar)``.
        sin_theta: (N,) ``sin(theta_bar)``.
    """

    point: F64
    rho: F64
    rho_bar: F64
    cos_phi: F64
    sin_phi: F64
    cos_theta: F64
    sin_theta: F64

    def rows(self, sl: slice) -> LidarPointTerms:
        """The terms of the points ``sl`` (views)."""
        return LidarPointTerms(
            self.point[sl],
            self.rho[sl],
            self.rho_bar[sl],
            self.cos_phi[sl],
            self.sin_phi[sl],
            self.cos_theta[sl],
            self.sin_theta[sl],
        )

    def jacobian(self) -> F64:
        """(N, 3, 6) ``d p_L / d [dphi, dtheta, V, H, s, drho]`` of each point's beam."""
        rb, cp, sp, ct, st = (
            self.rho_bar,
            self.cos_phi,
            self.sin_phi,
            self.cos_theta,
            self.sin_theta,
        )
        ux, uy = cp * ct, cp * st
        n = rb.shape[0]
        jac = np.zeros((n, 3, NUM_BEAM_INTRINSICS))
        jac[:, 0, _E.ELEVATION] = -rb * sp * ct
        jac[:, 1, _E.ELEVATION] = -rb * sp * st
        jac[:, 2, _E.ELEVATION] = rb * cp
        # the offset term turns with the azimuth too
        jac[:, 0, _E.AZIMUTH] = -self.point[:, 1]
        jac[:, 1, _E.AZIMUTH] = self.point[:, 0]
        jac[:, 2, _E.VERTICAL_OFFSET] = 1.0
        jac[:, 0, _E.HORIZONTAL_OFFSET] = st
        jac[:, 1, _E.HORIZONTAL_OFFSET] = -ct
        jac[:, 0, _E.RANGE_SCALE] = self.rho * ux
        jac[:, 1, _E.RANGE_SCALE] = self.rho * uy
        jac[:, 2, _E.RANGE_SCALE] = self.rho * sp
        jac[:, 0, _E.RANGE_OFFSET] = ux
        jac[:, 1, _E.RANGE_OFFSET] = uy
        jac[:, 2, _E.RANGE_OFFSET] = sp
        return jac

    def vjp(self, v: F64, range_shift: F64 | None = None, range_scale: F64 | None = None) -> F64:
        """(N, 6) ``v_k^T d p_L / d intrinsics`` for (N, 3) row vectors ``v`` (no (N, 3, 6)).

        Args:
            v: (N, 3) row vectors.
            range_shift: (N,) metres added to each corrected range ``rho_bar`` before the
                derivatives are taken (the derivative at another range along the same ray); None
                for the derivative at the measured range.
            range_scale: (N,) range scale ``s_i`` of each point's beam, which turns the shift
                into raw range for the range-scale column; needed with ``range_shift``.
        """
        vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
        cp, sp, ct, st = self.cos_phi, self.sin_phi, self.cos_theta, self.sin_theta
        horizontal = vx * ct + vy * st
        along = cp * horizontal + sp * vz  # v . u
        rho_bar, rho, px, py = self.rho_bar, self.rho, self.point[:, 0], self.point[:, 1]
        if range_shift is not None:
            if range_scale is None:
                msg = "a range shift needs the beams' range scales"
                raise ValueError(msg)
            rho_bar = rho_bar + range_shift
            rho = rho + range_shift / range_scale
            px = px + range_shift * cp * ct
            py = py + range_shift * cp * st
        out = np.empty((v.shape[0], NUM_BEAM_INTRINSICS))
        out[:, _E.ELEVATION] = rho_bar * (cp * vz - sp * horizontal)
        out[:, _E.AZIMUTH] = vy * px - vx * py
        out[:, _E.VERTICAL_OFFSET] = vz
        out[:, _E.HORIZONTAL_OFFSET] = vx * st - vy * ct
        out[:, _E.RANGE_SCALE] = rho * along
        out[:, _E.RANGE_OFFSET] = along
        return out


def lidar_point_terms(
    nominal_elevation: F64,
    values: F64,
    beam: npt.NDArray[np.integer],
    rho: F64,
    theta: F64,
    cos_sin_theta: tuple[F64, F64] | None = None,
) -> LidarPointTerms:
    """Points in ``{L}`` from raw measurements, keeping the terms needed for derivatives.

    Trigonometric functions of the elevation are evaluated once per beam.

    Args:
        nominal_elevation: (B,) nominal elevations ``phi_i``, rad.
        values: (B, 6) intrinsics ``[dphi, dtheta, V, H, s, drho]``.
        beam: (N,) beam index of each point.
        rho: (N,) raw range, m.
        theta: (N,) raw azimuth, rad.
        cos_sin_theta: precomputed ``(cos(theta), sin(theta))`` of the raw azimuths; the
            azimuth corrections are then applied with the angle-addition formulas.

    Returns:
        :class:`LidarPointTerms`.
    """
    phi_bar = nominal_elevation + values[:, _E.ELEVATION]
    cos_phi = np.cos(phi_bar)[beam]
    sin_phi = np.sin(phi_bar)[beam]
    if cos_sin_theta is None:
        theta_bar = theta + values[beam, _E.AZIMUTH]
        c_th, s_th = np.cos(theta_bar), np.sin(theta_bar)
    else:
        c0, s0 = cos_sin_theta
        d_theta = values[:, _E.AZIMUTH]
        c_d, s_d = np.cos(d_theta)[beam], np.sin(d_theta)[beam]
        c_th = c0 * c_d - s0 * s_d
        s_th = s0 * c_d + c0 * s_d
    rho_bar = values[beam, _E.RANGE_SCALE] * rho + values[beam, _E.RANGE_OFFSET]
    h = values[beam, _E.HORIZONTAL_OFFSET]
    n = rho.shape[0]
    horizontal = rho_bar * cos_phi
    p = np.empty((n, 3))
    p[:, 0] = horizontal * c_th + h * s_th
    p[:, 1] = horizontal * s_th - h * c_th
    p[:, 2] = rho_bar * sin_phi + values[beam, _E.VERTICAL_OFFSET]
    return LidarPointTerms(p, rho, rho_bar, cos_phi, sin_phi, c_th, s_th)


def lidar_point(
    intrinsics: LidarIntrinsics, beam: npt.NDArray[np.integer], rho: F64, theta: F64
) -> F64:
    """Point in the LiDAR frame from raw (beam, range, azimuth) with the full model.

    Args:
        intrinsics: per-beam parameters.
        beam: (N,) beam index.
        rho: (N,) raw range, m.
        theta: (N,) raw azimuth, rad.

    Returns:
        (N, 3) points in the LiDAR frame, m (:func:`lidar_point_terms`).
    """
    values = intrinsics_to_array(intrinsics)
    return lidar_point_terms(intrinsics.nominal_elevation, values, beam, rho, theta).point


def nominal_point(rho: F64, theta: F64, phi: F64) -> F64:
    """The driver's nominal conversion of raw range/azimuth at elevation ``phi`` -> (N, 3).

    This is the model with nominal intrinsics (:func:`lidar_point` of
    ``LidarIntrinsics.nominal``), written for a per-point elevation.
    """
    c_phi = np.cos(phi)
    return np.stack(
        [rho * c_phi * np.cos(theta), rho * c_phi * np.sin(theta), rho * np.sin(phi)], axis=-1
    )


def raw_from_nominal(xyz: F64) -> tuple[F64, F64]:
    """Raw range and azimuth ``(rho, theta)`` of nominally converted points (N, 3)."""
    return np.linalg.norm(xyz, axis=-1), np.arctan2(xyz[:, 1], xyz[:, 0])


def lidar_point_with_jacobian(
    nominal_elevation: F64,
    values: F64,
    beam: npt.NDArray[np.integer],
    rho: F64,
    theta: F64,
    jacobian: bool = True,
) -> tuple[F64, F64 | None]:
    """Points in ``{L}`` from raw measurements, and their derivatives w.r.t. the beam intrinsics.

    Args:
        nominal_elevation: (B,) nominal elevations ``phi_i``, rad.
        values: (B, 6) intrinsics ``[dphi, dtheta, V, H, s, drho]``.
        beam: (N,) beam index of each point.
        rho: (N,) raw range, m.
        theta: (N,) raw azimuth, rad.
        jacobian: also return the Jacobian.

    Returns:
        ``(p_L (N, 3) m, J (N, 3, 6) or None)`` with ``J[k, :, j] = d p_L / d values[beam_k, j]``.
    """
    terms = lidar_point_terms(nominal_elevation, values, beam, rho, theta)
    return terms.point, (terms.jacobian() if jacobian else None)


@dataclass(frozen=True)
class PointToPlaneGeometry:
    """Signed point-to-plane distances and their derivatives (not whitened).

    Attributes:
        distance: (N,) ``n^T p_G + d``, m.
        p_imu: (N, 3) points in the IMU frame ``R_IL p_L + t_IL``, m.
        d_rotation: (N, 3) derivative w.r.t. a right perturbation ``R(t) Exp(eps)``, m/rad.
        d_position: (N, 3) derivative w.r.t. ``p(t)`` (equals ``n``).
        d_ext_rotation: (N, 3) derivative w.r.t. a right perturbation ``R_IL Exp(delta)``, m/rad.
        d_ext_translation: (N, 3) derivative w.r.t. ``t_IL`` (``R^T n``).
        d_point: (N, 3) derivative w.r.t. ``p_L`` (``R_IL^T R^T n``).
        d_time: (N,) derivative w.r.t. the query time ``t``, m/s, or None without rates.
    """

    distance: F64
    p_imu: F64
    d_rotation: F64
    d_position: F64
    d_ext_rotation: F64
    d_ext_translation: F64
    d_point: F64
    d_time: F64 | None


def point_to_plane(
    rotation: F64,
    position: F64,
    R_imu_lidar: F64,
    t_imu_lidar: F64,
    p_lidar: F64,
    normal: F64,
    d: F64,
    angular_velocity: F64 | None = None,
    velocity: F64 | None = None,
) -> PointToPlaneGeometry:
    """Signed distance of LiDAR points to their planes in ``{G}`` with all first derivatives.

    ``d(t) = n^T (R(t) (R_IL p_L + t_IL) + p(t)) + d``; the time derivative is
    ``n^T (R hat(w) p_I + v)``.

    Args:
        rotation: (N, 3, 3) ``R_G_I(t)``.
        position: (N, 3) ``G p_I(t)``, m.
        R_imu_lidar: (3, 3) extrinsic rotation ``R_IL``.
        t_imu_lidar: (3,) extrinsic translation ``t_IL``, m.
        p_lidar: (N, 3) points in ``{L}``, m.
        normal: (N, 3) unit plane normals in ``{G}``.
        d: (N,) plane offsets ``d``, m.
        angular_velocity: (N, 3) body rate ``w_I(t)``, rad/s (for ``d_time``), or None.
        velocity: (N, 3) ``p_dot(t)`` in ``{G}``, m/s (for ``d_time``), or None.

    Returns:
        :class:`PointToPlaneGeometry`.
    """
    p_imu = p_lidar @ R_imu_lidar.T + t_imu_lidar
    # n_I = R^T n (normal in the IMU frame)
    n_imu = np.einsum("nji,nj->ni", rotation, normal)
    n_lidar = n_imu @ R_imu_lidar
    distance = np.einsum("ni,ni->n", n_imu, p_imu) + np.einsum("ni,ni->n", normal, position)
    distance += d
    # d/d eps of n^T R Exp(eps) p_I = -n_I^T hat(p_I) = (p_I x n_I)^T
    d_rotation = cross_rows(p_imu, n_imu)
    d_ext_rotation = cross_rows(p_lidar, n_lidar)
    d_time = None
    if angular_velocity is not None and velocity is not None:
        # n_I . (w x p_I) = w . (p_I x n_I)
        d_time = np.einsum("ni,ni->n", angular_velocity, d_rotation)
        d_time += np.einsum("ni,ni->n", normal, velocity)
    return PointToPlaneGeometry(
        distance=distance,
        p_imu=p_imu,
        d_rotation=d_rotation,
        d_position=normal,
        d_ext_rotation=d_ext_rotation,
        d_ext_translation=n_imu,
        d_point=n_lidar,
        d_time=d_time,
    )
