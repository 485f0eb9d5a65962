"""The LiDAR points the optimisation uses: raw measurements per point, sampled per sweep.

A point is kept as the LiDAR model's raw measurement (beam, range, azimuth; method.md section 4)
together with what the driver's published point adds to the nominal model point (``model_gap``:
zero for a driver that converts with the nominal beam table, a per-beam correction otherwise),
so that the map and the solver apply exactly the same point model.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, DataError
from licalib_cli.estimation import CalibrationState, LidarPoints
from licalib_cli.geometry.vectors import norms
from licalib_cli.measurements import LidarScan
from licalib_cli.models.lidar import lidar_point, nominal_point
from licalib_cli.parallel.threads import map_slices

__all__ = [
    "MORE_POINTS_FACTOR",
    "PointBudget",
    "PointSample",
    "joint_point_budget",
    "nominal_elevations",
    "point_budget",
    "points_and_rays_in_global",
    "points_in_global",
    "points_per_scan",
    "query_times",
    "round_points",
    "sample_points",
    "solver_points",
    "usable_mask",
    "usable_points",
]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PointSample:
    """Points kept for the optimisation, with their raw measurements.

    Attributes:
        t_ns: (N,) LiDAR-clock time of each point, ns.
        sweep_start_ns: (N,) LiDAR-clock time of the first point of the point's sweep, ns.
        beam: (N,) beam index.
        rho: (N,) raw range, m.
        theta: (N,) raw azimuth, rad.
        model_gap: (N, 3) published point minus the nominal model point, m (zero for an ideal
            driver conversion); kept so that nominal intrinsics reproduce the published cloud.
    """

    t_ns: npt.NDArray[np.int64]
    sweep_start_ns: npt.NDArray[np.int64]
    beam: npt.NDArray[np.int64]
    rho: F64
    theta: F64
    model_gap: F64

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def subset(self, mask: npt.NDArray[Any]) -> PointSample:
        """The points selected by a boolean mask or an index array."""
        return PointSample(
            self.t_ns[mask],
            self.sweep_start_ns[mask],
            self.beam[mask],
            self.rho[mask],
            self.theta[mask],
            self.model_gap[mask],
        )


def nominal_elevations(scans: tuple[LidarScan, ...], cfg: CalibConfig) -> F64:
    """Nominal elevation ``phi_i`` of each beam, rad: the config's table or the data's median.

    Raises:
        DataError: the clouds carry no beam index.
        ConfigError: the configured beam table lists fewer beams than the data has.
    """
    rings = [s.ring for s in scans if s.ring is not None and len(s) > 0]
    if not rings:
        msg = "The LiDAR clouds carry no beam index; set lidar.ring_field or lidar.num_beams."
        raise DataError(msg)
    n_beams = int(max(int(r.max()) for r in rings)) + 1
    if cfg.lidar.nominal_elevation_deg is not None:
        table = np.radians(np.asarray(cfg.lidar.nominal_elevation_deg, dtype=np.float64))
        if table.shape[0] < n_beams:
            msg = (
                f"lidar.nominal_elevation_deg lists {table.shape[0]} beams but the data has "
                f"ring numbers up to {n_beams - 1}; list one elevation per ring."
            )
            raise ConfigError(msg)
        return table
    step = max(1, len(scans) // 20)
    xyz = np.concatenate([s.xyz for s in scans[::step] if s.ring is not None])
    ring = np.concatenate([s.ring for s in scans[::step] if s.ring is not None]).astype(np.int64)
    elev = np.arcsin(np.clip(xyz[:, 2] / np.maximum(norms(xyz), 1e-9), -1, 1))
    order = np.argsort(ring, kind="stable")
    ring, elev = ring[order], elev[order]
    bounds = np.searchsorted(ring, np.arange(n_beams + 1))
    out = np.zeros(n_beams)
    for b in range(n_beams):  # loop over beams (at most a few hundred), not points
        seg = elev[bounds[b] : bounds[b + 1]]
        out[b] = float(np.median(seg)) if seg.size else 0.0
    return out


def points_per_scan(cfg: CalibConfig, num_scans: int, wanted: int | None = None) -> int:
    """Points kept per scan: ``wanted`` (default ``surfels.points_per_scan``), lowered so that
    all scans together keep at most ``surfels.max_points``."""
    per_scan = cfg.surfels.points_per_scan if wanted is None else wanted
    return max(1, min(per_scan, cfg.surfels.max_points // max(num_scans, 1)))


MORE_POINTS_FACTOR = 2
"""The last round's points are said to bound the sigmas when a sweep holds at least this many
times the points it kept of each."""


@dataclass(frozen=True)
class PointBudget:
    """How many points of each sweep the last round kept, against how many a sweep holds.

    Attributes:
        kept: points kept per sweep (``surfels.final_points_per_scan`` for the dense final
            round, ``surfels.points_per_scan`` without one, both lowered to keep
            ``surfels.max_points`` over all sweeps).
        available: points of the median sweep.
    """

    kept: int
    available: int

    @property
    def more_available(self) -> bool:
        """Whether a sweep holds at least :data:`MORE_POINTS_FACTOR` times the points kept."""
        return self.available >= MORE_POINTS_FACTOR * self.kept


def round_points(cfg: CalibConfig, num_scans: int) -> tuple[int, int | None]:
    """Points per sweep of the regular rounds, and of the denser final round: None when there
    is none (``surfels.final_points_per_scan`` unset, or not above the regular rounds' once
    both keep ``surfels.max_points``)."""
    regular = points_per_scan(cfg, num_scans)
    final = cfg.surfels.final_points_per_scan
    dense = points_per_scan(cfg, num_scans, final) if final is not None else None
    return regular, dense if dense is not None and dense > regular else None


def point_budget(cfg: CalibConfig, scans: tuple[LidarScan, ...]) -> PointBudget | None:
    """The last round's points per sweep against the sweeps' (None without sweeps)."""
    if not scans:
        return None
    regular, dense = round_points(cfg, len(scans))
    kept = regular if dense is None else dense
    available = int(np.median([len(s) for s in scans]))  # loop over sweeps, not points
    return PointBudget(kept, available)


def joint_point_budget(budgets: Sequence[PointBudget | None]) -> PointBudget | None:
    """The points of segments estimated together: the most any segment's last round kept per
    sweep against the fewest a segment's sweep holds, so that more are said to be available
    only when every segment holds them (None when a segment has no budget)."""
    known = [b for b in budgets if b is not None]
    if not known or len(known) < len(budgets):
        return None
    return PointBudget(max(b.kept for b in known), min(b.available for b in known))


def sample_points(
    scans: tuple[LidarScan, ...], phi: F64, per_scan: int, cfg: CalibConfig, seed: int = 0
) -> PointSample:
    """Keep up to ``per_scan`` points of each sweep, spread uniformly over the sweep."""
    rng = np.random.default_rng(seed)
    parts: list[tuple[Any, ...]] = []
    for scan in scans:  # loop over sweeps, not points
        if scan.ring is None or len(scan) == 0:
            continue
        rho = norms(scan.xyz)
        ok = (rho >= cfg.lidar.min_range_m) & (rho <= cfg.lidar.max_range_m)
        idx = np.flatnonzero(ok)
        if idx.size > per_scan:
            idx = np.sort(rng.choice(idx, per_scan, replace=False))
        start = np.full(idx.size, int(scan.t_ns.min()), dtype=np.int64)
        parts.append(
            (scan.t_ns[idx], start, scan.ring[idx].astype(np.int64), scan.xyz[idx], rho[idx])
        )
    t_ns = np.concatenate([p[0] for p in parts])
    start_ns = np.concatenate([p[1] for p in parts])
    beam = np.concatenate([p[2] for p in parts])
    xyz = np.concatenate([p[3] for p in parts])
    rho = np.concatenate([p[4] for p in parts])
    theta = np.arctan2(xyz[:, 1], xyz[:, 0])
    gap = xyz - nominal_point(rho, theta, phi[beam])
    return PointSample(t_ns, start_ns, beam, rho, theta, gap)


def query_times(state: CalibrationState, sample: PointSample) -> F64:
    """(N,) the trajectory time of each point, seconds on the splines' axis: its LiDAR time plus
    the time offset (and, when estimated, the clock drift and the per-point time error)."""
    tau = np.asarray((sample.t_ns - state.t0_ns) * 1e-9, dtype=np.float64)
    t = tau + state.time_offset_s
    if state.time_drift:
        t = t + state.time_drift * (tau - state.t_ref_s)
    if state.point_time_scale:
        t = t - state.point_time_scale * (sample.t_ns - sample.sweep_start_ns) * 1e-9
    return t


def points_in_global(state: CalibrationState, sample: PointSample) -> F64:
    """(N, 3) sampled points mapped into ``{G}`` with the state's trajectory and calibration."""
    return _mapped(state, sample, rays=False)[0]


