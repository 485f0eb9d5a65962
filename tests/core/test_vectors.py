"""Row norms of point arrays."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.geometry.vectors import norms


def test_norms_match_numpy() -> None:
    v = np.random.default_rng(3).normal(scale=30.0, size=(1000, 3))
    np.testing.assert_allclose(norms(v), np.linalg.norm(v, axis=1), rtol=1e-15)
    assert norms(np.zeros((0, 3))).shape == (0,)


def test_norms_take_lists_and_other_widths() -> None:
    assert norms([[3.0, 4.0], [0.0, 0.0]]).tolist() == [5.0, 0.0]
    assert norms(np.array([[1, 2, 2]], dtype=np.int32)).tolist() == pytest.approx([3.0])
