"""LiDAR odometry: kiss-icp, then a point-to-plane refinement; scans in, one pose per scan out.

:func:`run_odometry` registers the scans with kiss-icp. Its point-to-point ICP on sparse
multi-beam rings is biased (rings lock onto rings) and its constant-velocity deskew lags fast
motion, so its scan-to-scan rotations can be off by degrees. :func:`refine_odometry` re-registers
every scan against a local map with point-to-plane ICP (open3d), seeded by the kiss-icp poses,
and deskews with the refined motion, or with a rotation prior such as the gyro when given.

Conventions:
    - ``T_map_lidar[k]`` maps points of scan ``k`` (LiDAR frame at time ``t_ns[k]``) into the map
      frame ``{M}`` = the LiDAR frame of the first scan, so ``T_map_lidar[0]`` is the identity.
    - kiss-icp (>= 1.2.2) deskews every scan to its latest point time, so a pose refers to the
      absolute time of the latest point of its scan; licalib stamps it with that time itself.
      Without deskewing (``deskew=False`` or a scan whose points all share one time) the cloud is
      registered as a rigid snapshot and the pose is stamped with the mean point time instead.
    - Per-point times are handed to kiss-icp as float seconds relative to the first point of the
      scan. A scan whose points all share one time is passed with an empty time array, because a
      zero time span makes kiss-icp divide 0/0 and abort the process.
    - The kiss-icp configuration is built field by field, so ``kiss_icp_*`` environment variables
      cannot change it.
    - :func:`refine_odometry` refers every pose to the latest point time of its scan and
      stamps it with that time, whether or not kiss-icp deskewed.
    - Optional rotation pre-deskew: given the LiDAR orientation ``R_w_lidar(t)`` in any fixed frame
      (for example from the gyro and the rotation extrinsic), every point is rotated into the LiDAR
      frame at the latest point time before registration, and kiss-icp's own constant-velocity
      deskew is switched off for that run. Translation during the sweep is compensated with the
      constant velocity of the two previous poses (none for the first two scans).
"""

from __future__ import annotations

import importlib
import logging
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from licalib_cli.errors import ConfigError, DataError
from licalib_cli.geometry.vectors import norms
from licalib_cli.measurements import LidarScan
from licalib_cli.parallel.threads import Filled, serial, threads

if TYPE_CHECKING:
    import open3d
    from kiss_icp.config import KISSConfig

__all__ = [
    "MIN_KEYPOINTS",
    "MIN_SCENE_SCALE",
    "OdometryConfig",
    "PoseSeries",
    "ProgressFn",
    "RefineConfig",
    "RotationAt",
    "at_scale",
    "kiss_icp_config",
    "refine_odometry",
    "run_odometry",
    "scene_scale",
]

logger = logging.getLogger(__name__)

RotationAt = Callable[[npt.NDArray[np.int64]], Rotation]
"""Orientation of the LiDAR frame in a fixed frame, ``R_w_lidar(t)``, at absolute times (ns)."""