def points_and_rays_in_global(state: CalibrationState, sample: PointSample) -> tuple[F64, F64]:
    """:func:`points_in_global` and (N, 3) each point's unit ray direction in ``{G}`` (the
    direction of its range, along which its range noise moves it)."""
    p_g, rays = _mapped(state, sample, rays=True)
    assert rays is not None
    return p_g, rays


def _mapped(state: CalibrationState, sample: PointSample, rays: bool) -> tuple[F64, F64 | None]:
    # A point whose trajectory time has left the spline (a round moved the time offset past the
    # margin its points were chosen with) is mapped at the spline's end, as the point-to-plane
    # residuals evaluate it; the next round's usable points leave it out.
    t = state.knots.clamp(query_times(state, sample))
    r_il = state.R_imu_lidar
    out = np.empty((t.shape[0], 3))
    ray_out = np.empty_like(out) if rays else None

    def block(sl: slice) -> None:
        # the splines' own blocks (BLOCK queries): the values of one evaluation of all points;
        # the LiDAR model per point as well
        p_l = lidar_point(state.lidar_intrinsics, sample.beam[sl], sample.rho[sl], sample.theta[sl])
        p_i = (p_l + sample.model_gap[sl]) @ r_il.T + state.t_imu_lidar
        rot = state.so3_spline.rotation(t[sl])
        np.einsum("nij,nj->ni", rot, p_i, out=out[sl])
        out[sl] += state.r3_spline.position(t[sl])
        if ray_out is not None:
            u_i = p_l @ r_il.T
            u_i /= np.maximum(np.linalg.norm(u_i, axis=1, keepdims=True), 1e-12)
            np.einsum("nij,nj->ni", rot, u_i, out=ray_out[sl])

    map_slices(block, t.shape[0])
    return out, ray_out


