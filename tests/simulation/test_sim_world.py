"""Ray casting against the room: exact first hits, checked by independent ray marching."""

from __future__ import annotations

import numpy as np

from licalib_cli.simulation import default_world


def _rays(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    centres = np.array([[5.0, 5.0, 5.0], [0.0, 5.0, 2.0], [2.5, 5.0, 1.5], [6.0, 3.0, 1.4]])
    o = centres[rng.integers(len(centres), size=n)] + rng.uniform(-0.5, 0.5, (n, 3))
    d = rng.normal(size=(n, 3))
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def test_planes_are_normalised_and_counted() -> None:
    world = default_world()
    planes = world.planes()
    assert planes.shape == (6 + 6 * world.num_boxes + world.num_quads, 4)
    assert np.allclose(np.linalg.norm(planes[:, :3], axis=1), 1.0)
    # Many distinct normal directions (up to sign): walls, rotated boxes, slanted quads.
    dirs = planes[:, :3] * np.sign(planes[:, :3] @ [0.3, 0.5, 0.8])[:, None]
    assert len(np.unique(np.round(dirs, 3), axis=0)) >= 12


def test_hits_lie_on_their_plane_and_match_ray_marching() -> None:
    """Distances equal sphere tracing on the exact distance field to 1e-6 m."""
    world = default_world()
    o, d = _rays(3000, seed=0)
    dist, pid = world.raycast(o, d, chunk=700)
    planes = world.planes()
    hit = o + dist[:, None] * d
    assert np.max(np.abs(np.einsum("ni,ni->n", planes[pid, :3], hit) + planes[pid, 3])) < 1e-9
    assert np.all(dist > 0) and np.all(np.isfinite(dist))

    t = np.zeros(len(o))
    active = np.ones(len(o), dtype=bool)
    for _ in range(2000):
        step = world.clearance(o[active] + t[active, None] * d[active])
        t[active] += np.maximum(step, 0.0)
        active[np.flatnonzero(active)[step < 1e-10]] = False
        if not active.any():
            break
    converged = ~active
    assert converged.mean() > 0.99
    assert np.max(np.abs(t[converged] - dist[converged])) < 1e-6
    # Obstacles inside the room are actually hit (not only the walls).
    assert np.mean(pid >= 6) > 0.05


def test_chunking_does_not_change_results() -> None:
    world = default_world()
    o, d = _rays(1000, seed=1)
    a = world.raycast(o, d, chunk=1000)
    b = world.raycast(o, d, chunk=97)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
