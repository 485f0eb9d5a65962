"""The twin recording's map: planes re-estimated from the twin's points as a round builds them."""

from __future__ import annotations

import numpy as np

from licalib_cli.estimation import Planes
from licalib_cli.pipeline.twin import _refit_planes


def test_planes_are_refitted_from_their_points_and_keep_their_orientation() -> None:
    rng = np.random.default_rng(3)
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    offsets = np.array([-1.0, 2.0, 0.5])
    old = Planes(normal=normals, d=offsets, thickness=np.full(3, 0.01))
    # new planes: slightly tilted and shifted; the third has only two points
    tilt = np.array([[0.02, 0.0, 1.0], [1.0, 0.03, 0.0], [0.0, -1.0, 0.0]])
    tilt /= np.linalg.norm(tilt, axis=1, keepdims=True)
    shift = np.array([-1.01, 2.02, 0.7])
    plane = np.repeat([0, 1, 2], [500, 500, 2])
    pts = []
    for k, n in enumerate(tilt):
        a = np.cross(n, [0.3, 0.5, 0.8])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        m = int(np.sum(plane == k))
        uv = rng.uniform(-2.0, 2.0, (m, 2))
        pts.append(-shift[k] * n + uv[:, :1] * a + uv[:, 1:] * b + rng.normal(0, 1e-3, (m, 1)) * n)
    new = _refit_planes(old, plane, np.vstack(pts))
    for k in (0, 1):
        assert np.dot(new.normal[k], tilt[k]) > 0.9999  # same side as the old normal
        assert abs(new.d[k] - shift[k]) < 2e-4
    np.testing.assert_array_equal(new.normal[2], normals[2])  # too few points: kept
    assert new.d[2] == offsets[2]
    np.testing.assert_array_equal(new.thickness, old.thickness)