ProgressFn = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each scan."""


@dataclass(frozen=True)
class OdometryConfig:
    """Settings of the kiss-icp odometry.

    Attributes:
        voxel_size: map voxel size, metres; None gives ``max_range / 100`` (kiss-icp's rule).
        max_range: points farther than this from the sensor are dropped, metres.
        min_range: points closer than this are dropped, metres.
        deskew: motion-compensate each scan with kiss-icp's constant-velocity model.
        max_points_per_voxel: kiss-icp local-map density.
        max_threads: threads kiss-icp may use; 0 lets it decide. One by default: its
            registration sums in a parallel reduction whose order varies from run to run, so
            with more threads the poses differ in their last bits between runs of the same
            bag, and a calibration is no longer reproducible (see :func:`_open3d`).
    """

    voxel_size: float | None = None
    max_range: float = 100.0
    min_range: float = 0.5
    deskew: bool = True
    max_points_per_voxel: int = 20
    max_threads: int = 1


@dataclass(frozen=True)
class PoseSeries:
    """LiDAR poses from odometry.

    Attributes:
        t_ns: (K,) int64 absolute time each pose refers to, nanoseconds (see module docstring).
        T_map_lidar: (K, 4, 4) float64 pose of the LiDAR in the map frame; the first is identity.
        n_points: (K,) int64 points of each scan left after the range filter.
        n_keypoints: (K,) int64 downsampled points used for registration.
        threshold_m: (K,) float64 kiss-icp adaptive correspondence threshold used, metres.
        deviation_m: (K,) float64 translation between the constant-velocity prediction and the
            registered pose, metres (large jumps flag registration failures).
        deviation_deg: (K,) float64 rotation between prediction and registered pose, degrees.
    """

    t_ns: npt.NDArray[np.int64]
    T_map_lidar: npt.NDArray[np.float64]
    n_points: npt.NDArray[np.int64]
    n_keypoints: npt.NDArray[np.int64]
    threshold_m: npt.NDArray[np.float64]
    deviation_m: npt.NDArray[np.float64]
    deviation_deg: npt.NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def rotations(self) -> Rotation:
        """``R_map_lidar`` of every pose as one scipy Rotation of length K."""
        return Rotation.from_matrix(self.T_map_lidar[:, :3, :3])

    @property
    def positions(self) -> npt.NDArray[np.float64]:
        """(K, 3) LiDAR origin in the map frame, metres."""
        return self.T_map_lidar[:, :3, 3]


_PLOTLY_VIEWER = "open3d.visualization.draw_plotly"


class _DeferredViewer(ModuleType):
    """Stands in for open3d's plotly viewer module: its functions import the real one (and
    dash and plotly with it) when first called."""

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("__"):
            raise AttributeError(name)

        def call(*args: Any, **kwargs: Any) -> Any:
            if sys.modules.get(_PLOTLY_VIEWER) is self:
                del sys.modules[_PLOTLY_VIEWER]
            return getattr(importlib.import_module(_PLOTLY_VIEWER), name)(*args, **kwargs)

        call.__name__ = call.__qualname__ = name
        return call


def _open3d() -> ModuleType:
    """open3d, imported without loading its plotly viewer, limited to one thread.

    ``import open3d`` imports its plotly viewer, and dash and plotly with it: half of its
    0.5 s import, none of it used here. The viewer's functions stay callable and import it on
    their first call (:class:`_DeferredViewer`).

    One thread, so that a calibration is reproducible: open3d's ICP sums its normal equations
    in a parallel reduction whose order varies from run to run, and the last bits it changes
    grew, through the registrations and the rounds' associations, into a different result on
    the same bag and configuration (a 30 s VLP-16 shake: 150 or 261 map planes, the time
    offset 5.5 or 1.2 of its sigmas off).
    """
    if "open3d" not in sys.modules:
        sys.modules.setdefault(_PLOTLY_VIEWER, _DeferredViewer(_PLOTLY_VIEWER))
    import open3d

    open3d.utility.set_max_threads(1)
    return open3d


def kiss_icp_config(cfg: OdometryConfig) -> KISSConfig:
    """Build a kiss-icp ``KISSConfig`` from ``cfg`` without reading environment variables.

    Every field is given explicitly and the pydantic-settings sources are bypassed
    (``model_construct``), so ``kiss_icp_*`` variables in the environment have no effect.

    Returns:
        The ``kiss_icp.config.KISSConfig`` instance.

    Raises:
        ConfigError: ``min_range``/``max_range`` are inconsistent.
    """
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import (
        AdaptiveThresholdConfig,
        DataConfig,
        MappingConfig,
        RegistrationConfig,
    )

    max_range = float(cfg.max_range)
    min_range = float(cfg.min_range)
    if not 0.0 <= min_range < max_range:
        msg = (
            f"Odometry range limits are inconsistent (min_range {min_range} m, max_range "
            f"{max_range} m); set 0 <= min_range < max_range."
        )
        raise ConfigError(msg)
    voxel = float(cfg.voxel_size) if cfg.voxel_size is not None else max_range / 100.0
    return KISSConfig.model_construct(
        out_dir="results",
        data=DataConfig(max_range=max_range, min_range=min_range, deskew=bool(cfg.deskew)),
        registration=RegistrationConfig(
            max_num_iterations=500, convergence_criterion=1e-4, max_num_threads=cfg.max_threads
        ),
        mapping=MappingConfig(voxel_size=voxel, max_points_per_voxel=cfg.max_points_per_voxel),
        adaptive_threshold=AdaptiveThresholdConfig(
            fixed_threshold=None, initial_threshold=2.0, min_motion_th=0.1
        ),
    )


def _rotation_deskew(
    scan: LidarScan,
    rotation_at: RotationAt,
    velocity_lidar: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """Move every point of ``scan`` into the LiDAR frame at the scan's latest point time.

    ``p_end = R_w_lidar(t_end)^T R_w_lidar(t) p + v (t - t_end)``, with the rotation from
    ``rotation_at`` and ``v`` (3,) the LiDAR velocity expressed in the end frame, m/s.

    Returns:
        (N, 3) float64 points.
    """
    t_end = scan.t_ns.max()
    r_pts = rotation_at(scan.t_ns)
    r_end = rotation_at(np.array([t_end], dtype=np.int64))
    dt = (scan.t_ns - t_end).astype(np.float64) * 1e-9
    moved = (r_end.inv() * r_pts).apply(scan.xyz) + dt[:, None] * velocity_lidar[None, :]
    return np.asarray(moved, dtype=np.float64)


def run_odometry(
    scans: Sequence[LidarScan],
    cfg: OdometryConfig,
    progress: ProgressFn | None = None,
    *,
    rotation_at: RotationAt | None = None,
) -> PoseSeries:
    """Register the scans one after the other with kiss-icp.

    Args:
        scans: K scans in time order, points in the LiDAR frame with absolute per-point times.
        cfg: odometry settings.
        progress: optional ``progress(done, total)`` callback, called after each scan.
        rotation_at: optional ``R_w_lidar(t)`` used to rotation-deskew each scan before
            registration (kiss-icp's own deskew is then off); see the module docstring.

    Returns:
        One pose per scan, stamped with the time it refers to.

    Raises:
        DataError: no scans, a scan without points, or scans out of time order.
        ConfigError: inconsistent range limits.
    """
    if len(scans) == 0:
        msg = "No LiDAR scans to run odometry on; check the LiDAR topic and the time window."
        raise DataError(msg)
    from kiss_icp.kiss_icp import KissICP

    kcfg = kiss_icp_config(cfg)
    odom = KissICP(config=kcfg)
    k = len(scans)
    t_out = np.empty(k, dtype=np.int64)
    poses = np.empty((k, 4, 4), dtype=np.float64)
    n_points = np.zeros(k, dtype=np.int64)
    n_keys = np.zeros(k, dtype=np.int64)
    thresholds = np.zeros(k, dtype=np.float64)
    dev_m = np.zeros(k, dtype=np.float64)
    dev_deg = np.zeros(k, dtype=np.float64)
    empty = np.zeros(0, dtype=np.float64)
    for i, scan in enumerate(scans):
        if len(scan) == 0:
            msg = (
                f"LiDAR scan {i} (stamp {scan.stamp_ns} ns) has no points; "
                "drop empty scans before odometry."
            )
            raise DataError(msg)
        rng = norms(scan.xyz)
        if not np.any((rng >= kcfg.data.min_range) & (rng <= kcfg.data.max_range)):
            msg = (
                f"LiDAR scan {i} (stamp {scan.stamp_ns} ns) has no point between "
                f"{kcfg.data.min_range:g} m and {kcfg.data.max_range:g} m; check the range "
                "limits of the odometry and the point units."
            )
            raise DataError(msg)
        t_min = int(scan.t_ns.min())
        t_max = int(scan.t_ns.max())
        span = t_max - t_min
        if rotation_at is not None and span > 0:
            # Translation during the sweep from the constant velocity of the last two poses,
            # expressed in the predicted end frame.
            velocity = np.zeros(3)
            if i >= 2:
                dt_prev = float(t_out[i - 1] - t_out[i - 2]) * 1e-9
                v_map = (poses[i - 1, :3, 3] - poses[i - 2, :3, 3]) / dt_prev
                r_pred = (odom.last_pose @ odom.last_delta)[:3, :3]
                velocity = r_pred.T @ v_map
            xyz = _rotation_deskew(scan, rotation_at, velocity)
            times = empty
            t_ref = t_max
        elif cfg.deskew and span > 0:
            xyz = np.ascontiguousarray(scan.xyz, dtype=np.float64)
            times = (scan.t_ns - t_min).astype(np.float64) * 1e-9
            t_ref = t_max
        else:
            xyz = np.ascontiguousarray(scan.xyz, dtype=np.float64)
            times = empty
            t_ref = t_min + int(np.mean(scan.t_ns - t_min))
        if i > 0 and t_ref <= t_out[i - 1]:
            msg = (
                f"LiDAR scan {i} refers to time {t_ref} ns, not after scan {i - 1} "
                f"({t_out[i - 1]} ns); sort the scans by time and drop duplicates."
            )
            raise DataError(msg)
        sigma = float(odom.adaptive_threshold.get_threshold())
        prediction = odom.last_pose @ odom.last_delta
        frame, source = odom.register_frame(xyz, times)
        deviation = np.linalg.inv(prediction) @ odom.last_pose
        t_out[i] = t_ref
        poses[i] = odom.last_pose
        n_points[i] = frame.shape[0]
        n_keys[i] = source.shape[0]
        thresholds[i] = sigma
        dev_m[i] = float(np.linalg.norm(deviation[:3, 3]))
        dev_deg[i] = float(np.degrees(Rotation.from_matrix(deviation[:3, :3]).magnitude()))
        if progress is not None:
            progress(i + 1, k)
    # kiss-icp starts at identity already; re-anchor anyway so the contract holds exactly.
    poses = np.linalg.inv(poses[0]) @ poses
    logger.info(
        "odometry: %d scans, %.1f m path, max prediction deviation %.3f m / %.2f deg",
        k,
        float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()),
        float(dev_m.max()),
        float(dev_deg.max()),
    )
    return PoseSeries(
        t_ns=t_out,
        T_map_lidar=poses,
        n_points=n_points,
        n_keypoints=n_keys,
        threshold_m=thresholds,
        deviation_m=dev_m,
        deviation_deg=dev_deg,
    )


# ------------------------------------------------------------------ point-to-plane refinement


@dataclass(frozen=True)
class RefineConfig:
    """Settings of :func:`refine_odometry` (point-to-plane scan-to-local-map registration).

    Attributes:
        voxel_size: keypoint voxel, metres; the first point of each voxel is kept, with its time.
        map_voxel_size: voxel of the points a scan contributes to the local map, metres.
        map_scans: registered scans kept in the local map.
        normal_neighbors: most neighbours of a map point used for its normal.
        normal_radius: neighbours farther than this are ignored for normals, metres.
        max_correspondence: correspondence distance of the first pass, metres.
        fine_correspondence: correspondence distance of the later passes, metres.
        robust_scale: Tukey kernel scale of the point-to-plane residuals, metres.
        max_iterations: ICP iterations per registration.
        passes: passes over all scans; the first deskews with a prediction, every later one
            with the motion the previous pass found around each sweep.
        warmup_scans: the first scans are registered twice (two passes) before the first
            pass, whose seeds for them come from that; 0 switches the warm-up off.
        min_fitness: a registration matching fewer than this fraction of the keypoints is
            rejected and the seed relative pose kept for that scan.
    """

    voxel_size: float = 0.4
    map_voxel_size: float = 0.25
    map_scans: int = 3
    normal_neighbors: int = 15
    normal_radius: float = 0.6
    max_correspondence: float = 0.6
    fine_correspondence: float = 0.3
    robust_scale: float = 0.1
    max_iterations: int = 10
    passes: int = 2
    warmup_scans: int = 6
    min_fitness: float = 0.3


@dataclass(frozen=True)
class _Sweep:
    """Points of one scan prepared for deskewing and registration.

    Attributes:
        n_points: points of the scan left after the range filter.
        xyz: (N, 3) float64 map points, LiDAR frame at their own times, metres.
        normals: (N, 3) float64 unit normals of the map points, same frame.
        dt_ns: (N,) int64 point time minus the scan's reference (latest) time, <= 0.
        rot_to_end: (N, 3, 3) ``R_end^T R(t)`` from the rotation prior, or None.
        keys: (M,) int64 indices of the keypoints among the map points.
    """

    n_points: int
    xyz: npt.NDArray[np.float64]
    normals: npt.NDArray[np.float64]
    dt_ns: npt.NDArray[np.int64]
    rot_to_end: npt.NDArray[np.float64] | None
    keys: npt.NDArray[np.int64]


def _voxel_first(xyz: npt.NDArray[np.float64], voxel: float) -> npt.NDArray[np.int64]:
    """Indices of the first point of every occupied voxel of size ``voxel``, ascending."""
    keys = np.floor(xyz / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    n = flat.shape[0]
    if n == 0 or int(flat.max()) >= (2**62) // n:
        _, first = np.unique(flat, return_index=True)
        return np.sort(first)
    # Voxel and index in one int64 (an unstable sort of plain integers is several times faster
    # than the stable argsort np.unique's indices need): the smallest index of every voxel
    # comes first in its run.
    packed = np.sort(flat * n + np.arange(n, dtype=np.int64))
    voxel_of = packed // n
    starts = np.ones(n, dtype=bool)
    starts[1:] = voxel_of[1:] != voxel_of[:-1]
    return np.sort(packed[starts] % n)


def _log(T: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """(6,) ``[rotation vector, translation]`` of a (4, 4) pose."""
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def _deskew(
    sweep: _Sweep,
    node_dt_ns: npt.NDArray[np.float64],
    node_xi: npt.NDArray[np.float64],
    keys_only: bool,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Move points (and normals) into the LiDAR frame at the scan's reference (latest) time.

    The motion within the sweep is the polynomial through M poses relative to the reference
    pose: ``node_xi`` (M, 6) holds ``[rotation vector, translation]`` of ``T_end^-1 T(t_j)`` at
    ``node_dt_ns`` (M,) = ``t_j - t_end``. Each point moves by the Lagrange interpolation at its
    time, ``p_end = Exp(r(t)) p + tau(t)``; ``sweep.rot_to_end`` replaces ``Exp(r(t))`` when
    set. Two nodes (the previous pose and the identity) give constant velocity.

    Returns:
        (N, 3) points and (N, 3) normals, float64 (the keypoints only if ``keys_only``).
    """
    sel = sweep.keys if keys_only else slice(None)
    x = sweep.dt_ns[sel].astype(np.float64)
    nodes = np.asarray(node_dt_ns, dtype=np.float64)
    w = np.ones((x.shape[0], nodes.shape[0]))
    for j in range(nodes.shape[0]):
        for m in range(nodes.shape[0]):
            if m != j:
                w[:, j] *= (x - nodes[m]) / (nodes[j] - nodes[m])
    xi = w @ node_xi
    if sweep.rot_to_end is not None:
        rot = sweep.rot_to_end[sel]
    else:
        rot = np.asarray(Rotation.from_rotvec(xi[:, :3]).as_matrix())
    pts = np.einsum("nij,nj->ni", rot, sweep.xyz[sel]) + xi[:, 3:]
    nrm = np.einsum("nij,nj->ni", rot, sweep.normals[sel])
    return pts, nrm


_SETTLED_ROTATION_RAD = 3e-4
_SETTLED_TRANSLATION_M = 1e-3
"""A sweep's registration stops once a step turns it by less than 0.3 mrad and moves each of its
two positions by less than 1 mm. The positions' steps level off at a few tenths of a millimetre
(nearest map points switching from step to step) while the rotation keeps converging; a finer
translation limit was reached by few sweeps, which then ran all ``refine.max_iterations``."""

_BEGIN_PRIOR = 1e-3
"""Weight of the sweep's start position at the previous scan's end, relative to the summed
weights of the matched points (:func:`_register_with_sweep_motion`)."""


_END_PRIOR = 1e-3
"""Weight of the sweep's end position at its prediction, relative to the summed weights of the
matched points (:func:`_register_with_sweep_motion`). It holds only what the sweep leaves
undetermined: a narrow field of view seeing one or two planes cannot fix the translation
along them, and without it the registration slid there. On a simulated Avia-like rosette
(about 70 keypoints a sweep) with the true calibration, sweeps slid up to 6 m, the map
followed them, and 65 of 99 registrations were then rejected; with it none was, and no end
moved more than 0.18 m from its prediction. Where the sweep determines the translation the
prediction moves it by a thousandth of its error."""

_PARALLEL_QUERY_POINTS = 20_000
"""Nearest-neighbour queries of at least this many points use the block threads. A sweep's
keypoints (about a thousand on a VLP-16, against a local map of seven thousand) are queried
in a fraction of a millisecond, less than starting the query's threads costs: on a 12 s
shake with three gyro-aided hand-eye rounds the initialisation took 2.4 s instead of 3.1 s and
the odometry 3.7 s instead of 4.1 s, with identical results."""


def _register_with_sweep_motion(
    y: npt.NDArray[np.float64],
    end_weight: npt.NDArray[np.float64],
    p_before: npt.NDArray[np.float64],
    target: tuple[cKDTree, npt.NDArray[np.float64], npt.NDArray[np.float64]],
    pose: npt.NDArray[np.float64],
    correspondence: float,
    refine: RefineConfig,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], float]:
    """Point-to-plane ICP of one sweep together with the LiDAR's translation within the sweep.

    The rotation within the sweep is known (``y``: the points already rotated into the LiDAR
    frame at the sweep's end with the rotation prior); the LiDAR origin moves linearly from
    ``p_begin`` at the sweep's start to ``p`` at its end, so a point lies at
    ``R y + w p + (1 - w) p_begin`` in the map, with ``w`` its ``end_weight``. ``R``, ``p`` and
    ``p_begin`` are estimated together (Gauss-Newton, Tukey weights of scale
    ``refine.robust_scale``, nearest map points within ``correspondence`` found again every
    step, at most ``refine.max_iterations`` steps, fewer once a step moves less than 1 mm and
    0.3 mrad: :data:`_SETTLED_ROTATION_RAD`), ``p_begin`` held softly at ``p_before``
    (:data:`_BEGIN_PRIOR`) and ``p`` at the prediction ``pose`` (:data:`_END_PRIOR`).

    On hand-held shaking the LiDAR's translation turns from one sweep to the next (the more so
    the longer the lever arm): a translation deskewed with the previous motion, even once
    re-registered with the sweep's own, left scan-to-scan rotations 0.3 deg off on a shaking
    OS1-64 1.8 m from its IMU (0.1 deg with this registration) and hand-eye 0.6-0.8 deg off.

    Args:
        y: (N, 3) keypoints rotated into the LiDAR frame at the sweep's end (no translation).
        end_weight: (N,) weight of the end position for every keypoint, in [0, 1] (0 at the
            sweep's start, 1 at its end).
        p_before: (3,) map position of the previous scan's LiDAR origin.
        target: KD-tree of the local map points, the points (M, 3) and their normals (M, 3).
        pose: (4, 4) starting end pose ``T_map_lidar``.
        correspondence: largest point distance of a correspondence, metres.
        refine: settings.

    Returns:
        The end pose (4, 4), ``p_begin`` (3,) and the fitness (fraction of keypoints with a
        correspondence within ``correspondence``).
    """
    tree, q_all, n_all = target
    rot = np.array(pose[:3, :3], dtype=np.float64)
    pos = np.array(pose[:3, 3], dtype=np.float64)
    predicted = pos.copy()
    beg = np.array(p_before, dtype=np.float64)
    a = end_weight[:, None]
    k = float(refine.robust_scale)

    def correspondences() -> tuple[
        npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.int64]
    ]:
        ry = y @ rot.T
        world = ry + a * pos + (1.0 - a) * beg
        workers = threads() if world.shape[0] >= _PARALLEL_QUERY_POINTS else 1
        dist, idx = tree.query(world, distance_upper_bound=correspondence, workers=workers)
        return ry, np.flatnonzero(np.isfinite(dist)), idx

    for _ in range(int(refine.max_iterations)):
        ry, ok, idx = correspondences()
        if ok.shape[0] < 9:
            break
        q, n = q_all[idx[ok]], n_all[idx[ok]]
        world = ry[ok] + a[ok] * pos + (1.0 - a[ok]) * beg
        r = np.einsum("ij,ij->i", n, world - q)
        w = np.where(np.abs(r) < k, (1.0 - (r / k) ** 2) ** 2, 0.0)
        jac = np.concatenate([np.cross(ry[ok], n), a[ok] * n, (1.0 - a[ok]) * n], axis=1)
        h = (jac * w[:, None]).T @ jac
        g = (jac * w[:, None]).T @ r
        # p_begin is held at the previous scan's end with the weight of a thousandth of the
        # matched points: pinned there, an error of that pose turned this sweep's rotation.
        lam = _BEGIN_PRIOR * float(w.sum())
        h[6:, 6:] += lam * np.eye(3)
        g[6:] += lam * (beg - p_before)
        mu = _END_PRIOR * float(w.sum())
        h[3:6, 3:6] += mu * np.eye(3)
        g[3:6] += mu * (pos - predicted)
        h += 1e-9 * max(float(np.trace(h)), 1e-12) * np.eye(9)
        step = -np.linalg.solve(h, g)
        rot = Rotation.from_rotvec(step[:3]).as_matrix() @ rot
        pos = pos + step[3:6]
        beg = beg + step[6:]
        moved = max(float(np.linalg.norm(step[3:6])), float(np.linalg.norm(step[6:])))
        if np.linalg.norm(step[:3]) < _SETTLED_ROTATION_RAD and moved < _SETTLED_TRANSLATION_M:
            break  # the fitness is that of this step's correspondences (it moved so little)
    else:
        _, ok, _ = correspondences()
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, pos
    return out, beg, float(ok.shape[0]) / max(y.shape[0], 1)


