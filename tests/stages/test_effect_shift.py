"""The planes-free effect shift: which planes stay held."""

from __future__ import annotations

import numpy as np

from licalib_cli.pipeline.effect_shift import _degenerate


def _block(jac: np.ndarray) -> np.ndarray:
    return jac.T @ jac


def test_planes_whose_own_information_is_singular_or_indefinite_are_held() -> None:
    rng = np.random.default_rng(4)
    healthy = _block(np.column_stack([rng.normal(size=(40, 2)), np.ones(40)]))
    # points along one scan line: the normal's turn about the line is not determined
    line = rng.normal(size=40)
    collinear = _block(np.column_stack([line, 0.0 * line, np.ones(40)]))
    one_point = _block(np.array([[0.3, -0.2, 1.0]]))
    indefinite = healthy - np.diag([0.0, 0.0, 2.0 * healthy[2, 2]])
    empty = np.zeros((3, 3))
    got = _degenerate(np.stack([healthy, collinear, one_point, indefinite, empty]))
    assert got.tolist() == [False, True, True, True, True]
