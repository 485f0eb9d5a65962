"""Surfel map: planar voxels of an aggregated point cloud, and point-to-surfel association.

Conventions:
    - Input points are (N, 3) float64 metres, all in one frame (the map or the global frame);
      the caller transforms the scans first. Surfels are expressed in that same frame.
    - Cells are axis-aligned cubes ``floor(p / cell_size)``. With several cell sizes (coarse to
      fine), a coarse cell that is planar becomes one surfel and its points are not voxelised
      again; the points of non-planar coarse cells are re-voxelised at the next finer size.
    - Per cell: covariance of its points (population, ``1/n``), eigenvalues
      ``l0 <= l1 <= l2``, plane-likeness ``P = 2 (l1 - l0) / (l0 + l1 + l2)`` (1 for an evenly
      filled plane, 0 for a line or an isotropic blob).
    - A surfel is the plane ``n^T x + d = 0`` through the cell centroid with ``n`` the eigenvector
      of ``l0``, oriented so that ``d >= 0`` (the normal faces the frame origin); its closest
      point to the origin is ``-d n``. Thickness is ``sqrt(l0)`` (RMS distance to the plane).
    - Signed point-to-plane distance: ``n^T p + d``.
    - Everything is vectorised: grouping by sorting packed cell keys, sums by ``np.bincount``,
      batched ``eigh``; no Python loop over points or cells.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import DataError

__all__ = [
    "Association",
    "SurfelConfig",
    "Surfels",
    "associate_points",
    "build_surfels",
    "cell_keys",
    "subsample_per_group",
    "voxel_downsample",
]

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


@dataclass(frozen=True)
class SurfelConfig:
    """Surfel extraction and association settings.

    Attributes:
        cell_sizes: cell edge lengths, metres, coarse to fine (one entry = single resolution).
        min_points: fewest points for a cell to be considered.
        min_planarity: plane-likeness ``P`` a cell needs to become a surfel.
        max_thickness_m: largest RMS point-to-plane distance of a surfel; None disables.
        min_extent_ratio: the points must spread in the plane by at least this fraction of the
            cell size along both in-plane axes (``sqrt(l1) >= ratio * cell_size``): slivers of a
            plane cut by a cell corner give poorly determined normals. A plane filling the cell
            has ``sqrt(l1) ~ 0.29 * cell_size``.
        max_point_distance_m: a cell with any point farther than this from its fitted plane
            holds a second surface (an edge or corner of the scene, an object in front of a
            wall) and is left to the finer cells; None disables. A few such points hardly
            raise the cell's thickness, but the plane fitted through them is tilted and the
            other surface's points near the edge are associated with it: on a simulated
            OS1-64 shake without any noise this left t_y 1.4 mm off.
        max_distance_m: largest ``|n^T p + d|`` for a point to be associated.
        neighbors: also search the 26 neighbouring cells for points whose own cell has no
            surfel (the point must project inside one cell size of the surfel centroid).
    """

    cell_sizes: tuple[float, ...] = (1.0, 0.5)
    min_points: int = 10
    min_planarity: float = 0.6
    max_thickness_m: float | None = 0.1
    max_point_distance_m: float | None = None
    min_extent_ratio: float = 0.15
    max_distance_m: float = 0.05
    neighbors: bool = False


@dataclass(frozen=True)
class Surfels:
    """Planar cells of a map.

    Attributes:
        normal: (S, 3) unit plane normals, oriented so that ``d >= 0``.
        d: (S,) plane offsets, metres: ``n^T x + d = 0`` on the plane.
        centroid: (S, 3) mean of the cell's points, metres.
        thickness: (S,) ``sqrt(l0)``, RMS point-to-plane distance, metres.
        planarity: (S,) plane-likeness ``P``.
        eigenvalues: (S, 3) ascending covariance eigenvalues, m^2.
        n_points: (S,) points in the cell.
        level: (S,) index into ``cell_sizes`` of the surfel's cell.
        key: (S,) packed integer cell key at that level (see :func:`cell_keys`).
        cell_sizes: the cell sizes used, metres, coarse to fine.
    """

    normal: FloatArray
    d: FloatArray
    centroid: FloatArray
    thickness: FloatArray
    planarity: FloatArray
    eigenvalues: FloatArray
    n_points: IntArray
    level: IntArray
    key: IntArray
    cell_sizes: tuple[float, ...]

    def __len__(self) -> int:
        return int(self.d.shape[0])

    @property
    def closest_point(self) -> FloatArray:
        """(S, 3) closest-point parametrisation ``-d n`` of each plane, metres."""
        return -self.d[:, None] * self.normal


@dataclass(frozen=True)
class Association:
    """Points matched to surfels.

    Attributes:
        point_index: (M,) int64 index into the associated point array.
        surfel_index: (M,) int64 index into :class:`Surfels`.
        distance: (M,) float64 signed point-to-plane distance ``n^T p + d``, metres.
    """

    point_index: IntArray
    surfel_index: IntArray
    distance: FloatArray

    def __len__(self) -> int:
        return int(self.point_index.shape[0])

    def rms(self) -> float:
        """RMS point-to-plane distance, metres (NaN when empty)."""
        return float(np.sqrt(np.mean(self.distance**2))) if len(self) else float("nan")


def cell_keys(points: FloatArray, cell_size: float) -> IntArray:
    """Pack the integer cell coordinates ``floor(p / cell_size)`` into one int64 per point.

    Args:
        points: (N, 3) metres.
        cell_size: cell edge, metres.

    Returns:
        (N,) int64 keys (21 bits per axis).

    Raises:
        DataError: a point lies beyond +-2^20 cells from the origin.
    """
    ijk = np.floor(np.asarray(points, dtype=np.float64) / cell_size).astype(np.int64) + _OFFSET
    if ijk.size and (ijk.min() < 0 or ijk.max() > _MASK):
        msg = (
            f"Points lie too far from the origin for {cell_size:g} m cells; express the map in "
            "a frame near the data (for example the first scan) or use larger cells."
        )
        raise DataError(msg)
    return (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]


def _key_centers(keys: IntArray, cell_size: float) -> FloatArray:
    ijk = np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], axis=1)
    return (ijk - _OFFSET + 0.5).astype(np.float64) * cell_size


def _cell_statistics(
    points: FloatArray, keys: IntArray, cell_size: float
) -> tuple[IntArray, IntArray, IntArray, FloatArray, FloatArray]:
    """Group points by key; per-cell count, centroid and covariance.

    Returns:
        unique keys (C,), inverse (N,) cell of each point, counts (C,), centroids (C, 3),
        covariances (C, 3, 3).
    """
    uniq, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    centers = _key_centers(uniq, cell_size)
    local = points - centers[inv]  # small numbers: no cancellation in E[xx^T] - mu mu^T
    c = uniq.shape[0]
    s1 = np.stack([np.bincount(inv, local[:, j], minlength=c) for j in range(3)], axis=1)
    iu, ju = np.triu_indices(3)
    s2 = np.stack(
        [
            np.bincount(inv, local[:, i] * local[:, j], minlength=c)
            for i, j in zip(iu, ju, strict=True)
        ],
        axis=1,
    )
    n = counts.astype(np.float64)
    mu = s1 / n[:, None]
    cov = np.empty((c, 3, 3))
    cov[:, iu, ju] = s2 / n[:, None]
    cov[:, ju, iu] = cov[:, iu, ju]
    cov -= mu[:, :, None] * mu[:, None, :]
    return uniq, inv, counts.astype(np.int64), centers + mu, cov


def build_surfels(points: FloatArray, cfg: SurfelConfig | None = None) -> Surfels:
    """Extract planar cells from an aggregated point cloud.

    Args:
        points: (N, 3) float64 points in one frame, metres.
        cfg: settings; defaults when None.

    Returns:
        The surfel table (possibly empty).

    Raises:
        DataError: the cloud is not (N, 3) or not finite.
    """
    cfg = cfg or SurfelConfig()
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        msg = f"Surfel extraction needs finite (N, 3) points, got shape {pts.shape}."
        raise DataError(msg)
    active = np.ones(pts.shape[0], dtype=bool)
    parts: list[dict[str, np.ndarray]] = []
    for level, size in enumerate(cfg.cell_sizes):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        sub = pts[idx]
        keys = cell_keys(sub, size)
        uniq, inv, counts, centroid, cov = _cell_statistics(sub, keys, size)
        lam, vec = np.linalg.eigh(cov)
        lam = np.clip(lam, 0.0, None)
        total = lam.sum(axis=1)
        planarity = np.where(
            total > 0.0, 2.0 * (lam[:, 1] - lam[:, 0]) / np.maximum(total, 1e-300), 0.0
        )
        thickness = np.sqrt(lam[:, 0])
        good = (
            (counts >= cfg.min_points)
            & (planarity >= cfg.min_planarity)
            & (np.sqrt(lam[:, 1]) >= cfg.min_extent_ratio * size)
        )
        if cfg.max_thickness_m is not None:
            good &= thickness <= cfg.max_thickness_m
        normal = vec[:, :, 0]
        if cfg.max_point_distance_m is not None:
            dist = np.abs(np.einsum("ij,ij->i", normal[inv], sub - centroid[inv]))
            far = np.bincount(inv, dist > cfg.max_point_distance_m, minlength=uniq.shape[0])
            good &= far == 0
        d = -np.einsum("ij,ij->i", normal, centroid)
        flip = d < 0.0
        normal = np.where(flip[:, None], -normal, normal)
        d = np.abs(d)
        parts.append(
            {
                "normal": normal[good],
                "d": d[good],
                "centroid": centroid[good],
                "thickness": thickness[good],
                "planarity": planarity[good],
                "eigenvalues": lam[good],
                "n_points": counts[good],
                "level": np.full(int(good.sum()), level, dtype=np.int64),
                "key": uniq[good],
            }
        )
        active[idx[good[inv]]] = False
        logger.debug(
            "surfels: %.2f m cells: %d of %d cells planar", size, int(good.sum()), uniq.size
        )
    names = ("normal", "d", "centroid", "thickness", "planarity", "eigenvalues", "n_points")
    shapes = {"normal": (0, 3), "centroid": (0, 3), "eigenvalues": (0, 3)}
    cat = {
        k: (np.concatenate([p[k] for p in parts]) if parts else np.zeros(shapes.get(k, (0,))))
        for k in (*names, "level", "key")
    }
    return Surfels(
        normal=cat["normal"].astype(np.float64),
        d=cat["d"].astype(np.float64),
        centroid=cat["centroid"].astype(np.float64),
        thickness=cat["thickness"].astype(np.float64),
        planarity=cat["planarity"].astype(np.float64),
        eigenvalues=cat["eigenvalues"].astype(np.float64),
        n_points=cat["n_points"].astype(np.int64),
        level=cat["level"].astype(np.int64),
        key=cat["key"].astype(np.int64),
        cell_sizes=tuple(float(s) for s in cfg.cell_sizes),
    )


_NEIGHBOR_OFFSETS = np.array(
    [
        (i, j, k)
        for i in (-1, 0, 1)
        for j in (-1, 0, 1)
        for k in (-1, 0, 1)
        if (i, j, k) != (0, 0, 0)
    ],
    dtype=np.int64,
)


def _lookup(sorted_keys: IntArray, order: IntArray, keys: IntArray) -> IntArray:
    """Index (into the unsorted table) of each key, -1 when absent."""
    if sorted_keys.size == 0:
        return np.full(keys.shape, -1, dtype=np.int64)
    pos = np.clip(np.searchsorted(sorted_keys, keys), 0, sorted_keys.size - 1)
    return np.where(sorted_keys[pos] == keys, order[pos], -1)


def associate_points(
    points: FloatArray, surfels: Surfels, cfg: SurfelConfig | None = None
) -> Association:
    """Match points to the surfel of their cell (coarse levels first) within a distance.

    Args:
        points: (N, 3) float64 points in the surfels' frame, metres.
        surfels: table from :func:`build_surfels`.
        cfg: settings (``max_distance_m``, ``neighbors``); defaults when None.

    Returns:
        The associations, sorted by point index.
    """
    cfg = cfg or SurfelConfig()
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    best = np.full(n, -1, dtype=np.int64)
    best_dist = np.full(n, np.inf)
    for level, size in enumerate(surfels.cell_sizes):
        sel = np.flatnonzero(surfels.level == level)
        order = sel[np.argsort(surfels.key[sel])]
        sorted_keys = surfels.key[order]
        free = np.flatnonzero(best < 0)
        if free.size == 0 or order.size == 0:
            continue
        p = pts[free]
        keys = cell_keys(p, size)
        hit = _lookup(sorted_keys, order, keys)
        ok = hit >= 0
        dist = np.full(free.size, np.inf)
        dist[ok] = np.einsum("ij,ij->i", surfels.normal[hit[ok]], p[ok]) + surfels.d[hit[ok]]
        if cfg.neighbors:
            ijk = np.stack(
                [(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], axis=1
            )
            for off in _NEIGHBOR_OFFSETS:
                nb = ijk + off
                nkeys = (nb[:, 0] << (2 * _BITS)) | (nb[:, 1] << _BITS) | nb[:, 2]
                cand = np.where(ok, -1, _lookup(sorted_keys, order, nkeys))
                m = cand >= 0
                if not np.any(m):
                    continue
                nrm = surfels.normal[cand[m]]
                dd = np.einsum("ij,ij->i", nrm, p[m]) + surfels.d[cand[m]]
                in_plane = p[m] - dd[:, None] * nrm - surfels.centroid[cand[m]]
                near = np.linalg.norm(in_plane, axis=1) <= size
                better = near & (np.abs(dd) < np.abs(dist[m]))
                rows = np.flatnonzero(m)[better]
                hit[rows] = cand[m][better]
                dist[rows] = dd[better]
        accept = np.isfinite(dist) & (np.abs(dist) <= cfg.max_distance_m)
        best[free[accept]] = hit[accept]
        best_dist[free[accept]] = dist[accept]
    idx = np.flatnonzero(best >= 0)
    return Association(point_index=idx, surfel_index=best[idx], distance=best_dist[idx])


def subsample_per_group(group: IntArray, max_per_group: int, seed: int = 0) -> IntArray:
    """Indices keeping at most ``max_per_group`` uniformly random members of each group.

    Args:
        group: (N,) integer group label per point (for example the scan index or a voxel key).
        max_per_group: members kept per group.
        seed: random seed (deterministic output for a given seed).

    Returns:
        (M,) int64 sorted indices into the input.
    """
    g = np.asarray(group)
    n = g.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    perm = np.random.default_rng(seed).permutation(n)
    order = perm[np.argsort(g[perm], kind="stable")]
    gs = g[order]
    first = np.searchsorted(gs, gs, side="left")
    rank = np.arange(n) - first
    return np.sort(order[rank < max_per_group]).astype(np.int64)


def voxel_downsample(
    points: FloatArray, voxel_size: float, max_per_voxel: int = 1, seed: int = 0
) -> IntArray:
    """Indices keeping at most ``max_per_voxel`` random points per ``voxel_size`` cube.

    Args:
        points: (N, 3) metres.
        voxel_size: cube edge, metres.
        max_per_voxel: points kept per voxel.
        seed: random seed.

    Returns:
        (M,) int64 sorted indices into ``points``.
    """
    return subsample_per_group(cell_keys(points, voxel_size), max_per_voxel, seed)