_PIVOT_RIDGE = 0.01


class _PivotPrediction:
    """The next LiDAR position of a rig whose rotation is known: the LiDAR origin turns with the
    rig about the IMU, ``p_L(k) = p_I(k) + R_M_L(k) w`` with ``w`` (the IMU-to-LiDAR vector in
    the LiDAR frame) constant, and the IMU moves with constant velocity from scan to scan.

    A LiDAR on a long lever arm swings at the rig's angular rate: 1.8 m from the IMU of a rig
    turning 100 deg/s it moves 3 m/s in a direction that turns with the rig, which no constant
    LiDAR velocity predicts. A registration weak along one direction (the spin axis of a LiDAR
    scanning a room's floor, ceiling and two walls) keeps the prediction there, and the LiDAR's
    constant velocity drifted 4 m in 10 s (the trust benchmark's seed 8504, a HDL-32 mounted
    sideways 1.8 m from the IMU) where this prediction stays within 6 cm.

    ``w`` comes from every registered triple of scans, by least squares of the second
    differences ``p(k+1) - 2 p(k) + p(k-1) = (R(k+1) - 2 R(k) + R(k-1)) w`` (the IMU's own
    acceleration is the error), with a ridge :data:`_PIVOT_RIDGE` towards ``w = 0``, the
    constant LiDAR velocity, while the rotations have not varied enough to tell it.
    """

    def __init__(self) -> None:
        self._normal = _PIVOT_RIDGE * np.eye(3)
        self._rhs = np.zeros(3)

    def add(self, triple: npt.NDArray[np.float64]) -> None:
        """Take the lever arm's information from three consecutive poses (none when empty)."""
        if triple.shape[0] < 3:
            return
        a = triple[2, :3, :3] - 2.0 * triple[1, :3, :3] + triple[0, :3, :3]
        y = triple[2, :3, 3] - 2.0 * triple[1, :3, 3] + triple[0, :3, 3]
        self._normal += a.T @ a
        self._rhs += a.T @ y

    def predict(
        self,
        last: npt.NDArray[np.float64],
        rotation: npt.NDArray[np.float64],
        t_ns: npt.NDArray[np.int64],
    ) -> npt.NDArray[np.float64]:
        """The position at ``t_ns[2]`` from the two poses ``last`` at ``t_ns[:2]`` and the
        rotation there."""
        w = np.linalg.solve(self._normal, self._rhs)
        ratio = float(t_ns[2] - t_ns[1]) / float(t_ns[1] - t_ns[0])
        imu = last[:, :3, 3] - last[:, :3, :3] @ w
        return np.asarray(imu[1] + ratio * (imu[1] - imu[0]) + rotation @ w, dtype=np.float64)


