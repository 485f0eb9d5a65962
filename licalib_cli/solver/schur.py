"""Elimination of the trajectory block: Schur complement, banded Cholesky, sparse LU fallback.

:func:`schur_complement` factorises ``A_tt = H_tt + damping``. Coordinates whose rows are
nearly dense (IMU biases, gravity) form a border; the rest, reordered by reverse
Cuthill-McKee (which interleaves the so3 and r3 control points by knot), is banded with about
``6 * 4`` coordinates of bandwidth and gets a banded Cholesky factorisation; the border is
eliminated by a small dense Schur complement. The calibration system needs only the forward
substitution with the Cholesky factor (LAPACK ``tbtrs``): ``S = H_cc - W^T W`` with
``W = L^-1 H_tc``. When the structure is not banded or ``A_tt`` is not numerically positive
definite, a sparse LU (SuperLU, COLAMD) is used instead.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.linalg.lapack as lapack
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from licalib_cli.parallel.threads import map_slices

if TYPE_CHECKING:
    from licalib_cli.solver.problem import Linearization

__all__ = ["SchurSystem", "schur_complement"]

F64 = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]


@dataclass(frozen=True)
class SchurSystem:
    """The calibration system after eliminating the trajectory block.

    ``S = H_cc - H_ct A_tt^-1 H_tc`` and ``b = -g_c + H_ct A_tt^-1 g_t`` with
    ``A_tt = H_tt + diag(trajectory_damping)``; for a calibration step ``dc`` the trajectory step
    is ``dt = y_t - X dc``.

    Attributes:
        S: (Nc, Nc) Schur complement (no damping on the calibration block).
        b: (Nc,) right-hand side.
        y_t: (Nt,) ``-A_tt^-1 g_t``.
        X: (Nt, Nc) ``A_tt^-1 H_tc``, formed on first access (the step does not need it:
            :meth:`back_substitute` solves with ``H_tc dc`` instead).
    """

    S: F64
    b: F64
    y_t: F64
    solve_tt: Callable[[F64], F64] = field(repr=False, compare=False)
    H_tc: F64 = field(repr=False, compare=False)

    @cached_property
    def X(self) -> F64:
        """(Nt, Nc) ``A_tt^-1 H_tc``."""
        if self.H_tc.size == 0:
            return np.zeros(self.H_tc.shape)
        return self.solve_tt(self.H_tc)

    def back_substitute(self, dc: F64) -> F64:
        """(Nt,) trajectory step ``y_t - A_tt^-1 H_tc dc`` for the (Nc,) calibration step ``dc``."""
        if self.y_t.size == 0:
            return np.zeros(0)
        return self.y_t - self.solve_tt(self.H_tc @ dc)


def schur_complement(lin: Linearization, trajectory_damping: F64 | float = 0.0) -> SchurSystem:
    """Eliminate the trajectory block.

    ``A_tt`` is factorised by :class:`_BandedCholesky` (banded Cholesky plus a dense border) when
    its structure allows and it is numerically positive definite, and by a sparse LU otherwise.
    With the Cholesky factor ``A_tt = L L^T`` only the forward substitution ``W = L^-1 H_tc`` is
    needed (``S = H_cc - W^T W``), half the work of solving with ``A_tt``. Trajectory coordinates
    that no residual touches (zero diagonal) get a unit diagonal so the factorisation exists;
    their step is zero.

    Args:
        lin: Normal equations.
        trajectory_damping: Scalar or (Nt,) values added to the diagonal of ``H_tt``.

    Returns:
        The reduced calibration system.

    Raises:
        numpy.linalg.LinAlgError: When ``H_tt`` plus damping is exactly singular.
    """
    nt = lin.layout.num_trajectory
    nc = lin.layout.num_calibration
    if nt == 0:
        return SchurSystem(
            lin.H_cc.copy(), -lin.g_c.copy(), np.zeros(0), lambda r: r, np.zeros((0, nc))
        )
    add = _trajectory_diagonal(lin.H_tt, trajectory_damping)
    rhs = np.empty((nt, nc + 1), order="F")
    rhs[:, :nc] = lin.H_tc
    rhs[:, nc] = -lin.g_t
    factor = _BandedCholesky.factorize(lin.H_tt, add)
    if factor is not None:
        w = factor.forward(rhs)
        w_x, w_g = w[:, :nc], w[:, nc]
        s = lin.H_cc - w_x.T @ w_x
        b = -lin.g_c - w_x.T @ w_g
        y_t = factor.backward(w_g)
        solve: Callable[[F64], F64] = factor.solve
    else:
        solve = _sparse_lu_solver(lin.H_tt, add)
        sol = solve(rhs)
        x, y_t = sol[:, :nc], sol[:, nc]
        s = lin.H_cc - lin.H_tc.T @ x
        b = -lin.g_c - lin.H_tc.T @ y_t
    s = 0.5 * (s + s.T)
    return SchurSystem(s, b, y_t, solve, lin.H_tc)


def _trajectory_diagonal(h_tt: sp.spmatrix, trajectory_damping: F64 | float) -> F64:
    """(Nt,) values added to the diagonal of ``H_tt``: the damping, plus 1 where it is zero."""
    nt = h_tt.shape[0]
    add = np.broadcast_to(np.asarray(trajectory_damping, dtype=np.float64), (nt,)).copy()
    add[h_tt.diagonal() <= 0.0] += 1.0
    return add


def _sparse_lu_solver(h_tt: sp.spmatrix, add: F64) -> Callable[[F64], F64]:
    """``rhs -> (H_tt + diag(add))^-1 rhs`` by SuperLU (COLAMD ordering).

    Args:
        h_tt: (Nt, Nt) sparse trajectory block.
        add: (Nt,) diagonal addition.

    Returns:
        The solver for (Nt,) or (Nt, k) right-hand sides.

    Raises:
        numpy.linalg.LinAlgError: When the matrix is exactly singular.
    """
    a_tt = (h_tt + sp.diags(add, format="csc")).tocsc()
    try:
        lu = spla.splu(a_tt, permc_spec="COLAMD")
    except RuntimeError as err:
        msg = "The trajectory block of the normal equations is singular; add damping or priors."
        raise np.linalg.LinAlgError(msg) from err
    return lu.solve  # type: ignore[no-any-return]


# Border detection: a trajectory coordinate whose row of H_tt holds more than
# _BORDER_FACTOR times the median number of non-zeros (and more than _BORDER_MIN_NONZEROS) is
# eliminated densely (IMU biases, gravity: they couple to every control point the IMU sees).
_BORDER_FACTOR = 4.0
_BORDER_MIN_NONZEROS = 64
# Beyond these sizes the banded factorisation is not worth it; SuperLU handles the general case.
_MAX_BORDER = 256
_MAX_BANDWIDTH = 512
# The forward substitution of many right-hand sides (the planes-free steps' couplings: a few
# thousand columns) is shared between the block threads in four blocks of columns, each at least
# this wide (0.20 -> 0.14 s for 2251 columns of a 4526-coordinate trajectory on 2 cores).
_FORWARD_COLUMNS = 64


def _scatter(flat: IntArray, vals: F64, shape: tuple[int, int]) -> F64:
    """Dense array of ``shape`` with ``vals`` summed at the flat indices ``flat``."""
    size = shape[0] * shape[1]
    return np.bincount(flat, vals, size).astype(np.float64, copy=False).reshape(shape)


def _band_solve(factor: F64, rhs: F64) -> F64:
    """``(L L^T)^-1 rhs`` for a lower band factor ``L`` ((bandwidth + 1, n)) and (n, k) ``rhs``."""
    # pbtrs works on Fortran-ordered columns; converting here avoids a second copy inside.
    return sla.cho_solve_banded((factor, True), np.asfortranarray(rhs), check_finite=False)


@dataclass(frozen=True)
class _BandStructure:
    """What :meth:`_BandedCholesky.factorize` derives from the sparsity pattern of ``H_tt`` alone.

    Entries are positions in the CSC data of ``H_tt``; flat indices address the dense arrays
    the entries are summed into.

    Attributes:
        order: (Nb,) H_tt indices of the band coordinates, in band order.
        border: (Nk,) H_tt indices of the border coordinates.
        bandwidth: Number of sub-diagonals of ``A_bb`` in band order.
        band: Entries of the lower band (both coordinates in the band, row >= column in band
            order).
        band_flat: Their flat indices in the (bandwidth + 1, Nb) LAPACK band storage.
        coupling: Entries with a band row and a border column.
        coupling_flat: Their flat indices in (Nb, Nk) ``A_bc``.
        corner: Entries with a border row and column.
        corner_flat: Their flat indices in (Nk, Nk) ``A_cc``.
    """

    order: IntArray
    border: IntArray
    bandwidth: int
    band: IntArray
    band_flat: IntArray
    coupling: IntArray
    coupling_flat: IntArray
    corner: IntArray
    corner_flat: IntArray


# Band structures of the latest patterns (a solve factorises matrices of one pattern many
# times); None for a pattern that is not banded enough.
_STRUCTURES: list[tuple[IntArray, IntArray, _BandStructure | None]] = []
_MAX_STRUCTURES = 4


def _band_structure(h: sp.csc_matrix) -> _BandStructure | None:
    """The band structure of the pattern of ``h`` (kept for the latest patterns), or None when
    the pattern is not banded enough for :class:`_BandedCholesky`."""
    indptr = h.indptr.astype(np.intp, copy=False)
    row = h.indices.astype(np.intp, copy=False)
    for cached_ptr, cached_row, structure in _STRUCTURES:
        if (
            cached_ptr.shape == indptr.shape
            and cached_row.shape == row.shape
            and np.array_equal(cached_ptr, indptr)
            and np.array_equal(cached_row, row)
        ):
            return structure
    structure = _new_band_structure(indptr, row)
    _STRUCTURES.insert(0, (indptr.copy(), row.copy(), structure))
    del _STRUCTURES[_MAX_STRUCTURES:]
    return structure


def _new_band_structure(indptr: IntArray, row: IntArray) -> _BandStructure | None:
    """:func:`_band_structure` computed from the CSC pattern ``(indptr, row)``."""
    n = indptr.shape[0] - 1
    counts = np.diff(indptr)  # non-zeros per column = per row (symmetric)
    col = np.repeat(np.arange(n, dtype=np.intp), counts)
    cutoff = max(_BORDER_FACTOR * float(np.median(counts)), _BORDER_MIN_NONZEROS)
    is_border = counts > cutoff
    border = np.flatnonzero(is_border)
    nk = border.size
    if nk > _MAX_BORDER or nk == n:
        return None
    row_b, col_b = is_border[row], is_border[col]
    inner = np.flatnonzero(~row_b & ~col_b)
    r_in, c_in = row[inner], col[inner]
    # The pattern without the border, as a CSR graph built without sorting (the CSC arrays of
    # a symmetric matrix are the CSR arrays of its transpose).
    inner_ptr = np.zeros(n + 1, dtype=np.intp)
    np.cumsum(np.bincount(c_in, minlength=n), out=inner_ptr[1:])
    graph = sp.csr_matrix((np.ones(r_in.size), r_in, inner_ptr), shape=(n, n))
    order = reverse_cuthill_mckee(graph, symmetric_mode=True).astype(np.intp)
    order = order[~is_border[order]]
    nb = order.size
    pos = np.empty(n, dtype=np.intp)
    pos[order] = np.arange(nb)
    pos[border] = np.arange(nk)
    pr, pc = pos[r_in], pos[c_in]
    lower = pr >= pc
    offset = pr[lower] - pc[lower]
    bandwidth = int(offset.max()) if offset.size else 0
    if bandwidth > _MAX_BANDWIDTH:
        return None
    coupling = np.flatnonzero(~row_b & col_b)
    corner = np.flatnonzero(row_b & col_b)
    return _BandStructure(
        order=order,
        border=border,
        bandwidth=bandwidth,
        band=inner[lower],
        band_flat=offset * nb + pc[lower],
        coupling=coupling,
        coupling_flat=pos[row[coupling]] * nk + pos[col[coupling]],
        corner=corner,
        corner_flat=pos[row[corner]] * nk + pos[col[corner]],
    )


@dataclass(frozen=True)
class _BandedCholesky:
    """Cholesky factorisation of ``A = H_tt + diag(add)`` as a band plus a dense border.

    The coordinates split into a *band* part, reordered by reverse Cuthill-McKee so that its
    block ``A_bb`` is banded (the interleaved so3 / r3 control points of the splines), and a small
    *border* part ``c`` (coordinates whose rows are nearly dense). ``A_bb = L L^T`` is factorised
    by LAPACK ``pbtrf`` and applied by ``pbtrs`` (or ``tbtrs`` for one triangular factor at a
    time, :meth:`forward` and :meth:`backward`); the border is eliminated with the dense Schur
    complement ``S_c = A_cc - A_cb A_bb^-1 A_bc``, which is positive definite whenever ``A`` is.

    ``pbtrs`` uses level-2 BLAS (one right-hand side at a time). A blocked level-3 substitution
    was measured faster single-threaded but its many mid-sized triangular solves start OpenBLAS
    threads, which on a loaded machine made it several times slower.

    Attributes:
        order: (Nb,) H_tt indices of the band coordinates, in band order.
        border: (Nk,) H_tt indices of the border coordinates.
        band_factor: (bandwidth + 1, Nb) lower Cholesky factor of ``A_bb`` in LAPACK band storage.
        coupling: (Nb, Nk) ``A_bc``.
        coupling_solved: (Nb, Nk) ``A_bb^-1 A_bc``.
        border_factor: (Nk, Nk) lower Cholesky factor of ``S_c``.
    """

    order: IntArray
    border: IntArray
    band_factor: F64
    coupling: F64
    coupling_solved: F64
    border_factor: F64

    @property
    def bandwidth(self) -> int:
        """Number of sub-diagonals of ``A_bb`` in band order."""
        return int(self.band_factor.shape[0]) - 1

    @classmethod
    def factorize(cls, h_tt: sp.spmatrix, add: F64) -> _BandedCholesky | None:
        """Factorise ``H_tt + diag(add)``.

        Args:
            h_tt: (Nt, Nt) symmetric sparse trajectory block (both triangles stored).
            add: (Nt,) diagonal addition.

        Returns:
            The factorisation, or None when the structure is not banded enough or the matrix is
            not numerically positive definite (the caller then uses a sparse LU).
        """
        h = sp.csc_matrix(h_tt)
        structure = _band_structure(h)
        if structure is None:
            return None
        order, border = structure.order, structure.border
        nb, nk = order.size, border.size
        val = h.data
        ab = _scatter(structure.band_flat, val[structure.band], (structure.bandwidth + 1, nb))
        ab[0] += add[order]
        try:
            factor = sla.cholesky_banded(ab, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            return None
        # A_bc and A_cc from the entries touching the border.
        coupling = _scatter(structure.coupling_flat, val[structure.coupling], (nb, nk))
        a_cc = _scatter(structure.corner_flat, val[structure.corner], (nk, nk))
        a_cc[np.diag_indices(nk)] += add[border]
        if not np.all(np.isfinite(factor)):
            return None
        if nk:
            solved = _band_solve(factor, coupling)
            s_c = a_cc - coupling.T @ solved
            try:
                border_factor = np.asarray(
                    np.linalg.cholesky(0.5 * (s_c + s_c.T)), dtype=np.float64
                )
            except np.linalg.LinAlgError:
                return None
        else:
            solved = coupling
            border_factor = a_cc
        if not np.all(np.isfinite(border_factor)):
            return None
        return cls(order, border, factor, coupling, solved, border_factor)

    def forward(self, rhs: F64) -> F64:
        """``W = L_A^-1 rhs`` with ``A = L_A L_A^T`` (so ``W^T W = rhs^T A^-1 rhs``).

        ``L_A = [[L, 0], [A_cb L^-T, L_c]]`` in (band, border) order, with ``S_c = L_c L_c^T``.

        Args:
            rhs: (Nt, k) right-hand sides in H_tt order.

        Returns:
            (Nt, k) ``W``, rows in (band, border) order.
        """
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.ndim == 1:
            return self.forward(rhs[:, None])[:, 0]
        nb, nk = self.order.size, self.border.size
        out = np.empty((nb + nk, rhs.shape[1]), order="F")

        def columns(cols: slice) -> None:
            # Each column is substituted on its own (level-2 LAPACK).
            r_b = np.asfortranarray(rhs[self.order, cols])
            if nk:
                r_c = rhs[self.border, cols] - self.coupling_solved.T @ r_b
                out[nb:, cols] = sla.solve_triangular(
                    self.border_factor, r_c, lower=True, check_finite=False
                )
            w_b, info = lapack.dtbtrs(self.band_factor, r_b, uplo="L", overwrite_b=1)
            if info != 0:
                msg = f"banded triangular solve failed (info {info})"
                raise np.linalg.LinAlgError(msg)
            out[:nb, cols] = w_b

        k = rhs.shape[1]
        # The same blocks with any number of threads: the border's matrix products need not
        # give a column the same last bits in blocks of other widths.
        block = max(_FORWARD_COLUMNS, -(-k // 4))
        map_slices(columns, k, block)
        return out

    def backward(self, w: F64) -> F64:
        """``L_A^-T w`` in H_tt order for (Nt,) ``w`` in (band, border) order."""
        nb = self.order.size
        out = np.empty(w.shape[0])
        y_b, info = lapack.dtbtrs(self.band_factor, w[:nb, None], uplo="L", trans="T")
        if info != 0:
            msg = f"banded triangular solve failed (info {info})"
            raise np.linalg.LinAlgError(msg)
        y_b = y_b[:, 0]
        if self.border.size:
            y_c = sla.solve_triangular(
                self.border_factor, w[nb:], lower=True, trans="T", check_finite=False
            )
            y_b = y_b - self.coupling_solved @ y_c
            out[self.border] = y_c
        out[self.order] = y_b
        return out

    def solve(self, rhs: F64) -> F64:
        """``A^-1 rhs``.

        Args:
            rhs: (Nt,) or (Nt, k) right-hand sides in H_tt order.

        Returns:
            Solution of the same shape.
        """
        rhs = np.asarray(rhs, dtype=np.float64)
        flat = rhs.ndim == 1
        if flat:
            rhs = rhs[:, None]
        y = _band_solve(self.band_factor, rhs[self.order])
        out = np.empty_like(rhs)
        if self.border.size:
            r_c = rhs[self.border] - self.coupling.T @ y
            x_c = sla.cho_solve((self.border_factor, True), r_c, check_finite=False)
            y = y - self.coupling_solved @ x_c
            out[self.border] = x_c
        out[self.order] = y
        return out[:, 0] if flat else out
