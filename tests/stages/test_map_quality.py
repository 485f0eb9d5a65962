"""Mean map entropy and plane thickness."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from licalib_cli.errors import DataError
from licalib_cli.map_quality import mean_map_entropy, plane_thickness, point_entropies
from licalib_cli.parallel import threads as thr
from licalib_cli.surfels import Association


def _plane(gen: np.random.Generator, n: int, noise: float) -> npt.NDArray[np.float64]:
    xy = gen.uniform(-1.0, 1.0, size=(n, 2))
    return np.column_stack([xy, noise * gen.normal(size=n)])


def _direct(points: npt.NDArray[np.float64], radius: float, min_nb: int) -> npt.NDArray[np.float64]:
    """Brute-force reference: h = 0.5 ln det(2 pi e Sigma) with np.cov of the neighbourhood."""
    out = np.full(points.shape[0], np.nan)
    for i, p in enumerate(points):
        nb = points[np.linalg.norm(points - p, axis=1) <= radius]
        if nb.shape[0] >= min_nb:
            out[i] = 0.5 * np.log(np.linalg.det(2.0 * np.pi * np.e * np.cov(nb.T)))
    return out


def test_entropy_matches_direct_formula_on_tiny_example() -> None:
    gen = np.random.default_rng(0)
    pts = gen.normal(scale=0.2, size=(40, 3))
    h = point_entropies(pts, radius_m=0.3, min_neighbors=5, chunk_size=7)
    ref = _direct(pts, 0.3, 5)
    np.testing.assert_array_equal(np.isnan(h), np.isnan(ref))
    assert np.isfinite(ref).sum() > 10
    np.testing.assert_allclose(h[np.isfinite(h)], ref[np.isfinite(ref)], rtol=0, atol=1e-10)
    # Whole cloud within the radius: every point sees the same covariance.
    few = gen.normal(scale=0.05, size=(6, 3))
    expected = 0.5 * np.log(np.linalg.det(2.0 * np.pi * np.e * np.cov(few.T)))
    np.testing.assert_allclose(point_entropies(few, radius_m=1.0), expected, atol=1e-12)
    res = mean_map_entropy(few, radius_m=1.0)
    assert res.mean == pytest.approx(expected, abs=1e-12)
    assert res.n_evaluated == res.n_queried == 6


def test_noisy_plane_has_higher_entropy() -> None:
    gen = np.random.default_rng(1)
    sharp = mean_map_entropy(_plane(gen, 4000, 0.002))
    noisy = mean_map_entropy(_plane(gen, 4000, 0.02))
    # A 10x thicker plane adds about ln(10) = 2.3 nats (0.5 ln of the variance ratio 100).
    assert noisy.mean - sharp.mean == pytest.approx(np.log(10.0), abs=0.4)
    # The subsampled estimate stays close to the full mean.
    pts = _plane(gen, 6000, 0.01)
    full = mean_map_entropy(pts, max_query_points=None)
    sub = mean_map_entropy(pts, max_query_points=1000, seed=2)
    assert sub.n_queried == 1000 and full.n_queried == 6000
    assert sub.mean == pytest.approx(full.mean, abs=0.05)


def test_sparse_map_and_thickness() -> None:
    with pytest.raises(DataError, match="map entropy is undefined"):
        mean_map_entropy(np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]))
    assoc = Association(
        point_index=np.arange(4),
        surfel_index=np.zeros(4, np.int64),
        distance=np.array([0.01, -0.01, 0.02, -0.02]),
    )
    assert plane_thickness(assoc) == pytest.approx(np.sqrt(0.00025))
    empty = Association(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    assert np.isnan(plane_thickness(empty))


def test_entropies_on_block_threads_are_the_serial_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    """The query chunks are shared between the block threads: the values of the serial loop."""
    gen = np.random.default_rng(9)
    lifted = _plane(gen, 6000, 0.03) + np.array([0.0, 0.0, 2.0])
    pts = np.concatenate([_plane(gen, 6000, 0.01), lifted])
    query = np.arange(0, pts.shape[0], 2)  # 6000 queries: two chunks of 4096, the last short
    with thr.serial():
        expected = point_entropies(pts, query)
    monkeypatch.setattr(thr, "THREADS", 2)  # also when the suite runs with LICALIB_THREADS=1
    assert np.array_equal(point_entropies(pts, query), expected, equal_nan=True)
    assert np.isfinite(expected).sum() > 5000