def _registration_pass(
    sweeps: list[_Sweep],
    t_ns: npt.NDArray[np.int64],
    seed_rel: npt.NDArray[np.float64],
    previous: npt.NDArray[np.float64] | None,
    refine: RefineConfig,
    progress: Callable[[int], None] | None,
    seed_translation: bool = False,
    *,
    out: npt.NDArray[np.float64] | None = None,
    filled: Filled | None = None,
    previous_filled: Filled | None = None,
) -> tuple[npt.NDArray[np.float64], int]:
    """One pass of scan-to-local-map point-to-plane ICP over all K >= 2 scans.

    Args:
        sweeps: the K prepared scans.
        t_ns: (K,) reference time of every scan, ns.
        seed_rel: (K-1, 4, 4) relative poses whose rotations seed the first pass (and whose
            first one is the motion assumed for scans 0 and 1).
        previous: (K, 4, 4) poses of the previous pass, or None for the first pass. They give
            the motion within every sweep (cubic through the poses around it) and the starting
            relative poses. Without them a sweep is deskewed with the constant velocity of the
            two previous poses of this pass (rotation, unless the sweep has a rotation prior)
            and with its own motion (translation): with a rotation prior the registration
            estimates that motion with the pose (:func:`_register_with_sweep_motion`), without
            one the sweep is deskewed with the prediction.
        refine: settings.
        progress: optional callback with the number of scans done.
        seed_translation: the seed's relative translations come from a registration (kiss-icp
            without a rotation prior): the first pass starts each scan from the seed's whole
            relative pose instead of this pass's constant velocity. A registration weakly
            constrained along one direction then stays near the seed there; from its own
            velocity it ran away on an OS1-64 sinusoid (1.2 m per scan where kiss-icp had
            0.2 m), and the lever arm and the calibration with it.
        out: (K, 4, 4) array the poses are written to (returned); None: a new one.
        filled: told how many leading poses of ``out`` are final as the pass goes (a later
            pass running at the same time reads them); None: nobody waits.
        previous_filled: how many of ``previous`` are final, when the pass before is still
            running: scan ``k`` waits for its poses up to ``k + 1``.

    Returns:
        (K, 4, 4) poses (the first is the identity) and the number of rejected registrations.
    """
    o3d = _open3d()
    reg = o3d.pipelines.registration
    estimation = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=refine.robust_scale))
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=1e-4, relative_rmse=1e-4, max_iteration=refine.max_iterations
    )
    first = previous is None
    correspondence = refine.max_correspondence if first else refine.fine_correspondence
    k_total = len(sweeps)
    if out is None:
        out = np.empty((k_total, 4, 4), dtype=np.float64)
    out[0] = np.eye(4)
    window: list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]] = []

    def add_to_map(i: int, nodes: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]) -> None:
        pts, nrm = _deskew(sweeps[i], *nodes, keys_only=False)
        rot = out[i, :3, :3]
        window.append((pts @ rot.T + out[i, :3, 3], nrm @ rot.T))
        if len(window) > refine.map_scans:
            del window[0]

    def target() -> open3d.geometry.PointCloud:
        cloud = o3d.geometry.PointCloud(
            o3d.utility.Vector3dVector(np.concatenate([w[0] for w in window]))
        )
        cloud.normals = o3d.utility.Vector3dVector(np.concatenate([w[1] for w in window]))
        return cloud

    def linear_nodes(
        i: int,
        rel: npt.NDArray[np.float64],
        rel_span: float,
        rel_own: npt.NDArray[np.float64] | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        # Constant velocity over sweep i from rel (the motion over rel_span ns); rel_own (the
        # sweep's own motion) replaces the translation when given.
        span = float(t_ns[max(i, 1)] - t_ns[max(i, 1) - 1])
        xi = _log(np.asarray(np.linalg.inv(rel), dtype=np.float64)) * (span / rel_span)
        if rel_own is not None:
            xi[3:] = _log(np.asarray(np.linalg.inv(rel_own), dtype=np.float64))[3:]
        return np.array([-span, 0.0]), np.stack([xi, np.zeros(6)])

    def prediction(i: int) -> tuple[npt.NDArray[np.float64], float]:
        """Motion assumed for sweep ``i`` in the first pass and the time it spans, ns."""
        if i <= 1:
            return seed_rel[0], float(t_ns[1] - t_ns[0])
        return np.linalg.inv(out[i - 2]) @ out[i - 1], float(t_ns[i - 1] - t_ns[i - 2])

    def sweep_nodes(i: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        if previous is not None:
            idx = np.arange(0, 2) if i == 0 else np.arange(max(0, i - 2), min(k_total, i + 2))
            rel = np.linalg.inv(previous[i]) @ previous[idx]
            xi = np.concatenate(
                [Rotation.from_matrix(rel[:, :3, :3]).as_rotvec(), rel[:, :3, 3]], axis=1
            )
            return (t_ns[idx] - t_ns[i]).astype(np.float64), xi
        return linear_nodes(i, *prediction(i))

    def wait_for_previous(i: int) -> None:
        # sweep i reads the previous pass's poses up to i + 1 (its nodes and its guess)
        if previous_filled is not None:
            previous_filled.wait_for(min(k_total, i + 2))

    wait_for_previous(0)
    add_to_map(0, sweep_nodes(0))
    if filled is not None:
        filled.publish(1)
    n_rejected = 0
    pivot = _PivotPrediction()
    for i in range(1, k_total):
        wait_for_previous(i)
        if previous is not None:
            guess = out[i - 1] @ np.linalg.inv(previous[i - 1]) @ previous[i]
        elif seed_translation:
            guess = out[i - 1] @ seed_rel[i - 1]
        elif i >= 2:
            # Translation from the constant velocity, rotation from the seed.
            step = np.linalg.inv(out[i - 2]) @ out[i - 1]
            step[:3, 3] *= float(t_ns[i] - t_ns[i - 1]) / float(t_ns[i - 1] - t_ns[i - 2])
            step[:3, :3] = seed_rel[i - 1, :3, :3]
            guess = out[i - 1] @ step
            if sweeps[i].rot_to_end is not None:
                # The rotation is the gyro's: the LiDAR turns about the IMU, whose own
                # velocity is the one held constant.
                if i >= 3:
                    pivot.add(out[i - 3 : i])
                guess[:3, 3] = pivot.predict(out[i - 2 : i], guess[:3, :3], t_ns[i - 2 : i + 1])
        else:
            guess = seed_rel[0]
        sweep = sweeps[i]
        if first and sweep.rot_to_end is not None:
            # The rotation within the sweep is known: register the end pose together with
            # the translation within the sweep.
            span = float(t_ns[i] - t_ns[i - 1])
            keys = sweep.keys
            y = np.einsum("nij,nj->ni", sweep.rot_to_end[keys], sweep.xyz[keys])
            end_weight = np.clip(1.0 + sweep.dt_ns[keys] / span, 0.0, 1.0)
            pts = np.concatenate([w[0] for w in window])
            pose, p_begin, fitness = _register_with_sweep_motion(
                y,
                end_weight,
                out[i - 1, :3, 3],
                (cKDTree(pts), pts, np.concatenate([w[1] for w in window])),
                guess,
                correspondence,
                refine,
            )
            tau = pose[:3, :3].T @ (p_begin - pose[:3, 3])
            nodes = (np.array([-span, 0.0]), np.stack([np.r_[0.0, 0.0, 0.0, tau], np.zeros(6)]))
        else:
            nodes = sweep_nodes(i)
            src, _ = _deskew(sweep, *nodes, keys_only=True)
            result = reg.registration_icp(
                o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)),
                target(),
                correspondence,
                guess,
                estimation,
                criteria,
            )
            pose = np.asarray(result.transformation, dtype=np.float64)
            fitness = float(result.fitness)
        if fitness >= refine.min_fitness:
            out[i] = pose
        else:
            out[i] = guess
            n_rejected += 1
        if filled is not None:
            filled.publish(i + 1)
        add_to_map(i, nodes)
        if progress is not None:
            progress(i + 1)
    return out, n_rejected


