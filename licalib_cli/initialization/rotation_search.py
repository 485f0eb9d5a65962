"""Rotation extrinsic by map sharpness: a global search that needs no LiDAR odometry.

Hand-eye needs the LiDAR's own rotation between scans, and a LiDAR-only odometry cannot follow
violent hand-held motion (a sweep rotating by 10-20 degrees, the rate changing within it). The
gyro can, but deskewing with the gyro needs the very rotation extrinsic that is sought. This
module breaks the circle: for a candidate ``R_imu_lidar`` every point of a short window is
rotated into a fixed frame with the gyro orientation at its own time,

    ``p_ref = R_ref_imu(tau + t_c) R_imu_lidar p_lidar``

(translation ignored: within half a second a hand-held rig moves a few decimetres), and the
number of occupied voxels of the resulting cloud is counted. The true extrinsic gives the
sharpest cloud, i.e. the fewest voxels; a wrong one smears every surface by the angle error
times the range as the rig turns. A uniform coarse grid over SO(3) (super-Fibonacci spiral)
followed by local shrinking searches around the best candidates finds the minimum without any
initial guess; rotation about a single axis leaves the result ambiguous, which the returned
``ambiguity`` (score of the best candidate at least ``min_separation_deg`` away, relative to
the best) shows.

Conventions: ``R_imu_lidar`` maps LiDAR vectors into the IMU frame; ``t_imu = t_lidar + t_c``;
times are int64 nanoseconds at the interface.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from licalib_cli.errors import ExcitationError
from licalib_cli.geometry.vectors import norms
from licalib_cli.initialization.rotation import GyroIntegrator
from licalib_cli.measurements import LidarScan
from licalib_cli.parallel.threads import map_slices

__all__ = [
    "MIN_AMBIGUITY",
    "MIN_NORMAL_SHARPENING",
    "MIN_SHARPENING",
    "RotationSearch",
    "RotationSearchConfig",
    "search_rotation_and_time_offset",
    "search_rotation_extrinsic",
    "super_fibonacci_rotations",
]

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

# Golden-ratio-like constants of the super-Fibonacci spiral (Alexa, CVPR 2022).
_PHI = np.sqrt(2.0)
_PSI = 1.533751168755204288118041


@dataclass(frozen=True)
class RotationSearchConfig:
    """Settings of :func:`search_rotation_extrinsic`.

    Attributes:
        window_scans: consecutive scans per window (the translation within it is ignored).
        num_windows: windows used, the most rotation-rich ones of the segment.
        points_per_scan: points drawn from each scan of a window.
        voxel_size_m: voxel of the sharpness count, metres.
        min_range_m: points closer than this are not used, metres.
        max_range_m: points farther than this are not used, metres.
        coarse_candidates: quaternions of the uniform coarse grid (covering S^3, so about half
            as many distinct rotations).
        refine_starts: best coarse candidates (at least ``min_separation_deg`` apart) refined.
        refine_scales_deg: radii of the successive local searches, degrees.
        refine_samples: random perturbations per local search.
        min_separation_deg: candidates closer than this count as the same solution.
        seed: seed of the local-search perturbations (the result is deterministic).
        normal_window_scans: consecutive scans per window of the surface-normal score.
        normal_cell_m: cell size of the planar patches of one scan, metres.
        normal_min_points: points a cell needs to give a patch.
        normal_min_planarity: plane-likeness ``2 (l1 - l0) / (l0 + l1 + l2)`` a patch needs.
        normal_bin: bin size of the normal directions on the unit sphere (about 6 deg).
        log_level: level of the line that reports the search (the offset scan's many cheaper
            searches log theirs at DEBUG).
    """

    window_scans: int = 5
    num_windows: int = 3
    points_per_scan: int = 600
    voxel_size_m: float = 0.3
    min_range_m: float = 1.0
    max_range_m: float = 60.0
    coarse_candidates: int = 3000
    refine_starts: int = 4
    refine_scales_deg: tuple[float, ...] = (12.0, 6.0, 3.0, 1.5)
    refine_samples: int = 40
    min_separation_deg: float = 30.0
    seed: int = 0
    normal_window_scans: int = 10
    normal_cell_m: float = 1.0
    normal_min_points: int = 8
    normal_min_planarity: float = 0.7
    normal_bin: float = 0.1
    log_level: int = logging.INFO
    use_points: bool = True
    use_normals: bool = True


@dataclass(frozen=True)
class RotationSearch:
    """Result of the sharpness search.

    Attributes:
        R_imu_lidar: (3, 3) the sharpest rotation extrinsic.
        score: its sharpness score: occupied voxels of the points and occupied bins of the patch
            normals, each relative to a random rotation's, summed (lower is sharper).
        ambiguity: score of the best candidate at least ``min_separation_deg`` away divided by
            ``score`` (close to 1: the data cannot tell them apart).
        smear_score: median score over the coarse grid (what a random rotation gives).
        windows: (W, 2) int first and last scan index of each window used.
        time_offset_s: the time offset ``t_imu = t_lidar + time_offset_s`` the points were
            rotated with, s.
        normal_sharpening: how much sharper the best rotation makes the distribution of surface
            normals than a random rotation (None: no planar patches).
    """

    R_imu_lidar: FloatArray
    score: float
    ambiguity: float
    smear_score: float
    windows: npt.NDArray[np.int64]
    time_offset_s: float = 0.0
    normal_sharpening: float | None = None

    @property
    def unambiguous(self) -> bool:
        """Whether no distinct rotation makes the clouds nearly as sharp
        (:data:`MIN_AMBIGUITY`)."""
        return self.ambiguity >= MIN_AMBIGUITY

    @property
    def sharpening(self) -> float:
        """How much sharper the best rotation makes the clouds than a random one
        (``smear_score / score``)."""
        return self.smear_score / self.score

    @property
    def clear(self) -> bool:
        """Unambiguous, and sharp enough to have been searched near the right time offset: the
        surface normals at least :data:`MIN_NORMAL_SHARPENING` times sharper than under a random
        rotation (without planar patches, the whole score :data:`MIN_SHARPENING` times)."""
        if not self.unambiguous:
            return False
        if self.normal_sharpening is not None:
            return self.normal_sharpening >= MIN_NORMAL_SHARPENING
        return self.sharpening >= MIN_SHARPENING


MIN_AMBIGUITY = 1.02
"""A search whose next distinct candidate scores less than this times the best cannot tell the
rotation (about one axis only, or points rotated with a time offset far from the true one)."""

MIN_NORMAL_SHARPENING = 1.45
"""On violent motion the best rotation at the right time offset makes the surface normals
1.61-1.96 times sharper than a random rotation does (shakes of 10 s, five LiDAR models, offsets
up to 0.19 s), still 1.54-1.64 times 30-50 ms from it (lever arms up to 1.9 m included: normals
do not move with the translation); 100 ms and more from it, 1.17-1.34 times, and the rotation
can even look unambiguous there (1.029 on an OS1-32 shake at +190 ms). Below this the time
offset is searched too, the search at the offset assumed being kept unless another is clearly
sharper (:data:`SCAN_GAIN`)."""

MIN_SHARPENING = 1.3
"""The same for the whole score when the windows hold no planar patches: 1.44-1.53 at the right
offset and 1.09-1.19 100 ms and more from it on the same shakes; a lever arm of metres blurs the
points too (1.27 at 30 ms on a shake with the LiDAR 1.8 m from the IMU), hence the normals
first."""

SCAN_GAIN = 1.05
"""An unambiguous search at the offset assumed is replaced by the offset scan's only when that
scores this many times lower (on slow motion the offset hardly changes the sharpness, and the
scan's minimum is noise)."""


def super_fibonacci_rotations(n: int) -> FloatArray:
    """(n, 4) ``[x, y, z, w]`` unit quaternions spread uniformly over S^3 (super-Fibonacci).

    Args:
        n: number of quaternions.

    Returns:
        The quaternions; ``q`` and ``-q`` both cover SO(3), so about ``n / 2`` distinct
        rotations with a covering radius of roughly ``(8 pi^2 / n)^(1/3)`` rad.
    """
    s = np.arange(n, dtype=np.float64) + 0.5
    r = np.sqrt(s / n)
    big_r = np.sqrt(1.0 - s / n)
    alpha = 2.0 * np.pi * s / _PHI
    beta = 2.0 * np.pi * s / _PSI
    return np.stack(
        [r * np.sin(alpha), r * np.cos(alpha), big_r * np.sin(beta), big_r * np.cos(beta)],
        axis=1,
    )


def _rotation_richness(gyro: GyroIntegrator, t_ns: npt.NDArray[np.int64]) -> float:
    """Second-largest RMS rotation angle (rad) about a principal axis within a window.

    ``t_ns`` (M,) are IMU times inside the window; the rotations are taken relative to the
    middle one. Rotation about a single axis scores zero: it cannot fix the extrinsic.
    """
    rot = gyro(t_ns)
    rel = (rot[len(t_ns) // 2].inv() * rot).as_rotvec()
    lam = np.linalg.eigvalsh(rel.T @ rel / len(t_ns))
    return float(np.sqrt(max(lam[1], 0.0)))


def _select_windows(
    scans: Sequence[LidarScan], gyro: GyroIntegrator, t_c_ns: int, cfg: RotationSearchConfig
) -> list[tuple[int, int]]:
    """The ``cfg.num_windows`` non-overlapping windows with the richest rotation."""
    w = max(int(cfg.window_scans), 2)
    lo, hi = int(gyro.t_ns[0]), int(gyro.t_ns[-1])
    starts = []
    scores = []
    for k in range(0, len(scans) - w + 1, w):  # loop over windows (a few per second of data)
        t_first = int(scans[k].t_ns.min()) + t_c_ns
        t_last = int(scans[k + w - 1].t_ns.max()) + t_c_ns
        if t_first < lo or t_last > hi:
            continue
        starts.append(k)
        scores.append(
            _rotation_richness(gyro, np.linspace(t_first, t_last, 4 * w).astype(np.int64))
        )
    order = np.argsort(scores)[::-1][: max(int(cfg.num_windows), 1)]
    return [(starts[i], starts[i] + w - 1) for i in sorted(order)]


def _window_points(
    scans: Sequence[LidarScan],
    window: tuple[int, int],
    gyro: GyroIntegrator,
    t_c_ns: int,
    cfg: RotationSearchConfig,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """Sampled points (N, 3) of a window and their gyro orientations (N, 3, 3).

    The orientations are relative to the IMU frame at the window's middle time.
    """
    pts, times = [], []
    for scan in scans[window[0] : window[1] + 1]:
        rho = norms(scan.xyz)
        t_imu = scan.t_ns + t_c_ns
        ok = np.flatnonzero(
            (rho >= cfg.min_range_m)
            & (rho <= cfg.max_range_m)
            & (t_imu >= gyro.t_ns[0])
            & (t_imu <= gyro.t_ns[-1])
        )
        if ok.size > cfg.points_per_scan:
            ok = rng.choice(ok, cfg.points_per_scan, replace=False)
        pts.append(scan.xyz[ok])
        times.append(t_imu[ok])
    xyz = np.concatenate(pts)
    t_ns = np.concatenate(times)
    rot = gyro(t_ns)
    mid = gyro(np.array([(int(t_ns.min()) + int(t_ns.max())) // 2], dtype=np.int64))
    return np.asarray(xyz, dtype=np.float64), np.asarray((mid.inv() * rot).as_matrix())


def _scan_normals(
    scan: LidarScan, cfg: RotationSearchConfig
) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """Unit normals (M, 3) of the planar patches of one scan (LiDAR frame) and their times.

    A patch is a cell of ``cfg.normal_cell_m`` with a plane-like point spread; its points were
    fired within a few milliseconds, so its normal is not distorted by the motion during the
    sweep. Normals face the sensor.
    """
    rho = norms(scan.xyz)
    ok = (rho >= cfg.min_range_m) & (rho <= cfg.max_range_m)
    xyz, t = scan.xyz[ok], scan.t_ns[ok]
    if xyz.shape[0] < cfg.normal_min_points:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    key = np.floor(xyz / cfg.normal_cell_m).astype(np.int64)
    key -= key.min(axis=0)
    span = key.max(axis=0) + 1
    flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]  # one integer per cell
    _, cell, counts = np.unique(flat, return_inverse=True, return_counts=True)
    order = np.argsort(cell, kind="stable")
    xyz, t, cell = xyz[order], t[order], cell[order]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n = counts[:, None].astype(np.float64)
    mean = np.add.reduceat(xyz, starts, axis=0) / n
    outer = np.add.reduceat(xyz[:, :, None] * xyz[:, None, :], starts, axis=0) / n[:, :, None]
    cov = outer - mean[:, :, None] * mean[:, None, :]
    t_mean = (np.add.reduceat((t - t[0]).astype(np.float64), starts) / n[:, 0]).astype(np.int64)
    use = counts >= cfg.normal_min_points
    lam, vec = np.linalg.eigh(cov[use])
    planar = 2.0 * (lam[:, 1] - lam[:, 0]) / np.maximum(lam.sum(axis=1), 1e-12)
    keep = planar >= cfg.normal_min_planarity
    normal = vec[keep, :, 0]
    flip = np.einsum("ij,ij->i", normal, mean[use][keep]) > 0.0
    normal[flip] *= -1.0
    return normal, t_mean[use][keep] + t[0]


def _window_normals(
    scans: Sequence[LidarScan],
    window: tuple[int, int],
    gyro: GyroIntegrator,
    t_c_ns: int,
    cfg: RotationSearchConfig,
) -> tuple[FloatArray, FloatArray]:
    """Patch normals (N, 3) of a window and their gyro orientations (N, 3, 3).

    The orientations are relative to the IMU frame at the window's middle time. Normals do not
    move when the rig translates, so the lever arm and the rig's translation do not blur them.
    """
    normals, times = [], []
    for scan in scans[window[0] : window[1] + 1]:
        nrm, t = _scan_normals(scan, cfg)
        t_imu = t + t_c_ns
        inside = (t_imu >= gyro.t_ns[0]) & (t_imu <= gyro.t_ns[-1])
        normals.append(nrm[inside])
        times.append(t_imu[inside])
    nrm = np.concatenate(normals)
    t_ns = np.concatenate(times).astype(np.int64)
    if t_ns.size == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    rot = gyro(t_ns)
    mid = gyro(np.array([(int(t_ns.min()) + int(t_ns.max())) // 2], dtype=np.int64))
    return np.asarray(nrm, dtype=np.float64), np.asarray((mid.inv() * rot).as_matrix())


class _CombinedScorer:
    """Sum of several scorers, each divided by its score of a random rotation."""

    def __init__(self, scorers: list[_Scorer], reference: FloatArray) -> None:
        self.scorers = scorers
        self.norms = [float(np.median(_batched(sc, reference))) or 1.0 for sc in scorers]

    def __call__(self, rotations: FloatArray) -> FloatArray:
        total = np.zeros(len(rotations))
        for sc, n in zip(self.scorers, self.norms, strict=True):
            total = total + sc(rotations) / n
        return total


class _Scorer:
    """Occupied-voxel count of the windows' clouds for candidate extrinsics."""

    def __init__(self, windows: list[tuple[FloatArray, FloatArray]], voxel: float) -> None:
        self.windows = windows
        self.voxel = voxel

    def __call__(self, rotations: FloatArray) -> FloatArray:
        """Scores of (C, 3, 3) candidate ``R_imu_lidar``; (C,) float64, lower is sharper."""
        out = np.zeros(rotations.shape[0])
        for xyz, rot in self.windows:  # a few windows
            # Rotated points of every candidate at once, (C, N, 3): p_ref = rot_n R_c p_n, as
            # three broadcast multiply-adds (several times faster than einsum here).
            p_imu = xyz @ rotations.transpose(0, 2, 1)
            p_ref = (
                rot[None, :, :, 0] * p_imu[..., 0:1]
                + rot[None, :, :, 1] * p_imu[..., 1:2]
                + rot[None, :, :, 2] * p_imu[..., 2:3]
            )
            key = np.floor(p_ref / self.voxel).astype(np.int64)
            flat = (key[..., 0] * 73856093) ^ (key[..., 1] * 19349663) ^ (key[..., 2] * 83492791)
            flat.sort(axis=1)
            out += 1.0 + np.count_nonzero(np.diff(flat, axis=1), axis=1)
        return out


def _batched(
    scorer: _Scorer | _CombinedScorer, rotations: FloatArray, batch: int = 64
) -> FloatArray:
    """Scores of ``rotations``, ``batch`` candidates at a time; the batches are independent,
    so they are shared between the threads of :mod:`licalib_cli.parallel.threads` (numpy works
    on each batch's large arrays without the GIL), with the scores of the serial loop."""
    return np.concatenate(map_slices(lambda sl: scorer(rotations[sl]), rotations.shape[0], batch))


def _distinct_best(
    rotations: FloatArray, scores: FloatArray, count: int, min_sep_rad: float
) -> list[int]:
    """Indices of the ``count`` best-scoring rotations at least ``min_sep_rad`` apart."""
    chosen: list[int] = []
    for i in np.argsort(scores):  # stops after a handful of accepted candidates
        if all(
            Rotation.from_matrix(rotations[i].T @ rotations[j]).magnitude() >= min_sep_rad
            for j in chosen
        ):
            chosen.append(int(i))
            if len(chosen) == count:
                break
    return chosen


def search_rotation_extrinsic(
    scans: Sequence[LidarScan],
    gyro: GyroIntegrator,
    time_offset_s: float = 0.0,
    cfg: RotationSearchConfig | None = None,
) -> RotationSearch:
    """Sharpest rotation extrinsic over all of SO(3), from scans and the gyro alone.

    Args:
        scans: the segment's scans (LiDAR frame, absolute per-point times), in time order.
        gyro: integrated gyro orientation over the segment.
        time_offset_s: ``t_imu = t_lidar + time_offset_s`` assumed, seconds (tens of
            milliseconds off only blur the clouds a little).
        cfg: search settings; defaults when None.

    Returns:
        The best rotation, its score and how ambiguous it is.

    Raises:
        ExcitationError: not enough scans overlapping the IMU data for one window.
    """
    cfg = cfg or RotationSearchConfig()
    t_c_ns = round(time_offset_s * 1e9)
    spans = _select_windows(scans, gyro, t_c_ns, cfg)
    if not spans:
        msg = (
            f"The rotation search needs {cfg.window_scans} consecutive LiDAR scans inside the "
            "IMU data; record longer or check the clock offset between the sensors."
        )
        raise ExcitationError(msg)
    rng = np.random.default_rng(cfg.seed)
    coarse = Rotation.from_quat(super_fibonacci_rotations(cfg.coarse_candidates)).as_matrix()
    normal_cfg = replace(cfg, window_scans=cfg.normal_window_scans)
    normal_spans = _select_windows(scans, gyro, t_c_ns, normal_cfg)
    normal_windows = [_window_normals(scans, w, gyro, t_c_ns, cfg) for w in normal_spans]
    normal_windows = [w for w in normal_windows if w[0].shape[0] > 0]
    scorers: list[_Scorer] = []
    if cfg.use_points:
        scorers.append(
            _Scorer(
                [_window_points(scans, w, gyro, t_c_ns, cfg, rng) for w in spans],
                cfg.voxel_size_m,
            )
        )
    normals = (
        _Scorer(normal_windows, cfg.normal_bin) if normal_windows and cfg.use_normals else None
    )
    if normals is not None:
        scorers.append(normals)
    scorer = _CombinedScorer(scorers, coarse[:: max(1, coarse.shape[0] // 200)])

    coarse_scores = _batched(scorer, coarse)
    min_sep = np.radians(cfg.min_separation_deg)
    starts = _distinct_best(coarse, coarse_scores, cfg.refine_starts, min_sep)

    found: list[FloatArray] = []
    found_scores: list[float] = []
    for i in starts:  # a few starts, each a short sequence of shrinking local searches
        best, best_score = coarse[i], float(coarse_scores[i])
        for scale in cfg.refine_scales_deg:
            vec = rng.normal(size=(cfg.refine_samples, 3))
            vec *= (np.radians(scale) * rng.uniform(0.0, 1.0, cfg.refine_samples) ** (1 / 3))[
                :, None
            ] / np.linalg.norm(vec, axis=1, keepdims=True)
            trial = best @ Rotation.from_rotvec(vec).as_matrix()
            scores = _batched(scorer, trial)
            j = int(np.argmin(scores))
            if scores[j] < best_score:
                best, best_score = trial[j], float(scores[j])
        found.append(best)
        found_scores.append(best_score)

    order = np.argsort(found_scores)
    best = found[order[0]]
    rivals = [
        found_scores[k]
        for k in order[1:]
        if Rotation.from_matrix(best.T @ found[k]).magnitude() >= min_sep
    ]
    far = Rotation.from_matrix(np.einsum("ji,cjk->cik", best, coarse)).magnitude() >= min_sep
    rival = min([*rivals, float(coarse_scores[far].min()) if np.any(far) else np.inf])
    result = RotationSearch(
        R_imu_lidar=np.asarray(best, dtype=np.float64),
        score=float(found_scores[order[0]]),
        ambiguity=float(rival / found_scores[order[0]]),
        smear_score=float(np.median(coarse_scores)),
        windows=np.asarray(spans, dtype=np.int64),
        time_offset_s=float(time_offset_s),
        # a random rotation's score of the normals (the combined score's norm) over the best's
        normal_sharpening=None
        if normals is None
        else float(scorer.norms[-1] / normals(np.asarray(best)[None])[0]),
    )
    logger.log(
        cfg.log_level,
        "rotation search: sharpest extrinsic scores %.3g (next distinct %.3fx, random %.2fx, "
        "normals %s) over windows %s at time offset %+.3f s",
        result.score,
        result.ambiguity,
        result.sharpening,
        "none" if result.normal_sharpening is None else f"{result.normal_sharpening:.2f}x",
        [tuple(w) for w in spans],
        time_offset_s,
    )
    return result


def _scan_config(cfg: RotationSearchConfig) -> RotationSearchConfig:
    """The cheaper search of the coarse scan over the lag: a quarter of the coarse grid and two
    local refinements (on the OS1-64 shake of :func:`search_rotation_and_time_offset` the
    same landscape over the offset as the full search, in half its time)."""
    return replace(
        cfg,
        coarse_candidates=max(200, cfg.coarse_candidates // 4),
        refine_starts=2,
        log_level=logging.DEBUG,
    )


def _duration_text(seconds: float) -> str:
    """``42 s`` or ``3.5 min`` or ``1.2 h``."""
    if seconds < 90.0:
        return f"{seconds:.0f} s"
    if seconds < 5400.0:
        return f"{seconds / 60.0:.1f} min"
    return f"{seconds / 3600.0:.1f} h"


def search_rotation_and_time_offset(
    scans: Sequence[LidarScan],
    gyro: GyroIntegrator,
    time_offset_s: float = 0.0,
    max_lag_s: float = 0.2,
    step_s: float = 0.02,
    cfg: RotationSearchConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> RotationSearch:
    """:func:`search_rotation_extrinsic`, with the time offset searched too when the rotation
    at the one assumed is not :attr:`RotationSearch.clear` (ambiguous, or hardly sharpening the
    surface normals: :data:`MIN_NORMAL_SHARPENING`).

    On violent motion an offset of tens of milliseconds smears the clouds as much as a rotation
    error of degrees (the rig turns some 90 deg/s): on a 10 s OS1-64 shake with a true offset of
    -44 ms, the search at 0 s found no rotation clearly sharper than a distinct other (1.007
    times its score) while at -40 ms it did (1.10 times). Far from the true offset the
    sharpness is flat and noisy (a VLP-16 shake at +180 ms: 1.75-1.79 from -0.2 to 0 s, 1.32 at
    +0.2 s), so stepping downhill from the assumed offset can stop at once or walk the wrong way.
    The whole lag is then scanned, every ``2 step_s`` within ``max_lag_s`` of
    ``time_offset_s``, with a cheaper search (:func:`_scan_config`); from the sharpest point of
    the scan the offset is stepped by ``step_s`` in the direction the score falls, as long as it
    falls and stays within the lag, and a parabola through the best step and its neighbours
    (they may lie a step beyond the lag, its vertex not) gives one more, all with the cheaper
    search (the rotation needs only a few degrees: the
    gyro-aided hand-eye rounds refine it). The full search at the sharpest offset is returned
    (its own ``time_offset_s``), unless the one at the offset assumed scores lower, or was
    unambiguous and is not :data:`SCAN_GAIN` times less sharp; offsets where the search cannot
    run (too few scans inside the IMU data) are skipped.

    The scan's length grows with the lag (``2 max_lag_s / (2 step_s) + 1`` searches): it is
    logged with the time it will take, from the first search's, and ``progress(done, total)``
    follows it.
    """
    cfg = cfg or RotationSearchConfig()
    first = search_rotation_extrinsic(scans, gyro, time_offset_s, cfg)
    if first.clear:
        return first
    logger.info(
        "The rotation search at the time offset assumed is %s; scanning the offset within "
        "+-%.3g s too.",
        "ambiguous" if not first.unambiguous else "hardly sharper than a random rotation",
        max_lag_s,
    )
    quick = _scan_config(cfg)
    tried: dict[float, float] = {}

    def score(t: float) -> float:
        """The cheaper search's score at offset ``t`` (inf where it cannot run)."""
        key = round(t, 6)
        if key not in tried:
            try:
                tried[key] = search_rotation_extrinsic(scans, gyro, key, quick).score
            except ExcitationError:
                tried[key] = math.inf
        return tried[key]

    def within(t: float) -> bool:
        return abs(t - time_offset_s) <= max_lag_s + 1e-9

    coarse = 2.0 * step_s
    half = math.floor(max_lag_s / coarse + 1e-9)
    grid = [time_offset_s + k * coarse for k in range(-half, half + 1)]
    began = time.perf_counter()
    score(time_offset_s)
    each = time.perf_counter() - began
    logger.info(
        "Offset scan: %d searches every %.0f ms, about %s (%.1f s each); "
        "initialization.time_offset_s or a smaller time_offset_max_lag_s shortens it.",
        len(grid),
        1e3 * coarse,
        _duration_text(each * len(grid)),
        each,
    )
    for done, t in enumerate(grid, start=1):
        score(t)
        if progress is not None:
            progress(done, len(grid))
    start = min(grid, key=score)
    logger.info(
        "Offset scan: sharpest at %+.3f s (%.3g; at the offset assumed %.3g).",
        start,
        score(start),
        score(time_offset_s),
    )
    best_t = start
    for direction in (-1.0, 1.0):
        t = start + direction * step_s
        while within(t) and score(t) < score(t - direction * step_s):
            best_t = t if score(t) < score(best_t) else best_t
            t += direction * step_s
        if best_t != start:
            break  # the score fell this way; the other side rises from the start
    # the parabola's neighbours may lie a step beyond the lag; its vertex may not
    f_lo, f_mid, f_hi = score(best_t - step_s), score(best_t), score(best_t + step_s)
    curvature = f_lo - 2.0 * f_mid + f_hi
    if math.isfinite(curvature) and curvature > 0.0:
        vertex = best_t + 0.5 * step_s * (f_lo - f_hi) / curvature
        vertex = min(max(vertex, time_offset_s - max_lag_s), time_offset_s + max_lag_s)
        best_t = vertex if score(vertex) < f_mid else best_t
    if round(best_t, 6) == round(time_offset_s, 6):
        return first
    try:
        found = search_rotation_extrinsic(scans, gyro, round(best_t, 6), cfg)
    except ExcitationError:
        return first
    if found.score > first.score or (first.unambiguous and found.score * SCAN_GAIN > first.score):
        return first
    return found
