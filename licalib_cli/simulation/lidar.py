"""Synthetic LiDAR sweeps with motion distortion and per-beam intrinsics (method.md section 4).

For the ray of ring ``i`` fired at true time ``t`` with encoder azimuth ``theta``::

    theta_bar = theta + dtheta_i,  phi_bar = phi_i + dphi_i
    origin_L  = [H_i sin(theta_bar), -H_i cos(theta_bar), V_i]
    dir_L     = [cos(phi_bar) cos(theta_bar), cos(phi_bar) sin(theta_bar), sin(phi_bar)]

The ray is cast in the world from the LiDAR pose ``T_W_L(t) = T_W_I(t) T_imu_lidar`` at its own
firing time (motion distortion); the hit distance is ``rho_bar``. The raw range is
``rho = (rho_bar - drho_i) / s_i + n`` (``n`` Gaussian range noise) and the published point is the
driver's nominal conversion ``nominal_point(rho, theta, phi_i)``, so
``lidar_point(intrinsics, i, rho, theta)`` gives back the true point (up to noise).

A non-repetitive scanner (``mid360``, ``avia``) gives each ray its own nominal elevation ``phi``
(the pattern's ``elevation``, which changes from sweep to sweep) in place of ``phi_i``; it has no
per-beam intrinsics (all corrections zero), so its points are the true ones up to noise.

Stamps are on the LiDAR clock: ``tau = t - time_offset_s + lidar_clock_offset_s`` (plus the base
time). Sweep ``k`` covers true times ``[k T, (k + 1) T)``. With a per-point time error ``k_pt``
(the ``lidar_point_time`` effect) each point's published time since the sweep's first firing is
the true one divided by ``1 - k_pt``; header stamps stay true.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.models.lidar import nominal_point
from licalib_cli.simulation.ground_truth import SimulationSetup, Stream, build_setup, rng_for
from licalib_cli.simulation.lidar_models import FiringPattern
from licalib_cli.simulation.spec import LidarStamp, SimulationSpec

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ScanTruth:
    """Per-point truth of one sweep, aligned with ``points.reshape(-1)``.

    Attributes:
        t_true_s: (N,) true firing time relative to the base time, s.
        beam: (N,) ring index (``line`` of a Livox).
        theta: (N,) encoder azimuth, rad.
        phi: (N,) nominal elevation of the ray, rad (the ring's ``phi_i`` for a spinning LiDAR).
        rho: (N,) raw range as published (with noise), m; 0 for no-returns.
        rho_bar: (N,) true distance along the true ray, m.
        plane_id: (N,) int32 id of the surface hit (``World.planes()`` row).
        hit_world: (N, 3) true hit point in ``{W}``, m.
        valid: (N,) bool, False for no-returns (zero points of an organised cloud).
        t_published_s: (N,) the time the cloud gives the point, on the true time axis, s
            (``t_true_s`` unless the per-point times are off, ``lidar_point_time``).
    """

    t_true_s: F64
    beam: npt.NDArray[np.int64]
    theta: F64
    phi: F64
    rho: F64
    rho_bar: F64
    plane_id: npt.NDArray[np.int32]
    hit_world: F64
    valid: npt.NDArray[np.bool_]
    t_published_s: F64


@dataclass(frozen=True)
class SimulatedScan:
    """One published sweep.

    Attributes:
        index: sweep number k.
        stamp_ns: header stamp, LiDAR clock, absolute int64 ns.
        record_ns: bag record time (true time of the last ray), absolute int64 ns.
        points: structured array in the driver's layout, (N,) or organised (B, C).
        truth: per-point truth aligned with ``points.reshape(-1)``.
    """

    index: int
    stamp_ns: int
    record_ns: int
    points: np.ndarray
    truth: ScanTruth


def num_scans(spec: SimulationSpec) -> int:
    """Complete sweeps in the run."""
    return int(np.floor(spec.resolved_duration_s * spec.lidar_rate_hz + 1e-9))


def generate_scans(
    spec: SimulationSpec,
    setup: SimulationSetup | None = None,
    indices: Iterable[int] | None = None,
) -> Iterator[SimulatedScan]:
    """Sweeps of a run, one at a time (each vectorised over its rays).

    Args:
        spec: the options.
        setup: resolved truth; built from ``spec`` when None.
        indices: sweep numbers to generate; all ``num_scans(spec)`` when None.

    Yields:
        :class:`SimulatedScan` in the order of ``indices``.
    """
    setup = setup or build_setup(spec)
    model = setup.lidar_model
    pattern = model.pattern(spec.lidar_rate_hz, spec.azimuth_resolution_deg)
    planes = setup.world.planes()
    refl = setup.world.reflectivity()
    for k in range(num_scans(spec)) if indices is None else indices:
        if not model.repeats:  # a non-repetitive scanner: each sweep has its own rays
            pattern = model.pattern(spec.lidar_rate_hz, spec.azimuth_resolution_deg, int(k))
        yield _scan(setup, pattern, planes, refl, int(k))


def _scan(
    setup: SimulationSetup, pattern: FiringPattern, planes: F64, refl: F64, k: int
) -> SimulatedScan:
    spec = setup.spec
    model = setup.lidar_model
    kin = setup.lidar_intrinsics
    if model.organized:
        # (B, C): row = ring, column = firing column.
        t_rel = pattern.t_ns.T
        theta = pattern.theta.T
        ring = pattern.ring.T
        elevation = None if pattern.elevation is None else pattern.elevation.T
    else:
        # Driver order: cycle by cycle, lasers in firing order.
        order = np.argsort(model.firing_order)
        t_rel = pattern.t_ns[:, order]
        theta = pattern.theta[:, order]
        ring = pattern.ring[:, order]
        elevation = None if pattern.elevation is None else pattern.elevation[:, order]
    shape = t_rel.shape
    t_rel = t_rel.reshape(-1)
    theta = theta.reshape(-1)
    ring = ring.reshape(-1)
    if elevation is None:  # each ring at its elevation
        phi_true, phi_nominal = kin.nominal_elevation[ring], model.nominal_elevation[ring]
    else:  # each ray at its own
        phi_true = phi_nominal = elevation.reshape(-1)

    sweep_start_ns = k * pattern.period_ns
    t_true_ns = sweep_start_ns + t_rel
    uniq, inv = np.unique(t_true_ns, return_inverse=True)
    r_wl, p_wl = setup.lidar_pose_at(uniq.astype(np.float64) * 1e-9)
    r_wl, p_wl = r_wl[inv], p_wl[inv]

    theta_bar = theta + kin.azimuth_correction[ring]
    phi_bar = phi_true + kin.elevation_correction[ring]
    h = kin.horizontal_offset[ring]
    c_phi = np.cos(phi_bar)
    origin_l = np.stack(
        [h * np.sin(theta_bar), -h * np.cos(theta_bar), kin.vertical_offset[ring]], axis=-1
    )
    dir_l = np.stack(
        [c_phi * np.cos(theta_bar), c_phi * np.sin(theta_bar), np.sin(phi_bar)], axis=-1
    )
    origin_w = p_wl + np.einsum("nij,nj->ni", r_wl, origin_l)
    dir_w = np.einsum("nij,nj->ni", r_wl, dir_l)
    rho_bar, plane_id = setup.world.raycast(origin_w, dir_w)

    rng = rng_for(spec.resolved_noise_seed, Stream.LIDAR_NOISE, k)
    noise = rng.standard_normal(rho_bar.shape[0]) * spec.resolved_range_noise_m
    keep = rng.uniform(size=rho_bar.shape[0]) >= spec.dropout
    rho = (rho_bar - kin.range_offset[ring]) / kin.range_scale[ring] + noise
    valid = keep & (rho >= model.min_range) & (rho <= model.max_range)
    xyz = nominal_point(rho, theta, phi_nominal)
    cos_inc = np.abs(np.einsum("ni,ni->n", planes[plane_id, :3], dir_w))
    albedo = refl[plane_id] * cos_inc

    offset_ns = -setup.time_offset_ns + setup.lidar_clock_offset_ns
    first_ns = sweep_start_ns + int(t_rel.min())
    k_pt = spec.resolved_point_time_error
    if k_pt != 0.0:  # published times within the sweep run 1 / (1 - k) fast
        t_pub_ns = first_ns + np.round((t_true_ns - first_ns) / (1.0 - k_pt)).astype(np.int64)
    else:
        t_pub_ns = t_true_ns
    sweep_stamp_rel = first_ns
    if model.kind.is_velodyne and spec.lidar_stamp is LidarStamp.END:
        sweep_stamp_rel = sweep_start_ns + int(t_rel.max())
    stamp_ns = spec.base_time_ns + sweep_stamp_rel + offset_ns
    record_ns = spec.base_time_ns + sweep_start_ns + int(t_rel.max())
    if spec.record_delay_ms > 0.0:  # in order: at most half a period, so no cloud overtakes
        delay = rng_for(spec.resolved_noise_seed, Stream.RECORD_DELAY, 1, k).exponential(
            spec.record_delay_ms * 1e6
        )
        record_ns += round(min(delay, 0.5e9 / spec.lidar_rate_hz))

    points = np.zeros(t_rel.shape[0], dtype=model.dtype)
    if model.organized:
        points["x"], points["y"], points["z"] = (np.where(valid, xyz[:, i], 0.0) for i in range(3))
        points["intensity"] = np.where(valid, 1000.0 * albedo / (1.0 + 0.05 * rho_bar), 0.0)
        points["t"] = (t_pub_ns - first_ns).astype(np.uint32)
        reflectivity = np.where(valid, np.round(255 * refl[plane_id]), 0)
        points["reflectivity"] = reflectivity.astype(np.uint16)
        points["ring"] = ring.astype(np.uint16)
        points["ambient"] = (50 + 20 * np.cos(theta)).astype(np.uint16)
        points["range"] = np.where(valid, np.round(rho * 1000.0), 0).astype(np.uint32)
        points = points.reshape(shape)
        rho_out = np.where(valid, rho, 0.0)
        sel = np.ones(t_rel.shape[0], dtype=bool)
    else:
        sel = valid
        points = points[sel]
        points["x"], points["y"], points["z"] = xyz[sel, 0], xyz[sel, 1], xyz[sel, 2]
        points["intensity"] = np.round(255.0 * albedo[sel])
        if "line" in (model.dtype.names or ()):  # Livox: absolute ns on the stamp's clock
            points["line"] = ring[sel].astype(np.uint8)
            points["timestamp"] = (spec.base_time_ns + offset_ns + t_pub_ns[sel]).astype(np.float64)
        else:
            points["ring"] = ring[sel].astype(np.uint16)
            points["time"] = ((t_pub_ns[sel] - sweep_stamp_rel) * 1e-9).astype(np.float32)
        rho_out = rho

    truth = ScanTruth(
        t_true_s=t_true_ns[sel].astype(np.float64) * 1e-9,
        beam=ring[sel].astype(np.int64),
        theta=theta[sel],
        phi=phi_nominal[sel],
        rho=rho_out[sel],
        rho_bar=rho_bar[sel],
        plane_id=plane_id[sel],
        hit_world=origin_w[sel] + rho_bar[sel, None] * dir_w[sel],
        valid=valid[sel],
        t_published_s=t_pub_ns[sel].astype(np.float64) * 1e-9,
    )
    return SimulatedScan(k, int(stamp_ns), int(record_ns), points, truth)