def _registration_passes(
    sweeps: list[_Sweep],
    t_ns: npt.NDArray[np.int64],
    seed_rel: npt.NDArray[np.float64],
    refine: RefineConfig,
    n_passes: int,
    progress: ProgressFn | None,
    seed_translation: bool,
) -> tuple[npt.NDArray[np.float64], int]:
    """``n_passes`` registration passes (:func:`_registration_pass`), each from the one before.

    Sweep ``k`` of a pass needs the pass before only up to sweep ``k + 1``, so with a second
    thread (:func:`~licalib_cli.parallel.threads.threads`) each pass runs one or two sweeps
    behind the one before instead of after it: open3d's ICP, most of a pass, runs without the
    GIL. Every pass computes what it computes alone (open3d runs on one thread in either), so
    the poses are the same. Progress counts the sweeps of every pass done.

    Returns:
        The last pass's (K, 4, 4) poses and its number of rejected registrations.
    """
    k_total = len(sweeps)
    total = n_passes * k_total
    outs = [np.empty((k_total, 4, 4), dtype=np.float64) for _ in range(n_passes)]
    if n_passes < 2 or threads() < 2:
        previous: npt.NDArray[np.float64] | None = None
        n_rejected = 0
        for p in range(n_passes):

            def tick(done: int, p: int = p) -> None:
                if progress is not None:
                    progress(p * k_total + done, total)

            previous, n_rejected = _registration_pass(
                sweeps, t_ns, seed_rel, previous, refine, tick, seed_translation, out=outs[p]
            )
        assert previous is not None
        return previous, n_rejected
    filled = [Filled() for _ in range(n_passes)]
    failures: list[BaseException] = []

    def earlier_pass(p: int) -> None:
        try:
            with serial():
                _registration_pass(
                    sweeps,
                    t_ns,
                    seed_rel,
                    outs[p - 1] if p else None,
                    refine,
                    None,
                    seed_translation,
                    out=outs[p],
                    filled=filled[p],
                    previous_filled=filled[p - 1] if p else None,
                )
        except BaseException as err:
            failures.append(err)
            filled[p].fail()

    workers = [
        threading.Thread(target=earlier_pass, args=(p,), name=f"licalib-odometry-pass-{p}")
        for p in range(n_passes - 1)
    ]
    for worker in workers:
        worker.start()

    def tick_all(done: int) -> None:
        # the earlier passes are ahead of the last one: their sweeps done, and its own
        if progress is not None:
            progress(sum(f.count for f in filled[:-1]) + done, total)

    try:
        result = _registration_pass(
            sweeps,
            t_ns,
            seed_rel,
            outs[-2],
            refine,
            tick_all,
            seed_translation,
            out=outs[-1],
            previous_filled=filled[-2],
        )
    except RuntimeError:
        if failures:  # a pass before this one failed: its error, not the wait's
            raise failures[0] from None
        raise
    finally:
        for worker in workers:  # before any error leaves: no pass outlives the call
            worker.join()
    if failures:
        raise failures[0]
    return result


