"""Map quality: mean map entropy (paper Sec. VI) and plane thickness.

Conventions:
    - Points are (N, 3) float64 metres in one frame (the aggregated, undistorted map).
    - Point entropy ``h(p) = 0.5 ln |2 pi e Sigma(p)|`` with ``Sigma(p)`` the sample covariance
      (``1 / (k - 1)``) of the ``k`` map points within ``radius_m`` of ``p`` (``p`` included).
      Points with fewer than ``min_neighbors`` neighbours or a singular covariance are skipped.
      The mean map entropy (MME) is the mean of ``h`` over the evaluated points; lower is sharper.
      Units: nats with lengths in metres (so values are typically negative).
    - For speed the entropy may be evaluated at a random subset of the map points
      (``max_query_points``, seeded); the neighbourhoods always use the full map, so the subset
      changes only the sampling of the mean, not the per-point values.
    - Plane thickness is the RMS signed point-to-surfel distance of an association, metres.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from licalib_cli.errors import DataError
from licalib_cli.parallel.threads import map_slices
from licalib_cli.surfels import Association

__all__ = [
    "MapEntropy",
    "mean_map_entropy",
    "plane_thickness",
    "point_entropies",
]

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class MapEntropy:
    """Mean map entropy.

    Attributes:
        mean: mean of the point entropies, nats (lengths in metres); lower is sharper.
        n_evaluated: points whose entropy entered the mean.
        n_queried: points queried (the subset size, or all points).
        radius_m: neighbourhood radius used, metres.
    """

    mean: float
    n_evaluated: int
    n_queried: int
    radius_m: float


def point_entropies(
    points: FloatArray,
    query_index: npt.NDArray[np.int64] | None = None,
    radius_m: float = 0.3,
    min_neighbors: int = 5,
    chunk_size: int = 4096,
    tree: cKDTree | None = None,
) -> FloatArray:
    """Entropy ``0.5 ln |2 pi e Sigma|`` of the neighbourhood of each queried map point.

    Args:
        points: (N, 3) map points, metres.
        query_index: (Q,) indices of the points to evaluate; all when None.
        radius_m: neighbourhood radius, metres.
        min_neighbors: fewest neighbours (including the point) for a value.
        chunk_size: queries processed per vectorised batch (bounds memory).
        tree: a prebuilt ``cKDTree(points)`` to reuse.

    Returns:
        (Q,) float64 entropies, NaN where too few neighbours or a singular covariance.
    """
    pts = np.asarray(points, dtype=np.float64)
    q_idx = np.arange(pts.shape[0]) if query_index is None else np.asarray(query_index)
    tree = tree if tree is not None else cKDTree(pts)
    out = np.full(q_idx.shape[0], np.nan)
    iu, ju = np.triu_indices(3)
    const = 3.0 * np.log(2.0 * np.pi * np.e)

    def chunk(rows: slice) -> None:
        sel = q_idx[rows]
        qtree = cKDTree(pts[sel])
        pairs = qtree.sparse_distance_matrix(tree, radius_m, output_type="ndarray")
        qi, pj = pairs["i"], pairs["j"]
        m = sel.shape[0]
        k = np.bincount(qi, minlength=m).astype(np.float64)
        local = pts[pj] - pts[sel][qi]  # relative to the query point: no cancellation
        s1 = np.stack([np.bincount(qi, local[:, a], minlength=m) for a in range(3)], axis=1)
        s2 = np.stack(
            [
                np.bincount(qi, local[:, a] * local[:, b], minlength=m)
                for a, b in zip(iu, ju, strict=True)
            ],
            axis=1,
        )
        ok = k >= max(min_neighbors, 2)
        ks = np.where(ok, k, 2.0)
        cov = np.empty((m, 3, 3))
        cov[:, iu, ju] = (s2 - s1[:, iu] * s1[:, ju] / ks[:, None]) / (ks[:, None] - 1.0)
        cov[:, ju, iu] = cov[:, iu, ju]
        sign, logdet = np.linalg.slogdet(cov)
        h = 0.5 * (const + logdet)
        out[rows] = np.where(ok & (sign > 0), h, np.nan)

    # the chunks write disjoint slices: shared by the block threads, the values of the serial loop
    map_slices(chunk, q_idx.shape[0], chunk_size)
    return out


def mean_map_entropy(
    points: FloatArray,
    radius_m: float = 0.3,
    *,
    min_neighbors: int = 5,
    max_query_points: int | None = 20000,
    seed: int = 0,
) -> MapEntropy:
    """Mean map entropy of an aggregated point cloud (paper Sec. VI).

    Args:
        points: (N, 3) map points, metres.
        radius_m: neighbourhood radius, metres (the paper uses 0.3 m).
        min_neighbors: fewest neighbours for a point to count.
        max_query_points: evaluate at most this many random points (None: all). The mean is
            then a Monte-Carlo estimate of the full MME; neighbourhoods use every point.
        seed: seed of the subset.

    Returns:
        The MME and how many points it averages.

    Raises:
        DataError: no point has enough neighbours (empty or far too sparse map).
    """
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    if max_query_points is not None and n > max_query_points:
        q = np.sort(np.random.default_rng(seed).choice(n, max_query_points, replace=False))
    else:
        q = np.arange(n)
    h = point_entropies(pts, q, radius_m, min_neighbors)
    good = np.isfinite(h)
    if not np.any(good):
        msg = (
            f"No map point has {min_neighbors} neighbours within {radius_m:g} m, so the map "
            "entropy is undefined; check that the scans were aggregated into one frame."
        )
        raise DataError(msg)
    result = MapEntropy(
        mean=float(h[good].mean()),
        n_evaluated=int(good.sum()),
        n_queried=int(q.size),
        radius_m=float(radius_m),
    )
    logger.debug("mean map entropy %.4f over %d points", result.mean, result.n_evaluated)
    return result


def plane_thickness(association: Association) -> float:
    """RMS point-to-surfel distance of an association, metres (NaN when empty)."""
    return association.rms()