def solver_points(
    state: CalibrationState, sample: PointSample, plane: npt.NDArray[np.integer]
) -> LidarPoints:
    """The sampled points as the solver's input, each with the index of its plane: the same
    raw measurements, model gap and times as :func:`points_in_global` maps, so that the residual
    of a point that lies on its plane in the map is zero."""
    return LidarPoints(
        t_s=np.asarray((sample.t_ns - state.t0_ns) * 1e-9, dtype=np.float64),
        beam=sample.beam,
        rho=sample.rho,
        theta=sample.theta,
        plane=plane,
        model_gap=sample.model_gap,
        sweep_start_s=np.asarray((sample.sweep_start_ns - state.t0_ns) * 1e-9, dtype=np.float64),
    )


def usable_mask(
    state: CalibrationState, sample: PointSample, margin_s: float
) -> npt.NDArray[np.bool_]:
    """(N,) which points' trajectory time ``tau + t_c`` stays inside the spline with a margin."""
    t = query_times(state, sample)
    knots = state.knots
    lo = knots.t0_s + margin_s
    hi = knots.t_end_s - margin_s
    return (t >= lo) & (t <= hi)


def usable_points(state: CalibrationState, sample: PointSample, margin_s: float) -> PointSample:
    """Points whose trajectory time ``tau + t_c`` stays inside the spline with a margin."""
    return sample.subset(usable_mask(state, sample, margin_s))
