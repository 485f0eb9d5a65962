"""Elimination of the trajectory block: banded Cholesky with a dense border vs SuperLU and dense.

The test system has the structure of the calibration problem: two splines of ``N`` control
points (3 coordinates each) stored one after the other (so the band only appears after
interleaving them), every measurement touching 4 consecutive control points of both; a border
of 8 "bias and gravity" coordinates touched by most measurements; 7 calibration coordinates
touched by every measurement.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from licalib_cli.parallel.threads import serial
from licalib_cli.solver.problem import Layout, Linearization
from licalib_cli.solver.schur import (
    _FORWARD_COLUMNS,
    _BandedCholesky,
    _sparse_lu_solver,
    _trajectory_diagonal,
    schur_complement,
)

NUM_CTRL = 40
NUM_BORDER = 8
NUM_CALIB = 7


def _layout(nt: int, nc: int) -> Layout:
    names = tuple(f"t{i}" for i in range(nt)) + tuple(f"c{i}" for i in range(nc))
    owner = ("traj",) * nt + ("calib",) * nc
    return Layout(
        block_names=("traj", "calib"),
        index={"traj": np.arange(nt), "calib": np.arange(nt, nt + nc)},
        num_trajectory=nt,
        num_calibration=nc,
        names=names,
        scale=np.ones(nt + nc),
        owner=owner,
    )


def _linearization(h: np.ndarray, g: np.ndarray, nt: int) -> Linearization:
    nc = h.shape[0] - nt
    h_tt = sp.csc_matrix(h[:nt, :nt])
    h_tt.eliminate_zeros()
    return Linearization(
        _layout(nt, nc), 0.0, 0, h_tt, h[:nt, nt:].copy(), h[nt:, nt:].copy(), g.copy()
    )


def _banded_with_border(
    rng: np.random.Generator, *, untouched: tuple[int, ...] = ()
) -> tuple[np.ndarray, np.ndarray, int]:
    """Dense ``H = J^T J``, ``g = J^T r`` and ``Nt`` of the test system.

    Control points listed in ``untouched`` (of the first spline) are seen by no measurement.
    """
    n_spline = 3 * NUM_CTRL
    nt = 2 * n_spline + NUM_BORDER
    n_meas, m = 600, 3
    seg = rng.integers(0, NUM_CTRL - 3, n_meas)
    j = np.zeros((n_meas, m, nt + NUM_CALIB))
    rows = np.arange(n_meas)[:, None, None]
    res = np.arange(m)[None, :, None]
    for spline in range(2):
        cols = spline * n_spline + 3 * seg[:, None] + np.arange(12)[None, :]  # 4 control points
        j[rows, res, cols[:, None, :]] = rng.normal(size=(n_meas, m, 12))
    seen = rng.random(n_meas) < 0.7  # IMU-like measurements see biases and gravity
    j[seen, :, 2 * n_spline : nt] = rng.normal(size=(int(seen.sum()), m, NUM_BORDER))
    j[:, :, nt:] = rng.normal(size=(n_meas, m, NUM_CALIB))
    for k in untouched:
        j[:, :, 3 * k : 3 * k + 3] = 0.0
    jm = j.reshape(n_meas * m, -1)
    r = rng.normal(size=n_meas * m)
    return jm.T @ jm, jm.T @ r, nt


def _dense_reference(h: np.ndarray, g: np.ndarray, nt: int, add: np.ndarray) -> tuple:
    a = h[:nt, :nt] + np.diag(add)
    x = np.linalg.solve(a, h[:nt, nt:])
    y = -np.linalg.solve(a, g[:nt])
    s = h[nt:, nt:] - h[nt:, :nt] @ x
    b = -g[nt:] - h[nt:, :nt] @ y
    return s, b, x, y


def _assert_rel(actual: np.ndarray, expected: np.ndarray, rel: float = 1e-9) -> None:
    scale = np.abs(expected).max()
    assert np.abs(actual - expected).max() <= rel * scale, np.abs(actual - expected).max() / scale


@pytest.mark.parametrize("damping", [0.0, 1e-6, "vector"])
def test_banded_schur_matches_dense_and_sparse_lu(damping: float | str) -> None:
    rng = np.random.default_rng(21)
    h, g, nt = _banded_with_border(rng)
    lin = _linearization(h, g, nt)
    d = rng.uniform(1e-6, 1e-3, nt) * np.diag(h)[:nt] if damping == "vector" else float(damping)
    add = _trajectory_diagonal(lin.H_tt, d)
    # the structure is found: the 8 border coordinates and a band of 4 interleaved control
    # points of both splines (24 coordinates; 23 sub-diagonals, a little more allowed for RCM)
    factor = _BandedCholesky.factorize(lin.H_tt, add)
    assert factor is not None
    np.testing.assert_array_equal(factor.border, np.arange(nt - NUM_BORDER, nt))
    assert factor.bandwidth <= 30, factor.bandwidth
    sch = schur_complement(lin, d)
    s, b, x, y = _dense_reference(h, g, nt, add)
    for actual, expected in ((sch.S, s), (sch.b, b), (sch.X, x), (sch.y_t, y)):
        _assert_rel(actual, expected)
    # the former SuperLU path gives the same system
    rhs = np.column_stack([lin.H_tc, -lin.g_t])
    lu = _sparse_lu_solver(lin.H_tt, add)(rhs)
    _assert_rel(sch.X, lu[:, :-1])
    _assert_rel(sch.y_t, lu[:, -1])
    np.testing.assert_array_equal(sch.S, sch.S.T)
    dc = rng.normal(size=NUM_CALIB)
    _assert_rel(sch.back_substitute(dc), y - x @ dc)
    # the factor's forward and backward substitutions: W^T W = r^T A^-1 r, L^-T L^-1 r = A^-1 r
    a_inv = np.linalg.inv(h[:nt, :nt] + np.diag(add))
    w = factor.forward(rhs)
    _assert_rel(w.T @ w, rhs.T @ a_inv @ rhs)
    _assert_rel(factor.backward(w[:, -1]), a_inv @ rhs[:, -1])
    _assert_rel(factor.solve(rhs), a_inv @ rhs)


def test_forward_of_many_columns_is_shared_between_threads_exactly() -> None:
    """The forward substitution of a few hundred right-hand sides runs in column blocks on the
    block threads, in the same blocks as serially: the result is the serial one, bit for bit,
    with the border included, and a single vector gives its column."""
    rng = np.random.default_rng(5)
    h, _, nt = _banded_with_border(rng)
    lin = _linearization(h, np.zeros(h.shape[0]), nt)
    factor = _BandedCholesky.factorize(lin.H_tt, _trajectory_diagonal(lin.H_tt, 0.0))
    assert factor is not None and factor.border.size == NUM_BORDER
    rhs = np.asfortranarray(rng.normal(size=(nt, 3 * _FORWARD_COLUMNS + 5)))
    with serial():
        expected = factor.forward(rhs)
    np.testing.assert_array_equal(factor.forward(rhs), expected)
    np.testing.assert_array_equal(factor.forward(np.ascontiguousarray(rhs)), expected)
    _assert_rel(factor.forward(rhs[:, 7]), expected[:, 7], 1e-12)
    a_inv = np.linalg.inv(h[:nt, :nt])
    _assert_rel(expected.T @ expected, rhs.T @ a_inv @ rhs)


def test_untouched_trajectory_coordinates_get_a_zero_step() -> None:
    rng = np.random.default_rng(22)
    h, g, nt = _banded_with_border(rng, untouched=(0, 17))
    lin = _linearization(h, g, nt)
    sch = schur_complement(lin, 1e-6)
    idle = np.r_[0:3, 51:54]
    np.testing.assert_array_equal(sch.y_t[idle], 0.0)
    np.testing.assert_array_equal(sch.X[idle], 0.0)
    add = _trajectory_diagonal(lin.H_tt, 1e-6)
    np.testing.assert_array_equal(add[idle], 1.0 + 1e-6)
    s, b, _, _ = _dense_reference(h, g, nt, add)
    _assert_rel(sch.S, s)
    _assert_rel(sch.b, b)


def test_indefinite_block_falls_back_to_sparse_lu() -> None:
    rng = np.random.default_rng(23)
    h, g, nt = _banded_with_border(rng)
    w = np.linalg.eigvalsh(h[:nt, :nt])
    shift = 0.5 * (w[10] + w[11])  # between two eigenvalues: indefinite, well away from singular
    h[:nt, :nt] -= shift * np.eye(nt)
    lin = _linearization(h, g, nt)
    add = _trajectory_diagonal(lin.H_tt, 0.0)
    assert _BandedCholesky.factorize(lin.H_tt, add) is None
    sch = schur_complement(lin)
    s, b, x, y = _dense_reference(h, g, nt, add)
    for actual, expected in ((sch.S, s), (sch.b, b), (sch.X, x), (sch.y_t, y)):
        _assert_rel(actual, expected, 1e-8)


def test_singular_block_raises() -> None:
    # x0 and x1 only ever seen as x0 + x1
    h = np.zeros((3, 3))
    h[:2, :2] = 1.0
    h[2, 2] = 1.0
    h[:2, 2] = h[2, :2] = 0.5
    lin = _linearization(h, np.ones(3), 2)
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        schur_complement(lin)


def test_no_calibration_and_no_trajectory() -> None:
    rng = np.random.default_rng(24)
    h, g, nt = _banded_with_border(rng)
    traj_only = _linearization(h[:nt, :nt], g[:nt], nt)
    sch = schur_complement(traj_only, 1e-6)
    assert sch.S.shape == (0, 0) and sch.X.shape == (nt, 0)
    _assert_rel(sch.y_t, -np.linalg.solve(h[:nt, :nt] + 1e-6 * np.eye(nt), g[:nt]))
    calib_only = _linearization(h[nt:, nt:], g[nt:], 0)
    sch = schur_complement(calib_only, 1e-6)
    np.testing.assert_array_equal(sch.S, h[nt:, nt:])
    np.testing.assert_array_equal(sch.b, -g[nt:])