MIN_KEYPOINTS = 1000
"""The keypoints a sweep should have (median over the recording) for the refinement's
registration: a simulated spinning LiDAR in a room has 1150-2400 at the lengths of
:class:`RefineConfig` (a VLP-16 1150-1350), an Avia-like rosette 60-620."""

MIN_SCENE_SCALE = 0.25
"""The refinement's lengths shrink (:func:`scene_scale`) down to this fraction (the keypoints of
a sweep grow about as the inverse square)."""

SCALE_SWEEPS = 20
"""Sweeps, spread over the recording, whose keypoints :func:`scene_scale` counts."""

_SCALE_STEP = 1.2
"""The scales tried: 1, 1 / 1.2, 1 / 1.2^2, ... down to :data:`MIN_SCENE_SCALE`."""


def scene_scale(
    clouds: Sequence[npt.NDArray[np.float64]], refine: RefineConfig | None = None
) -> float:
    """The factor of the refinement's lengths for the scene of ``clouds`` (every sweep's points
    within the range filter): the largest of 1, 1/1.2, 1/1.2^2, ... (at least
    :data:`MIN_SCENE_SCALE`) at which the median sweep has :data:`MIN_KEYPOINTS` keypoints
    (:data:`SCALE_SWEEPS` sweeps spread over the recording are counted).

    The lengths (:class:`RefineConfig`: 0.4 m keypoint voxels, 0.25 m map voxels, 0.6 m normal
    radius and correspondence distance) were made for spinning LiDARs in rooms. A narrow field
    of view sees a few metres of a scene: an Avia-like rosette (70 x 77 deg) shaken 1.6 m
    (median range) from the walls had 60 keypoints a sweep, and its gyro-aided odometry over
    10 s, with the true calibration, was 43 cm off the truth (median) in each scan's motion
    from the one before, where the rig moved 3.6 cm: a 46 m path for a 3.6 m one. At a quarter
    of the lengths (1000 keypoints) it is 2.9 cm off and the path 5.0 m. The same rosette on a
    sinusoid 3.6 m from the walls (220 keypoints) drifted up to 9.7 m from the truth, and 0.5 m
    at 0.37 of the lengths (1650 keypoints).
    """
    refine = refine or RefineConfig()
    counted = [c for c in clouds[:: max(1, len(clouds) // SCALE_SWEEPS)] if c.shape[0]]
    if not counted:
        return 1.0
    scale = 1.0
    while True:
        kept = [c[_voxel_first(c, refine.map_voxel_size * scale)] for c in counted]
        count = np.median([len(_voxel_first(c, refine.voxel_size * scale)) for c in kept])
        if count >= MIN_KEYPOINTS or scale <= MIN_SCENE_SCALE:
            return scale
        scale = max(scale / _SCALE_STEP, MIN_SCENE_SCALE)


def at_scale(refine: RefineConfig, scale: float) -> RefineConfig:
    """``refine`` with its lengths of the scene (voxels, normal radius, correspondence
    distances) times ``scale``; the robust scale, which is the points' noise, stays."""
    if scale == 1.0:
        return refine
    return replace(
        refine,
        voxel_size=refine.voxel_size * scale,
        map_voxel_size=refine.map_voxel_size * scale,
        normal_radius=refine.normal_radius * scale,
        max_correspondence=refine.max_correspondence * scale,
        fine_correspondence=refine.fine_correspondence * scale,
    )


@dataclass(frozen=True)
class PreparedSweeps:
    """The scans' points prepared for :func:`refine_odometry`, independent of any rotation prior.

    Preparing (range filter, voxel thinning, normals, keypoints) costs about as much as one
    registration pass; a caller that refines the same scans several times (with different
    rotation priors) prepares them once.

    Attributes:
        t_ns: (K,) int64 reference (latest point) time of every scan, ns.
        sweeps: the K prepared scans (without rotation prior).
        settings: the range limits and voxel sizes asked for (before ``scale``).
        scale: the factor of the refinement's lengths for this scene (:func:`scene_scale`).
    """

    t_ns: npt.NDArray[np.int64]
    sweeps: tuple[_Sweep, ...]
    settings: tuple[float, ...]
    scale: float = 1.0

    def __len__(self) -> int:
        return len(self.sweeps)


def _prepare_settings(kcfg: KISSConfig, refine: RefineConfig) -> tuple[float, ...]:
    return (
        float(kcfg.data.min_range),
        float(kcfg.data.max_range),
        float(refine.map_voxel_size),
        float(refine.voxel_size),
        float(refine.normal_radius),
        float(refine.normal_neighbors),
    )


def _reference_times(scans: Sequence[LidarScan]) -> npt.NDArray[np.int64]:
    """(K,) latest point time of every scan, ns.

    Raises:
        DataError: the scans are out of time order.
    """
    t_out = np.array([int(s.t_ns.max()) for s in scans], dtype=np.int64)
    bad = np.flatnonzero(np.diff(t_out) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        msg = (
            f"LiDAR scan {i} refers to time {t_out[i]} ns, not after scan {i - 1} "
            f"({t_out[i - 1]} ns); sort the scans by time and drop duplicates."
        )
        raise DataError(msg)
    return t_out


def prepare_sweeps(
    scans: Sequence[LidarScan], cfg: OdometryConfig, refine: RefineConfig | None = None
) -> PreparedSweeps:
    """Range filter, map points with normals and keypoints of every scan.

    Normals come from the raw points of the scan itself: neighbouring points of a spinning
    LiDAR are fired within microseconds, so motion does not bend a neighbourhood.

    Raises:
        DataError: no scans, a scan without points in range, or scans out of time order.
        ConfigError: inconsistent range limits.
    """
    o3d = _open3d()
    refine = refine or RefineConfig()
    if len(scans) == 0:
        msg = "No LiDAR scans to run odometry on; check the LiDAR topic and the time window."
        raise DataError(msg)
    if any(len(s) == 0 for s in scans):
        msg = "A LiDAR scan has no points; drop empty scans before odometry."
        raise DataError(msg)
    kcfg = kiss_icp_config(cfg)
    t_ref = _reference_times(scans)
    in_range = []
    for i, scan in enumerate(scans):
        rng = norms(scan.xyz)
        keep = (rng >= kcfg.data.min_range) & (rng <= kcfg.data.max_range)
        if not np.any(keep):
            msg = (
                f"LiDAR scan {i} (stamp {scan.stamp_ns} ns) has no point between "
                f"{kcfg.data.min_range:g} m and {kcfg.data.max_range:g} m; check the range "
                "limits of the odometry and the point units."
            )
            raise DataError(msg)
        in_range.append(keep)
    # the scale from the sweeps it counts (a copy of every scan's points at once would double
    # the memory the scans hold)
    counted = range(0, len(scans), max(1, len(scans) // SCALE_SWEEPS))
    asked = refine
    scale = scene_scale([scans[i].xyz[in_range[i]] for i in counted], refine)
    refine = at_scale(refine, scale)
    search = o3d.geometry.KDTreeSearchParamHybrid(
        radius=refine.normal_radius, max_nn=refine.normal_neighbors
    )
    sweeps = []
    for i, (scan, keep) in enumerate(zip(scans, in_range, strict=True)):
        xyz = np.asarray(scan.xyz[keep], dtype=np.float64)
        n_points = xyz.shape[0]
        sel = _voxel_first(xyz, refine.map_voxel_size)
        xyz = xyz[sel]
        dt = np.asarray(scan.t_ns[keep][sel], dtype=np.int64) - t_ref[i]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        cloud.estimate_normals(search)
        sweeps.append(
            _Sweep(
                n_points=n_points,
                xyz=xyz,
                normals=np.asarray(cloud.normals, dtype=np.float64),
                dt_ns=dt,
                rot_to_end=None,
                keys=_voxel_first(xyz, refine.voxel_size),
            )
        )
    if scale < 1.0:
        logger.info(
            "odometry: a sweep has %d keypoints (median) at %.2f of the refinement's voxels "
            "and distances, which the registration uses.",
            int(np.median([s.keys.shape[0] for s in sweeps])),
            scale,
        )
    return PreparedSweeps(t_ref, tuple(sweeps), _prepare_settings(kcfg, asked), scale)


def _with_rotation_prior(prepared: PreparedSweeps, rotation_at: RotationAt | None) -> list[_Sweep]:
    """The prepared sweeps with ``R_end^T R(t)`` of every point from ``rotation_at`` (one call
    for all points of all scans)."""
    if rotation_at is None:
        return list(prepared.sweeps)
    sizes = [s.dt_ns.shape[0] for s in prepared.sweeps]
    t_pts = np.concatenate(
        [s.dt_ns + t for s, t in zip(prepared.sweeps, prepared.t_ns, strict=True)]
    )
    owner = np.repeat(np.arange(len(sizes)), sizes)
    r_end = np.asarray(rotation_at(prepared.t_ns).as_matrix())
    r_pts = np.asarray(rotation_at(t_pts).as_matrix())
    rel = np.einsum("nji,njk->nik", r_end[owner], r_pts)  # R_end^T R(t)
    out = []
    for s, part in zip(prepared.sweeps, np.split(rel, np.cumsum(sizes)[:-1]), strict=True):
        rot = np.ascontiguousarray(part) if np.any(s.dt_ns) else None
        out.append(replace(s, rot_to_end=rot))
    return out


def refine_odometry(
    scans: Sequence[LidarScan],
    poses: PoseSeries | None,
    cfg: OdometryConfig,
    refine: RefineConfig | None = None,
    *,
    rotation_at: RotationAt | None = None,
    progress: ProgressFn | None = None,
    prepared: PreparedSweeps | None = None,
) -> PoseSeries:
    """Re-register every scan against a local map with point-to-plane ICP, seeded by ``poses``.

    Point-to-point ICP on sparse multi-beam rings is biased (rings lock onto rings), which
    leaves kiss-icp's scan-to-scan rotations off by a degree or more; point-to-plane residuals
    let the rings slide along the surfaces. Each pass goes through the scans in order; for
    scan ``k``:

    1. deskew the keypoints (range filter of ``cfg``, then ``refine.map_voxel_size`` and
       ``refine.voxel_size`` voxels, each point keeping its own time; these and the normal
       radius and correspondence distances times the scene's :func:`scene_scale`) into the
       LiDAR frame at the scan's latest point time. First pass: rotation with the constant
       velocity of the two previous refined poses (a prediction: an error of this scan's pose
       cannot feed back into its own deskew, which for a spinning LiDAR hardly constrains the
       rate about its spin axis), translation with the prediction. Later passes: cubic through
       the previous pass's poses around the sweep. With ``rotation_at`` the rotation within
       every sweep comes from it instead;
    2. point-to-plane ICP (Tukey kernel) against the local map, starting from pose ``k - 1``
       times the seed relative pose: in the first pass kiss-icp's rotation with the
       constant-velocity translation, or ``rotation_at``'s with the translation of a LiDAR
       turning about an IMU of constant velocity (:class:`_PivotPrediction`), later the
       previous pass's.
       In the first pass with ``rotation_at`` the translation within the sweep is not taken
       from the prediction but estimated with the pose: the LiDAR origin moves linearly from
       the sweep's start (held softly at the previous scan's end) to its end
       (:func:`_register_with_sweep_motion`);
    3. the deskewed map points and their normals, mapped with the new pose, join the local
       map (the last ``refine.map_scans`` scans).

    Before the first pass the first ``refine.warmup_scans`` scans are refined on their own
    (two passes) and seed it, since kiss-icp's first motions deskew them poorly and the first
    map holds a single scan. A registration matching fewer than ``refine.min_fitness`` of the
    keypoints keeps the seed relative pose for that scan.

    Args:
        scans: the K scans given to :func:`run_odometry`, in time order.
        poses: kiss-icp poses of those scans (:func:`run_odometry`), or None with
            ``rotation_at``: the gyro alone predicts (rotation from ``rotation_at``, the
            translation of the first motion zero, then that of a LiDAR turning about an IMU of
            constant velocity).
        cfg: odometry settings (the range filter is shared with kiss-icp).
        refine: refinement settings; defaults when None.
        rotation_at: optional ``R_w_lidar(t)`` (e.g. the gyro with a rotation extrinsic, see
            :func:`licalib_cli.initialization.rotation.lidar_rotation_at`) giving the rotation
            within each sweep and the first pass's seed rotations. An extrinsic a few degrees
            off still deskews far better than any constant velocity on fast motion.
        progress: optional ``progress(done, total)`` callback; ``total`` is K times the passes.
        prepared: ``scans`` already prepared with :func:`prepare_sweeps` (same ``cfg`` and
            ``refine``), to skip that work when the same scans are refined again.

    Returns:
        One pose per scan in the frame of scan 0, each referring to (and stamped with) the
        latest point time of its scan. ``threshold_m`` holds the correspondence distance of the
        last pass, ``n_keypoints`` the keypoints registered, and ``deviation_m``/
        ``deviation_deg`` the difference between the refined and the seed (kiss-icp, or the
        gyro without ``poses``) relative pose from the previous scan (0 for scan 0).

    Raises:
        DataError: the scans and poses differ in number, there are no scans, a scan has no
            point in range, the scans are out of time order, or neither poses nor a rotation
            prior are given.
        ConfigError: inconsistent range limits.
    """
    refine = refine or RefineConfig()
    k_total = len(scans)
    if poses is None and rotation_at is None:
        msg = "Odometry refinement needs seed poses or a rotation prior; run run_odometry first."
        raise DataError(msg)
    if poses is not None and k_total != len(poses):
        msg = (
            f"Odometry refinement got {k_total} scans but {len(poses)} poses; pass the scans "
            "that run_odometry registered."
        )
        raise DataError(msg)
    if prepared is None:
        prepared = prepare_sweeps(scans, cfg, refine)
    elif len(prepared) != k_total or prepared.settings != _prepare_settings(
        kiss_icp_config(cfg), refine
    ):
        msg = (
            "The prepared sweeps do not belong to these scans and settings; prepare them with "
            "prepare_sweeps(scans, cfg, refine)."
        )
        raise DataError(msg)
    t_out = prepared.t_ns
    sweeps = _with_rotation_prior(prepared, rotation_at)
    refine = at_scale(refine, prepared.scale)

    if poses is not None:
        seed_rel = np.linalg.inv(poses.T_map_lidar[:-1]) @ poses.T_map_lidar[1:]
    else:
        seed_rel = np.eye(4)[None].repeat(max(k_total - 1, 0), axis=0)
    kiss_rel = seed_rel.copy()
    if rotation_at is not None and k_total > 1:
        r_w = rotation_at(t_out)
        seed_rel[:, :3, :3] = (r_w[:-1].inv() * r_w[1:]).as_matrix()
        if poses is None:
            kiss_rel = seed_rel.copy()
    seed_translation = poses is not None and rotation_at is None
    n_passes = max(int(refine.passes), 1)
    n_warm = min(k_total, int(refine.warmup_scans))
    if n_warm > 2:
        # Warm-up on the first scans: kiss-icp's first motions deskew them poorly and the
        # first map has a single scan, so register them twice and seed the pass with that.
        head = (sweeps[:n_warm], t_out[:n_warm], seed_rel[: n_warm - 1])
        warm, _ = _registration_pass(*head, None, refine, None, seed_translation)
        warm, _ = _registration_pass(*head, warm, refine, None)
        seed_rel[: n_warm - 1] = np.linalg.inv(warm[:-1]) @ warm[1:]
    out = np.eye(4)[None].repeat(k_total, axis=0)
    n_rejected = 0
    if k_total > 1:
        out, n_rejected = _registration_passes(
            sweeps, t_out, seed_rel, refine, n_passes, progress, seed_translation
        )
    if progress is not None:
        progress(n_passes * k_total, n_passes * k_total)
    if n_rejected:
        logger.warning(
            "odometry refinement: %d of %d registrations matched too few keypoints; kept the "
            "seed motion there",
            n_rejected,
            k_total - 1,
        )
    deviation = np.linalg.inv(kiss_rel) @ (np.linalg.inv(out[:-1]) @ out[1:])
    dev_m = np.zeros(k_total, dtype=np.float64)
    dev_deg = np.zeros(k_total, dtype=np.float64)
    if k_total > 1:
        dev_m[1:] = np.linalg.norm(deviation[:, :3, 3], axis=1)
        dev_deg[1:] = np.degrees(Rotation.from_matrix(deviation[:, :3, :3]).magnitude())
    logger.info(
        "refined odometry: %d scans, %d passes, %.1f m path, max deviation from kiss-icp "
        "%.3f m / %.2f deg",
        k_total,
        n_passes,
        float(np.linalg.norm(np.diff(out[:, :3, 3], axis=0), axis=1).sum()),
        float(dev_m.max()),
        float(dev_deg.max()),
    )
    last = refine.max_correspondence if n_passes == 1 else refine.fine_correspondence
    return PoseSeries(
        t_ns=t_out,
        T_map_lidar=out,
        n_points=np.array([s.n_points for s in sweeps], dtype=np.int64),
        n_keypoints=np.array([s.keys.shape[0] for s in sweeps], dtype=np.int64),
        threshold_m=np.full(k_total, last, dtype=np.float64),
        deviation_m=dev_m,
        deviation_deg=dev_deg,
    )
