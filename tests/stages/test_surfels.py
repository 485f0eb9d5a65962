"""Surfel extraction, point association and downsampling helpers."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from licalib_cli.errors import DataError
from licalib_cli.surfels import (
    SurfelConfig,
    associate_points,
    build_surfels,
    cell_keys,
    subsample_per_group,
    voxel_downsample,
)

# Planes n^T x + d = 0 (unit n) and the patch centre / half size over which points are drawn.
# None lies on a cell boundary (a plane on a boundary is split into two half-slabs).
_PLANES = [
    (np.array([0.0, 0.0, 1.0]), 1.37, np.array([2.0, 2.0, -1.37]), 3.0),  # floor z = -1.37
    (np.array([1.0, 0.0, 0.0]), -6.23, np.array([6.23, 1.0, 1.0]), 2.5),  # wall x = 6.23
    (np.array([0.0, 0.6, 0.8]), -4.0, np.array([-3.0, 2.4, 3.2]), 2.0),  # slanted roof
    (np.array([-0.6, 0.8, 0.0]), -2.8, np.array([-6.0, -1.0, 1.0]), 2.0),
]
NOISE = 0.005  # metres along the normal
DENSITY = 1000.0  # points per m^2, like several aggregated scans
_CLUTTER_CENTER = np.array([1.0, -6.0, 2.0])  # the 2 m clutter cube is cell aligned


def _plane_points(
    gen: np.random.Generator, n: npt.NDArray[np.float64], c: npt.NDArray[np.float64], half: float
) -> npt.NDArray[np.float64]:
    u = np.cross(n, [0.3, 0.5, 0.81])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    m = int(DENSITY * 4.0 * half * half)
    ab = gen.uniform(-half, half, size=(m, 2))
    return c + ab[:, :1] * u + ab[:, 1:] * v


@pytest.fixture(scope="module")
def scene() -> dict[str, npt.NDArray[np.float64]]:
    gen = np.random.default_rng(42)
    pts, labels, true_dist = [], [], []
    for k, (n, d, c, half) in enumerate(_PLANES):
        assert abs(n @ c + d) < 1e-6
        on = _plane_points(gen, n, c, half)
        noise = NOISE * gen.normal(size=on.shape[0])
        pts.append(on + noise[:, None] * n)
        labels.append(np.full(on.shape[0], k))
        true_dist.append(noise)
    clutter = _CLUTTER_CENTER + gen.uniform(-1.0, 1.0, size=(3000, 3))
    pts.append(clutter)
    labels.append(np.full(clutter.shape[0], -1))
    true_dist.append(np.full(clutter.shape[0], np.nan))
    return {
        "points": np.concatenate(pts),
        "label": np.concatenate(labels),
        "true_dist": np.concatenate(true_dist),
    }


@pytest.mark.parametrize("cell_sizes", [(1.0,), (1.0, 0.5)])
def test_surfels_recover_planes_and_reject_clutter(
    scene: dict[str, npt.NDArray[np.float64]], cell_sizes: tuple[float, ...]
) -> None:
    cfg = SurfelConfig(cell_sizes=cell_sizes)
    surfels = build_surfels(scene["points"], cfg)
    assert len(surfels) > 40
    assert np.all(surfels.d >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(surfels.normal, axis=1), 1.0, atol=1e-12)
    normals = np.array([p[0] for p in _PLANES])
    ds = np.array([p[1] for p in _PLANES])
    cos = surfels.normal @ normals.T  # (S, planes)
    k = np.argmax(np.abs(cos), axis=1)
    sign = np.sign(cos[np.arange(len(surfels)), k])
    ang = np.degrees(np.arccos(np.clip(np.abs(cos[np.arange(len(surfels)), k]), 0.0, 1.0)))
    # Tolerances: normals within 1 deg, d within 1 cm.
    print(f"{cell_sizes}: {len(surfels)} surfels, normal error max {ang.max():.3f} deg")
    assert ang.max() < 1.0, ang.max()
    # d within 1 cm, plus the lever of the normal error: d = -n^T c moves by |c| sin(angle).
    lever = np.linalg.norm(surfels.centroid, axis=1) * np.sin(np.radians(ang))
    assert np.all(np.abs(sign * surfels.d - ds[k]) < 0.01 + lever)
    if cell_sizes == (1.0,):
        assert np.abs(sign * surfels.d - ds[k]).max() < 0.01
    # Locally the surfel lies on its true plane: the centroid is within 1 cm of it.
    offset = np.einsum("ij,ij->i", surfels.centroid, normals[k]) + ds[k]
    assert np.abs(offset).max() < 0.01
    np.testing.assert_allclose(surfels.closest_point, -surfels.d[:, None] * surfels.normal)
    assert np.all(np.abs(surfels.thickness - NOISE) < 0.002)
    # No surfel inside the isotropic clutter cube.
    assert np.all(np.abs(surfels.centroid - _CLUTTER_CENTER).max(axis=1) > 1.0)
    assert np.all(surfels.planarity >= cfg.min_planarity)


def test_association_distances(scene: dict[str, npt.NDArray[np.float64]]) -> None:
    cfg = SurfelConfig(cell_sizes=(1.0, 0.5), max_distance_m=0.05)
    surfels = build_surfels(scene["points"], cfg)
    pts = scene["points"]
    # Add far outliers (0.2 m off the floor) that must not be associated.
    floor_n = _PLANES[0][0]
    on_floor = np.flatnonzero(scene["label"] == 0)[:200]
    outliers = pts[on_floor] + 0.2 * floor_n
    query = np.concatenate([pts, outliers])
    assoc = associate_points(query, surfels, cfg)
    assert np.all(assoc.point_index < pts.shape[0])
    assert np.all(np.abs(assoc.distance) <= 0.05)
    labels = scene["label"][assoc.point_index]
    assert np.all(labels >= 0)  # clutter never associated
    plane_pts = np.flatnonzero(scene["label"] >= 0)
    assert assoc.point_index.size > 0.9 * plane_pts.size
    # Signed distance to the surfel equals the true noise offset (up to plane-fit error, 3 mm).
    n_true = np.array([p[0] for p in _PLANES])[labels]
    sign = np.sign(np.einsum("ij,ij->i", surfels.normal[assoc.surfel_index], n_true))
    err = sign * assoc.distance - scene["true_dist"][assoc.point_index]
    assert np.abs(err).max() < 0.003, np.abs(err).max()
    assert assoc.rms() == pytest.approx(NOISE, abs=0.001)

    # Floor points beyond the sampled patch (cells without a surfel) are only found by the
    # neighbour search, on a floor surfel next door, within one cell of its centroid.
    g = np.linspace(-3.0, 5.7, 88)  # clear of the other planes
    xx, yy = np.meshgrid(g, g)
    floor = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, -1.37)], axis=1)
    plain = associate_points(floor, surfels, cfg)
    nb_cfg = SurfelConfig(cell_sizes=(1.0, 0.5), neighbors=True)
    with_nb = associate_points(floor, surfels, nb_cfg)
    assert np.all(np.isin(plain.point_index, with_nb.point_index))
    extra = ~np.isin(with_nb.point_index, plain.point_index)
    assert extra.sum() > 100
    sid = with_nb.surfel_index[extra]
    assert np.abs(with_nb.distance[extra]).max() < 0.006  # plane extrapolated up to one cell
    assert np.all(np.abs(surfels.normal[sid, 2]) > 0.999)
    reach = np.linalg.norm(floor[with_nb.point_index[extra]] - surfels.centroid[sid], axis=1)
    assert np.all(reach <= np.asarray(surfels.cell_sizes)[surfels.level[sid]] + 0.01)


def test_single_beam_line_is_not_a_plane() -> None:
    gen = np.random.default_rng(0)
    t = gen.uniform(0.0, 0.9, 200)
    line = np.stack([t, 0.3 + 0.001 * gen.normal(size=200), np.full(200, 0.4)], axis=1)
    assert len(build_surfels(line, SurfelConfig(cell_sizes=(1.0,)))) == 0
    with pytest.raises(DataError, match="finite"):
        build_surfels(np.array([[0.0, np.nan, 1.0]]))
    with pytest.raises(DataError, match="too far"):
        cell_keys(np.array([[1e7, 0.0, 0.0]]), 1.0)


def test_downsampling_helpers() -> None:
    gen = np.random.default_rng(1)
    group = gen.integers(0, 10, size=5000)
    keep = subsample_per_group(group, 100, seed=3)
    counts = np.bincount(group[keep], minlength=10)
    np.testing.assert_array_equal(counts, np.minimum(np.bincount(group, minlength=10), 100))
    assert np.all(np.diff(keep) > 0)
    np.testing.assert_array_equal(keep, subsample_per_group(group, 100, seed=3))
    pts = gen.uniform(0.0, 2.0, size=(4000, 3))
    idx = voxel_downsample(pts, 0.5, max_per_voxel=2)
    per_voxel = np.unique(cell_keys(pts[idx], 0.5), return_counts=True)[1]
    assert per_voxel.max() <= 2
    assert per_voxel.size == 64


def _cell_with_a_corner(gen: np.random.Generator, chunk: int) -> npt.NDArray[np.float64]:
    """A 1 m cell (0..1 on every axis) holding a floor z = 0.5 and, near x = 1, ``chunk``
    returns of a wall x = 0.98 rising 6-20 cm above that floor (a corner of the scene)."""
    floor = np.column_stack(
        [gen.uniform(0.02, 0.98, 800), gen.uniform(0.02, 0.98, 800), np.full(800, 0.5)]
    )
    wall = np.column_stack(
        [np.full(chunk, 0.98), gen.uniform(0.02, 0.98, chunk), gen.uniform(0.56, 0.70, chunk)]
    )
    pts = np.concatenate([floor, wall])
    return pts + gen.normal(scale=0.002, size=pts.shape)


def test_a_cell_holding_a_second_surface_is_left_to_the_finer_cells() -> None:
    gen = np.random.default_rng(7)
    pts = _cell_with_a_corner(gen, chunk=8)
    loose = SurfelConfig(cell_sizes=(1.0,), max_thickness_m=0.02, min_planarity=0.6)
    plane = build_surfels(pts, loose)
    # the few wall returns hardly thicken the cell: it passes planarity and thickness, tilted
    assert len(plane) == 1 and plane.thickness[0] < 0.02
    assert np.degrees(np.arccos(abs(plane.normal[0, 2]))) > 0.3
    strict = SurfelConfig(
        cell_sizes=(1.0, 0.5), max_thickness_m=0.02, max_point_distance_m=0.06, min_planarity=0.6
    )
    found = build_surfels(pts, strict)
    assert np.all(found.level == 1)  # no 1 m surfel; the finer cells without the wall remain
    level = found.normal[found.thickness < 0.005]
    assert len(level) >= 2
    assert np.all(np.degrees(np.arccos(np.abs(level[:, 2]))) < 0.3)
    # one plane with noise alone keeps its cell
    clean = build_surfels(_cell_with_a_corner(np.random.default_rng(8), chunk=0), strict)
    assert len(clean) == 1 and clean.level[0] == 0
