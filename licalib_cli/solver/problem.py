"""Least-squares problem: parameter blocks, residual blocks and assembly of the normal equations.

Residual blocks
    A residual block is any object with a ``name`` and
    ``evaluate(params, jacobians=True) -> ResidualEval``, where ``params`` maps every parameter
    block name to its current value (the block's construction shape). It returns *whitened*
    residuals ``(n, m)``: ``n`` measurements (robust-loss groups) of ``m`` residuals each (``m = 1``
    for a scalar point-to-plane residual, 3 for a gyro residual), and their Jacobians in the
    tangent coordinates of each parameter block it touches (see :mod:`.parameters`; so3 blocks use
    the right perturbation ``R Exp(delta)``). Two Jacobian forms exist:

    * :class:`DenseJacobian` (the fast path): measurement ``i`` touches elements
      ``elements[i, :a]`` of a block, with dense derivatives ``values[i, :m, :a, :d]``; e.g. a
      point touching 4 control points of 3 tangent dims has ``(n, 1, 4, 3)``.
    * :class:`SparseJacobian`: COO triplets ``(rows, cols, values)`` with ``rows`` indexing the
      flattened residual vector ``i * m + k`` and ``cols`` the block's tangent coordinates.

    Jacobians for blocks that are entirely fixed may be omitted. When called with
    ``jacobians=False`` a block may skip them (it may also return them anyway).

Normal equations
    With ``J`` and ``r`` whitened and each group reweighted by ``sqrt(rho'(|r|^2))`` (IRLS, see
    :mod:`.loss`), the solver needs ``H = J^T J`` and ``g = J^T r``, split into the trajectory
    group ``t`` and the calibration group ``c``: ``H_tt`` (sparse), ``H_tc`` (dense) and ``H_cc``
    (dense). Dense Jacobians are assembled block-wise without forming ``J``. Pieces with the same
    element pattern form a group of columns and measurements are grouped by their element tuple
    (e.g. the spline segment, the LiDAR beam); pieces whose tuple never changes (extrinsics, IMU
    intrinsics) are *constant* columns ``C``. For each keyed group ``K`` the values
    ``[K | C | r]`` are stacked once and one Gram product per group gives ``K^T K``, ``K^T C``
    and the gradient ``K^T r``: wide groups by batched BLAS products over zero-padded chunks of
    each group, narrow ones by a single sparse "one-hot" product (no sorting, no padding). The
    coupling of two keyed groups is one sparse product whose rows encode the second group when
    that group is calibration-only (it lands in the dense ``H_tc``/``H_cc``), else a Gram product
    over the partition refining both. ``H_tt`` is formed in CSC once per assembly; its sparsity
    pattern is kept and reused while the contributions keep their indices (the usual case from
    one LM iteration to the next). Residual blocks that use :class:`SparseJacobian` go through
    ``scipy.sparse`` instead.

The free coordinates are ordered trajectory blocks first (insertion order), then calibration
blocks; fixed coordinates are dropped (:class:`Layout`).

Trajectory elimination
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

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.linalg.lapack as lapack
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from licalib_cli.solver.parameters import ParameterBlock

if TYPE_CHECKING:
    from licalib_cli.solver.loss import Loss

__all__ = [
    "DenseJacobian",
    "Evaluation",
    "Layout",
    "Linearization",
    "Problem",
    "ResidualBlock",
    "ResidualEval",
    "SchurSystem",
    "SparseJacobian",
    "dense_to_coo",
    "schur_complement",
]

F64 = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

# Upper bound of m * n * k of one BLAS product in the grouped Gram assembly; OpenBLAS starts
# threads above 4 * 65536.
_BLAS_PRODUCT_LIMIT = 200_000


def dense_to_coo(
    values: npt.ArrayLike, elements: npt.ArrayLike, tangent_dim: int | None = None
) -> tuple[IntArray, IntArray, F64]:
    """COO triplets of dense per-measurement Jacobians.

    Args:
        values: (n, m, a, d) derivatives of the ``m`` residuals of measurement ``i`` with
            respect to the ``d`` tangent coordinates of its ``a`` elements.
        elements: (n, a) element indices into the block.
        tangent_dim: ``d``; taken from ``values`` when None.

    Returns:
        ``(rows, cols, vals)``, each (n * m * a * d,): ``rows = i * m + k`` (flattened residual
        index), ``cols = element * d + j`` (block tangent coordinate).
    """
    v = np.asarray(values, dtype=np.float64)
    e = np.asarray(elements, dtype=np.intp)
    n, m, _, d = v.shape
    if tangent_dim is not None and tangent_dim != d:
        msg = f"Dense Jacobian has {d} tangent coordinates per element, expected {tangent_dim}."
        raise ValueError(msg)
    rows = np.broadcast_to(np.arange(n * m, dtype=np.intp).reshape(n, m, 1, 1), v.shape)
    cols = np.broadcast_to(
        (e[:, None, :, None] * d + np.arange(d, dtype=np.intp)[None, None, None, :]), v.shape
    )
    return rows.reshape(-1), cols.reshape(-1), v.reshape(-1)


@dataclass(frozen=True)
class DenseJacobian:
    """Jacobian of a residual block with respect to one parameter block, per measurement.

    Attributes:
        block: Parameter block name.
        elements: (n, a) int element indices touched by each measurement.
        values: (n, m, a, d) derivatives of the ``m`` whitened residuals of each measurement with
            respect to the ``d`` tangent coordinates of each touched element.
    """

    block: str
    elements: npt.NDArray[np.integer]
    values: F64

    def __post_init__(self) -> None:
        elements = np.asarray(self.elements)
        if elements.ndim == 1:
            elements = elements[:, None]
        values = np.asarray(self.values, dtype=np.float64)
        if (
            values.ndim != 4
            or values.shape[0] != elements.shape[0]
            or (values.shape[2] != elements.shape[1])
        ):
            msg = (
                f"DenseJacobian for {self.block!r}: values must be (n, m, a, d) matching "
                f"elements (n, a); got {values.shape} and {elements.shape}."
            )
            raise ValueError(msg)
        object.__setattr__(self, "elements", elements.astype(np.intp, copy=False))
        object.__setattr__(self, "values", values)

    def to_coo(self) -> SparseJacobian:
        """The same Jacobian as COO triplets."""
        rows, cols, vals = dense_to_coo(self.values, self.elements)
        return SparseJacobian(self.block, rows, cols, vals)


@dataclass(frozen=True)
class SparseJacobian:
    """Jacobian of a residual block with respect to one parameter block, as COO triplets.

    Attributes:
        block: Parameter block name.
        rows: (K,) int flattened residual index ``i * m + k``.
        cols: (K,) int tangent coordinate of the block.
        values: (K,) derivatives (duplicates are summed).
    """

    block: str
    rows: npt.NDArray[np.integer]
    cols: npt.NDArray[np.integer]
    values: F64

    def __post_init__(self) -> None:
        rows = np.asarray(self.rows, dtype=np.intp).reshape(-1)
        cols = np.asarray(self.cols, dtype=np.intp).reshape(-1)
        values = np.asarray(self.values, dtype=np.float64).reshape(-1)
        if not rows.shape == cols.shape == values.shape:
            msg = f"SparseJacobian for {self.block!r}: rows, cols and values differ in length."
            raise ValueError(msg)
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "cols", cols)
        object.__setattr__(self, "values", values)


@dataclass(frozen=True)
class ResidualEval:
    """Whitened residuals of one residual block and their Jacobians.

    Attributes:
        residuals: (n, m) whitened residuals; one robust-loss group per row. A 1-D (n,) input is
            taken as ``n`` scalar groups.
        jacobians: Jacobian pieces, at most one form per block is needed; several pieces for the
            same block are summed.
    """

    residuals: F64
    jacobians: tuple[DenseJacobian | SparseJacobian, ...] = ()

    def __post_init__(self) -> None:
        r = np.asarray(self.residuals, dtype=np.float64)
        if r.ndim == 1:
            r = r[:, None]
        if r.ndim != 2:
            msg = f"Residuals must be (n,) or (n, m); got shape {r.shape}."
            raise ValueError(msg)
        object.__setattr__(self, "residuals", r)
        object.__setattr__(self, "jacobians", tuple(self.jacobians))
        n, m = r.shape
        for jac in self.jacobians:
            if isinstance(jac, DenseJacobian) and jac.values.shape[:2] != (n, m):
                msg = (
                    f"DenseJacobian for {jac.block!r} has {jac.values.shape[:2]} measurement rows; "
                    f"the residuals are {(n, m)}."
                )
                raise ValueError(msg)


@runtime_checkable
class ResidualBlock(Protocol):
    """A group of residuals with a common model (e.g. all point-to-plane residuals of a round)."""

    name: str

    def evaluate(self, params: Mapping[str, F64], jacobians: bool = True) -> ResidualEval:
        """Whitened residuals and (if ``jacobians``) their tangent-space Jacobians.

        Args:
            params: Block name -> current value (construction shape).
            jacobians: Whether Jacobians are needed.

        Returns:
            The residuals and Jacobians.
        """
        ...


@dataclass(frozen=True)
class Layout:
    """Map from block tangent coordinates to the reduced (free) solver vector.

    Attributes:
        block_names: Blocks in solver order (trajectory blocks, then calibration blocks).
        index: Block name -> (size,) position of each tangent coordinate in the reduced vector, or
            -1 when fixed.
        num_trajectory: ``Nt``, free trajectory coordinates (they come first).
        num_calibration: ``Nc``, free calibration coordinates.
        names: (Nt + Nc,) coordinate names in solver order.
        scale: (Nt + Nc,) characteristic magnitudes in solver order.
        owner: (Nt + Nc,) owning block name of each coordinate.
    """

    block_names: tuple[str, ...]
    index: Mapping[str, IntArray]
    num_trajectory: int
    num_calibration: int
    names: tuple[str, ...]
    scale: F64
    owner: tuple[str, ...]

    @property
    def num_free(self) -> int:
        """``Nt + Nc``."""
        return self.num_trajectory + self.num_calibration

    @property
    def calibration_names(self) -> tuple[str, ...]:
        """(Nc,) calibration coordinate names."""
        return self.names[self.num_trajectory :]

    @property
    def calibration_scale(self) -> F64:
        """(Nc,) calibration coordinate scales."""
        return self.scale[self.num_trajectory :]

    @property
    def calibration_owner(self) -> tuple[str, ...]:
        """(Nc,) owning block of each calibration coordinate."""
        return self.owner[self.num_trajectory :]


@dataclass(frozen=True)
class Evaluation:
    """Residual evaluation of a problem at one state.

    Attributes:
        values: Block name -> value used.
        evals: One :class:`ResidualEval` per residual block evaluated.
        losses: The loss of each residual block (None = squared).
        block_costs: Cost ``0.5 * sum rho`` of each residual block.
        cost: Total cost.
        num_residuals: Total scalar residuals.
    """

    values: Mapping[str, F64]
    evals: tuple[ResidualEval, ...]
    losses: tuple[Loss | None, ...]
    block_costs: tuple[float, ...]
    cost: float
    num_residuals: int


@dataclass(frozen=True)
class Linearization:
    """Gauss-Newton normal equations ``H dx = -g`` at one state (IRLS-reweighted).

    Attributes:
        layout: Coordinate layout used.
        cost: Cost at the linearisation point.
        num_residuals: Number of scalar residuals.
        H_tt: (Nt, Nt) sparse CSC trajectory block.
        H_tc: (Nt, Nc) dense coupling block.
        H_cc: (Nc, Nc) dense calibration block.
        g: (Nt + Nc,) gradient ``J^T r`` of the cost.
    """

    layout: Layout
    cost: float
    num_residuals: int
    H_tt: sp.csc_matrix
    H_tc: F64
    H_cc: F64
    g: F64

    @property
    def g_t(self) -> F64:
        """(Nt,) trajectory part of the gradient."""
        return self.g[: self.layout.num_trajectory]

    @property
    def g_c(self) -> F64:
        """(Nc,) calibration part of the gradient."""
        return self.g[self.layout.num_trajectory :]

    def quadratic(self, dx: F64) -> float:
        """``dx^T H dx`` for a (Nt + Nc,) step."""
        nt = self.layout.num_trajectory
        dt, dc = dx[:nt], dx[nt:]
        return float(dt @ (self.H_tt @ dt) + 2.0 * dt @ (self.H_tc @ dc) + dc @ (self.H_cc @ dc))

    def dense(self) -> F64:
        """The full (Nt + Nc, Nt + Nc) ``H`` as a dense array (small problems and tests only)."""
        top = np.hstack([self.H_tt.toarray(), self.H_tc])
        bottom = np.hstack([self.H_tc.T, self.H_cc])
        return np.vstack([top, bottom])


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


def _scatter(flat: IntArray, vals: F64, shape: tuple[int, int]) -> F64:
    """Dense array of ``shape`` with ``vals`` summed at the flat indices ``flat``."""
    size = shape[0] * shape[1]
    return np.bincount(flat, vals, size).astype(np.float64, copy=False).reshape(shape)


def _band_solve(factor: F64, rhs: F64) -> F64:
    """``(L L^T)^-1 rhs`` for a lower band factor ``L`` ((bandwidth + 1, n)) and (n, k) ``rhs``."""
    # pbtrs works on Fortran-ordered columns; converting here avoids a second copy inside.
    return sla.cho_solve_banded((factor, True), np.asfortranarray(rhs), check_finite=False)


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
        n = h_tt.shape[0]
        h = sp.csc_matrix(h_tt)
        indptr = h.indptr.astype(np.intp, copy=False)
        row = h.indices.astype(np.intp, copy=False)
        val = h.data
        counts = np.diff(indptr)  # non-zeros per column = per row (symmetric)
        col = np.repeat(np.arange(n, dtype=np.intp), counts)
        cutoff = max(_BORDER_FACTOR * float(np.median(counts)), _BORDER_MIN_NONZEROS)
        is_border = counts > cutoff
        border = np.flatnonzero(is_border)
        nk = border.size
        if nk > _MAX_BORDER or nk == n:
            return None
        row_b, col_b = is_border[row], is_border[col]
        inner = ~row_b & ~col_b
        r_in, c_in, v_in = row[inner], col[inner], val[inner]
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
        ab = _scatter(offset * nb + pc[lower], v_in[lower], (bandwidth + 1, nb))
        ab[0] += add[order]
        try:
            factor = sla.cholesky_banded(ab, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            return None
        # A_bc and A_cc from the entries touching the border.
        bc = ~row_b & col_b
        coupling = _scatter(pos[row[bc]] * nk + pos[col[bc]], val[bc], (nb, nk))
        cc = row_b & col_b
        a_cc = _scatter(pos[row[cc]] * nk + pos[col[cc]], val[cc], (nk, nk))
        a_cc[np.diag_indices(nk)] += add[border]
        if not np.all(np.isfinite(factor)):
            return None
        if nk:
            solved = _band_solve(factor, coupling)
            s_c = a_cc - coupling.T @ solved
            try:
                border_factor = np.linalg.cholesky(0.5 * (s_c + s_c.T))
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
        r_b = np.asfortranarray(rhs[self.order])
        w_b, info = lapack.dtbtrs(self.band_factor, r_b, uplo="L", overwrite_b=1)
        if info != 0:
            msg = f"banded triangular solve failed (info {info})"
            raise np.linalg.LinAlgError(msg)
        if not self.border.size:
            return w_b  # type: ignore[no-any-return]
        r_c = rhs[self.border] - self.coupling_solved.T @ rhs[self.order]
        w_c = sla.solve_triangular(self.border_factor, r_c, lower=True, check_finite=False)
        return np.concatenate([w_b, w_c])

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


# ------------------------------------------------------------------------------------- assembly
@dataclass(frozen=True)
class _GroupKey:
    """A partition of the measurements of a residual block into groups.

    Attributes:
        key: (n,) group index in ``[0, num_groups)`` of each measurement, or None for a single
            group.
        num_groups: Number of groups ``G``.
        counts: (G,) measurements per group.
        is_sorted: Whether ``key`` is non-decreasing (the groups are contiguous runs).
    """

    key: IntArray | None
    num_groups: int
    counts: IntArray
    is_sorted: bool

    def same_partition(self, other: _GroupKey) -> bool:
        """Whether both keys group the measurements identically."""
        if self.key is None or other.key is None:
            return self.key is None and other.key is None
        return self.num_groups == other.num_groups and bool(np.array_equal(self.key, other.key))


def _single_group(n: int) -> _GroupKey:
    return _GroupKey(None, 1, np.array([n], dtype=np.intp), True)


def _compress_key(raw: npt.NDArray[np.integer]) -> _GroupKey:
    """Group measurements by an integer key (dense ranks in increasing key order)."""
    n = raw.shape[0]
    if n == 0:
        return _single_group(0)
    lo, hi = int(raw.min()), int(raw.max())
    if lo == hi:
        return _single_group(n)
    shifted = (raw - lo).astype(np.intp, copy=False)
    is_sorted = bool(np.all(shifted[1:] >= shifted[:-1]))
    span = hi - lo + 1
    if span <= 4 * n + 4096:  # counting, no sort
        all_counts = np.bincount(shifted, minlength=span)
        present = all_counts > 0
        rank = np.cumsum(present, dtype=np.intp) - 1
        key = rank[shifted]
        counts = all_counts[present].astype(np.intp, copy=False)
    else:
        _, inv, cnt = np.unique(shifted, return_inverse=True, return_counts=True)
        key = inv.reshape(-1).astype(np.intp, copy=False)
        counts = cnt.astype(np.intp, copy=False)
    return _GroupKey(key, int(counts.shape[0]), counts, is_sorted)


def _element_key(elements: npt.NDArray[np.intp]) -> _GroupKey:
    """Group measurements by their tuple of touched elements."""
    n, a = elements.shape
    if n == 0:
        return _single_group(0)
    first = elements[:, 0]
    if a == 1:
        return _compress_key(first)
    rel = elements[:, 1:] - first[:, None]
    if np.all(rel == rel[0]):  # one pattern, shifted (e.g. the 4 control points of a segment)
        return _compress_key(first)
    lo, hi = elements.min(axis=0), elements.max(axis=0)
    span = (hi - lo + 1).astype(np.float64)
    if float(np.prod(span)) < 2.0**62:
        radix = np.concatenate([[1], np.cumprod((hi - lo + 1)[:-1])]).astype(np.int64)
        return _compress_key((elements - lo).astype(np.int64) @ radix)
    _, inv, cnt = np.unique(elements, axis=0, return_inverse=True, return_counts=True)
    key = inv.reshape(-1).astype(np.intp)
    return _GroupKey(key, int(cnt.shape[0]), cnt.astype(np.intp), bool(np.all(np.diff(key) >= 0)))


def _joint_key(p: _GroupKey, q: _GroupKey) -> _GroupKey:
    """The partition refining both ``p`` and ``q`` (both with keys)."""
    assert p.key is not None and q.key is not None
    return _compress_key(p.key.astype(np.int64) * q.num_groups + q.key)


@dataclass
class _Part:
    """Dense Jacobian columns of one parameter block in the assembly of a residual block.

    Attributes:
        elements: (n, a) touched elements of each measurement.
        table: (num_elements, d) reduced column of each element coordinate (-1 where fixed).
        values: (n, m, a * d) whitened derivatives (before the robust-loss reweighting).
        traj: Whether the block belongs to the trajectory group.
    """

    elements: npt.NDArray[np.intp]
    table: IntArray
    values: F64
    traj: bool

    @property
    def width(self) -> int:
        """Number of columns ``w = a * d``."""
        return int(self.values.shape[2])

    def cols_at(self, rows: IntArray) -> IntArray:
        """(len(rows), w) reduced columns of the given measurements (-1 where fixed)."""
        return self.table[self.elements[rows]].reshape(rows.shape[0], self.width)


@dataclass
class _PartGroup:
    """Parts whose measurements are grouped the same way (equal columns within each group)."""

    key: _GroupKey
    parts: list[_Part]

    @property
    def width(self) -> int:
        """Total number of columns."""
        return sum(p.width for p in self.parts)

    @property
    def traj(self) -> npt.NDArray[np.bool_]:
        """(width,) trajectory flag of each column."""
        if not self.parts:
            return np.zeros(0, dtype=bool)
        return np.concatenate([np.full(p.width, p.traj) for p in self.parts])

    @property
    def values(self) -> list[F64]:
        """The parts' (n, m, w_i) values."""
        return [p.values for p in self.parts]

    def cols_at(self, rows: IntArray) -> IntArray:
        """(len(rows), width) reduced columns of the given measurements."""
        if not self.parts:
            return np.zeros((rows.shape[0], 0), dtype=np.intp)
        return np.concatenate([p.cols_at(rows) for p in self.parts], axis=1)


def _stack(blocks: list[F64], sqrt_w: F64 | None) -> F64:
    """(n, m, w_i) arrays (2-D (n, m) arrays count as one column) side by side, times ``sqrt_w``."""
    cols = [b[:, :, None] if b.ndim == 2 else b for b in blocks]
    n, m = cols[0].shape[:2]
    width = sum(c.shape[2] for c in cols)
    if sqrt_w is None:
        return np.concatenate(cols, axis=2) if len(cols) > 1 else np.ascontiguousarray(cols[0])
    out = np.empty((n, m, width))
    w = sqrt_w[:, None, None]
    start = 0
    for c in cols:
        np.multiply(c, w, out=out[:, :, start : start + c.shape[2]])
        start += c.shape[2]
    return out


# Cost model of one batched Gram product (microseconds): a fixed cost per product, a cost per
# output value and a cost per multiply-add; it chooses the chunk size (only the ratios matter).
_COST_PER_PRODUCT = 0.3
_COST_PER_OUTPUT = 1.0e-3
_COST_PER_MULTIPLY = 7.0e-5
_CHUNK_CANDIDATES = np.array(
    [1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024, 2048],
    dtype=np.intp,
)
# Keyed groups at most this wide use the one-hot sparse product instead of padded chunks.
_ONE_HOT_MAX_WIDTH = 8
# Largest dense output (values) of a one-hot product.
_ONE_HOT_MAX_OUTPUT = 1 << 22


def _choose_chunk(counts: IntArray, m: int, left: int, right: int) -> int:
    """Chunk size (measurements per product) minimising the modelled cost of the Gram products.

    Every group of ``counts[g]`` measurements is split into ``ceil(counts[g] / chunk)`` zero-padded
    chunks: small chunks cost many products, large chunks cost padding. Products stay below
    ``_BLAS_PRODUCT_LIMIT`` multiply-adds so that none starts BLAS threads.
    """
    limit = max(1, _BLAS_PRODUCT_LIMIT // max(m * left * right, 1))
    top = int(counts.max())
    cands = np.unique(np.minimum(np.append(_CHUNK_CANDIDATES, top), min(limit, top)))
    values, freq = np.unique(counts, return_counts=True)
    chunks = (freq[:, None] * (-(-values[:, None] // cands[None, :]))).sum(axis=0)
    per_product = _COST_PER_PRODUCT + _COST_PER_OUTPUT * left * right
    cost = chunks * (per_product + _COST_PER_MULTIPLY * cands * m * left * right)
    return int(cands[int(np.argmin(cost))])


class _GroupPlan:
    """Measurements of a residual block split by group into zero-padded chunks of equal size.

    Each group's measurements go to ``ceil(count / chunk)`` consecutive chunks of ``chunk``
    measurements (the last one zero-padded), so that every group's ``A^T B`` is a sum of small
    BLAS products of one batched ``matmul``; a sparse indicator matrix adds the chunk products of
    each group.

    Attributes:
        rep: (G,) one measurement of each group (its first).
        num_groups: ``G``.
        chunk: Measurements per chunk.
        num_chunks: Total number of chunks.
        summer: (G, num_chunks) sparse indicator of the chunks of each group, or None when every
            group is one chunk.
        source: (num_chunks * chunk,) measurement copied to each buffer row (0 for padding).
        padding: Buffer rows that are padding.
        identity: Whether the buffer is the measurements in their own order (no copy needed).
    """

    def __init__(self, key: _GroupKey, n: int, m: int, left: int, right: int) -> None:
        counts = key.counts
        num_groups = key.num_groups
        order: IntArray | None = None
        if key.key is not None and not key.is_sorted:
            # numpy sorts 16-bit integers stably by radix sort (linear time)
            k = key.key.astype(np.uint16) if num_groups <= 1 << 16 else key.key
            order = np.argsort(k, kind="stable").astype(np.intp, copy=False)
        starts = np.zeros(num_groups, dtype=np.intp)
        np.cumsum(counts[:-1], out=starts[1:])
        self.rep = starts if order is None else order[starts]
        self.num_groups = num_groups
        self.chunk = _choose_chunk(counts, m, left, right) if n else 1
        chunks_per_group = -(-counts // self.chunk)
        chunk_start = np.zeros(num_groups, dtype=np.intp)
        np.cumsum(chunks_per_group[:-1], out=chunk_start[1:])
        self.num_chunks = int(chunks_per_group.sum())
        self.summer: sp.csr_matrix | None = None
        if self.num_chunks != num_groups:
            self.summer = sp.csr_matrix(
                (
                    np.ones(self.num_chunks),
                    np.arange(self.num_chunks, dtype=np.intp),
                    np.append(chunk_start, self.num_chunks),
                ),
                shape=(num_groups, self.num_chunks),
            )
        # source measurement of each row of the padded buffer (rows in group order)
        rows = self.num_chunks * self.chunk
        dest = np.arange(n, dtype=np.intp) + np.repeat(chunk_start * self.chunk - starts, counts)
        self.identity = order is None and rows == n  # no padding and no reordering
        self.source = np.zeros(rows, dtype=np.intp)
        self.source[dest] = np.arange(n, dtype=np.intp) if order is None else order
        padding = np.ones(rows, dtype=bool)
        padding[dest] = False
        self.padding = np.flatnonzero(padding)

    def pad(self, stacked: F64) -> F64:
        """(n, m, W) stacked values -> (num_chunks, chunk * m, W) buffer, padding rows zero."""
        _, m, width = stacked.shape
        if self.identity:
            out = np.ascontiguousarray(stacked)
        else:
            out = np.empty((self.source.shape[0], m, width))
            np.take(stacked, self.source, axis=0, out=out, mode="clip")
            out[self.padding] = 0.0
        return out.reshape(self.num_chunks, self.chunk * m, width)

    def gram(self, buf: F64, left: slice, right: slice) -> F64:
        """Per-group ``A^T B`` of two column ranges of a padded buffer -> (G, p, q)."""
        prods = np.matmul(buf[:, :, left].transpose(0, 2, 1), buf[:, :, right])
        if self.summer is None:
            return prods
        k, p, q = prods.shape
        return np.asarray(self.summer @ prods.reshape(k, p * q)).reshape(-1, p, q)


def _one_hot_gram(key: _GroupKey, stacked: F64, left: int) -> F64:
    """Per-group ``A^T B`` by one sparse-dense product, without sorting or padding.

    ``A`` is the first ``left`` columns of ``stacked``; the sparse (G * left, n * m) matrix holds
    ``A``'s values at row ``group * left + j``, so its product with the (n * m, W) stacked values
    is every group's Gram block at once.

    Args:
        key: Grouping of the n measurements.
        stacked: (n, m, W) weighted values.
        left: Number of leading columns forming ``A``.

    Returns:
        (G, left, W) blocks.
    """
    n, m, width = stacked.shape
    assert key.key is not None
    rows = key.key[:, None, None] * left + np.arange(left, dtype=np.intp)
    data = stacked[:, :, :left]
    a_t = sp.csc_matrix(
        (
            data.reshape(-1),
            np.broadcast_to(rows, data.shape).reshape(-1),
            np.arange(0, n * m * left + 1, left, dtype=np.intp),
        ),
        shape=(key.num_groups * left, n * m),
    )
    return np.asarray(a_t @ stacked.reshape(n * m, width)).reshape(key.num_groups, left, width)


def _add_gradient(g: F64, cols: IntArray, vals: F64) -> None:
    """``g[cols] += vals`` (summing duplicates, skipping -1)."""
    cols = cols.reshape(-1)
    vals = vals.reshape(-1)
    valid = cols >= 0
    if not np.all(valid):
        cols, vals = cols[valid], vals[valid]
    g += np.bincount(cols, vals, g.size)


@dataclass(frozen=True)
class _TrajectoryPattern:
    """Sparsity pattern of ``H_tt`` for one sequence of contributions (reused while unchanged).

    Attributes:
        signature: The (rows, cols) index arrays of every contribution, in order.
        slots: (K,) position in ``indices`` of each expanded contribution value.
        indptr: (Nt + 1,) CSC column pointers.
        indices: (nnz,) CSC row indices (sorted within columns).
    """

    signature: tuple[tuple[IntArray, IntArray], ...]
    slots: IntArray
    indptr: IntArray
    indices: IntArray

    def matches(self, signature: list[tuple[IntArray, IntArray]]) -> bool:
        """Whether ``signature`` has the same index arrays."""
        if len(signature) != len(self.signature):
            return False
        return all(
            r0.shape == r1.shape
            and c0.shape == c1.shape
            and np.array_equal(r0, r1)
            and np.array_equal(c0, c1)
            for (r0, c0), (r1, c1) in zip(self.signature, signature, strict=True)
        )


class _Accumulator:
    """Collects ``H`` contributions: ``H_tt`` as index/value blocks, dense ``H_tc`` and ``H_cc``.

    ``H_tt`` contributions are kept as broadcastable ``(rows, cols, values)`` blocks; the CSC
    matrix is formed once at the end, reusing the sparsity pattern of the previous assembly
    (``pattern``) when the contributions have the same indices.
    """

    def __init__(self, nt: int, nc: int, pattern: _TrajectoryPattern | None = None) -> None:
        self.nt, self.nc = nt, nc
        self.tt: list[tuple[IntArray, IntArray, F64]] = []
        self.h_tc = np.zeros(nt * nc)
        self.h_cc = np.zeros(nc * nc)
        self.pattern = pattern

    def add_tt(self, rows: IntArray, cols: IntArray, vals: F64) -> None:
        """``H[rows, cols] += vals`` for trajectory indices (broadcasting to ``vals``' shape)."""
        self.tt.append((rows, cols, vals))

    def add_tc(self, rows: IntArray, cols: IntArray, vals: F64) -> None:
        """``H_tc[rows, cols - nt] += vals`` (rows trajectory, cols calibration; no -1)."""
        flat = np.broadcast_to(rows * self.nc + (cols - self.nt), vals.shape)
        self.h_tc += np.bincount(flat.reshape(-1), vals.reshape(-1), self.h_tc.size)

    def add_cc(self, rows: IntArray, cols: IntArray, vals: F64, sym: bool) -> None:
        """``H_cc[rows - nt, cols - nt] += vals`` (and the transpose when ``sym``; no -1)."""
        r, c = rows - self.nt, cols - self.nt
        flat = np.broadcast_to(r * self.nc + c, vals.shape).reshape(-1)
        self.h_cc += np.bincount(flat, vals.reshape(-1), self.h_cc.size)
        if sym:
            flat = np.broadcast_to(c * self.nc + r, vals.shape).reshape(-1)
            self.h_cc += np.bincount(flat, vals.reshape(-1), self.h_cc.size)

    def add_block(
        self,
        rows: IntArray,
        cols: IntArray,
        blocks: F64,
        row_traj: npt.NDArray[np.bool_],
        col_traj: npt.NDArray[np.bool_],
        self_pair: bool,
    ) -> None:
        """Add per-group dense blocks.

        Args:
            rows: (G, p) reduced row indices (-1 fixed).
            cols: (G, q) reduced column indices (-1 fixed).
            blocks: (G, p, q) values.
            row_traj: (p,) trajectory flag of each row position.
            col_traj: (q,) trajectory flag of each column position.
            self_pair: The blocks are ``A^T A`` of one piece (already symmetric, all positions).
        """
        sym = not self_pair
        # Fixed coordinates: zero their values and point them at a valid index of the same group.
        rvalid, cvalid = rows >= 0, cols >= 0
        if not np.all(rvalid):
            blocks = blocks * rvalid[:, :, None]
            rows = np.where(rvalid, rows, np.where(row_traj, 0, self.nt))
        if not np.all(cvalid):
            blocks = blocks * cvalid[:, None, :]
            cols = np.where(cvalid, cols, np.where(col_traj, 0, self.nt))
        for r_is_t, c_is_t in ((True, True), (True, False), (False, True), (False, False)):
            rmask = row_traj if r_is_t else ~row_traj
            cmask = col_traj if c_is_t else ~col_traj
            if not (np.any(rmask) and np.any(cmask)):
                continue
            if self_pair and not r_is_t and c_is_t:
                continue  # the (calib, traj) part of a self pair mirrors its (traj, calib) part
            sub = blocks if np.all(rmask) else blocks[:, rmask]
            sub = sub if np.all(cmask) else sub[:, :, cmask]
            r = (rows if np.all(rmask) else rows[:, rmask])[:, :, None]
            c = (cols if np.all(cmask) else cols[:, cmask])[:, None, :]
            if r_is_t and c_is_t:
                self.add_tt(r, c, sub)
                if sym:
                    self.add_tt(c.transpose(0, 2, 1), r.transpose(0, 2, 1), sub.transpose(0, 2, 1))
            elif r_is_t:
                self.add_tc(r, c, sub)
            elif c_is_t:
                self.add_tc(c.transpose(0, 2, 1), r.transpose(0, 2, 1), sub.transpose(0, 2, 1))
            else:
                self.add_cc(r, c, sub, sym)

    def add_full(self, h: sp.coo_matrix) -> None:
        """Add a full symmetric (N, N) sparse contribution."""
        r, c, v = h.row.astype(np.intp), h.col.astype(np.intp), h.data
        rt, ct = r < self.nt, c < self.nt
        self.add_tt(r[rt & ct], c[rt & ct], v[rt & ct])
        tc, cc = rt & ~ct, ~rt & ~ct
        self.add_tc(r[tc], c[tc], v[tc])
        self.add_cc(r[cc], c[cc], v[cc], False)

    def result(self) -> tuple[sp.csc_matrix, F64, F64]:
        """``(H_tt, H_tc, H_cc)``; ``self.pattern`` is the pattern used for ``H_tt`` afterwards."""
        nt, nc = self.nt, self.nc
        signature = [(r, c) for r, c, _ in self.tt]
        vals = [
            np.broadcast_to(v, np.broadcast_shapes(r.shape, c.shape, v.shape))
            for r, c, v in self.tt
        ]
        v = np.concatenate([x.reshape(-1) for x in vals]) if vals else np.zeros(0)
        pattern = self.pattern
        if pattern is None or not pattern.matches(signature):
            if vals:
                flat = np.concatenate(
                    [
                        (
                            np.broadcast_to(c, x.shape).astype(np.int64) * nt
                            + np.broadcast_to(r, x.shape)
                        ).reshape(-1)
                        for (r, c), x in zip(signature, vals, strict=True)
                    ]
                )
            else:
                flat = np.zeros(0, dtype=np.int64)
            uniq, slots = np.unique(flat, return_inverse=True)
            col_u = (uniq // nt).astype(np.intp)
            indptr = np.zeros(nt + 1, dtype=np.intp)
            np.cumsum(np.bincount(col_u, minlength=nt), out=indptr[1:])
            pattern = _TrajectoryPattern(
                tuple((r.copy(), c.copy()) for r, c in signature),
                slots.reshape(-1).astype(np.intp),
                indptr,
                (uniq % nt).astype(np.intp),
            )
            self.pattern = pattern
        data = np.bincount(pattern.slots, v, pattern.indices.shape[0])
        h_tt = sp.csc_matrix((data, pattern.indices.copy(), pattern.indptr.copy()), shape=(nt, nt))
        h_cc = self.h_cc.reshape(nc, nc)
        return h_tt, self.h_tc.reshape(nt, nc), 0.5 * (h_cc + h_cc.T)


def _first_of_each_group(key: _GroupKey) -> IntArray:
    """(G,) index of the first measurement of each group."""
    assert key.key is not None
    n = key.key.shape[0]
    first = np.empty(key.num_groups, dtype=np.intp)
    first[key.key[::-1]] = np.arange(n - 1, -1, -1, dtype=np.intp)
    return first


def _encoded_size(layout: Layout, q: _PartGroup) -> int:
    """Dense output size of :func:`_add_encoded_pair` with ``q`` as the encoded group."""
    return layout.num_free * q.key.num_groups * q.width


def _add_encoded_pair(
    p: _PartGroup,
    p_stacked: F64,
    q: _PartGroup,
    q_stacked: F64,
    q_rep: IntArray,
    layout: Layout,
    acc: _Accumulator,
) -> None:
    """Add the coupling of two keyed groups when ``q`` holds calibration columns only.

    One sparse (N * G_q, n * m) matrix holds ``p``'s values at rows ``col + N * group_q`` (``N``
    free coordinates, ``col`` the reduced column of the value); its product with ``q``'s
    (n * m, w_q) values is, for every group of ``q``, the dense coupling of all coordinates with
    that group's columns. No sorting or padding is needed.

    Args:
        p: Any keyed group.
        p_stacked: (n, m, >= p.width) weighted values, ``p`` first.
        q: A keyed group of calibration columns.
        q_stacked: (n, m, >= q.width) weighted values, ``q`` first.
        q_rep: (G_q,) one measurement of each group of ``q``.
        layout: The layout (``N = layout.num_free``).
        acc: Receives ``H_tc`` (trajectory rows) and ``H_cc`` (calibration rows, both triangles).
    """
    n, m = p_stacked.shape[:2]
    big = layout.num_free
    nt = layout.num_trajectory
    assert q.key.key is not None
    pw, qw = p.width, q.width
    # reduced columns of p per group of p, then per measurement
    assert p.key.key is not None
    table = p.cols_at(_first_of_each_group(p.key))
    p_group = p.key.key
    data = np.ascontiguousarray(p_stacked[:, :, :pw])
    if np.any(table < 0):
        data *= (table >= 0)[p_group][:, None, :]
        table = np.maximum(table, 0)
    index_dtype = np.int32 if big * q.key.num_groups < 2**31 else np.int64
    rows = np.take(table.astype(index_dtype), p_group, axis=0)
    rows += (big * q.key.key).astype(index_dtype)[:, None]
    a_t = sp.csc_matrix(
        (
            data.reshape(-1),
            np.broadcast_to(rows[:, None, :], (n, m, pw)).reshape(-1),
            np.arange(0, n * m * pw + 1, pw, dtype=index_dtype),
        ),
        shape=(big * q.key.num_groups, n * m),
    )
    rhs = np.ascontiguousarray(q_stacked[:, :, :qw]).reshape(n * m, qw)
    out = np.asarray(a_t @ rhs).reshape(q.key.num_groups, big, qw)
    q_cols = q.cols_at(q_rep)  # (G_q, qw)
    valid = q_cols >= 0
    flat_cols = q_cols[valid]
    if np.unique(flat_cols).size == flat_cols.size:  # distinct columns: one fancy-indexed add
        vals = out.transpose(1, 0, 2)[:, valid]  # (big, number of valid columns)
        h_tc = acc.h_tc.reshape(nt, acc.nc)
        h_tc[:, flat_cols - nt] += vals[:nt]
        if big > nt:
            h_cc = acc.h_cc.reshape(acc.nc, acc.nc)
            h_cc[:, flat_cols - nt] += vals[nt:]
            h_cc[flat_cols - nt, :] += vals[nt:].T
        return
    if not np.all(valid):
        out = out * valid[:, None, :]
        q_cols = np.where(valid, q_cols, nt)
    q_cols = q_cols[:, None, :]
    if nt:
        acc.add_tc(np.arange(nt, dtype=np.intp)[None, :, None], q_cols, out[:, :nt])
    if big > nt:
        acc.add_cc(np.arange(nt, big, dtype=np.intp)[None, :, None], q_cols, out[:, nt:], True)


class Problem:
    """Parameter blocks plus residual blocks (each with an optional robust loss)."""

    def __init__(self) -> None:
        """Create an empty problem."""
        self._blocks: dict[str, ParameterBlock] = {}
        self._residuals: list[ResidualBlock] = []
        self._losses: list[Loss | None] = []
        # sparsity pattern of the last assembled H_tt, reused while the contributions keep it
        self._tt_pattern: _TrajectoryPattern | None = None

    # ------------------------------------------------------------------------------ building
    def add_parameter_block(self, block: ParameterBlock) -> ParameterBlock:
        """Add a parameter block.

        Args:
            block: The block; its name must be unique.

        Returns:
            The same block.

        Raises:
            ValueError: When the name is taken.
        """
        if block.name in self._blocks:
            msg = f"A parameter block named {block.name!r} already exists."
            raise ValueError(msg)
        self._blocks[block.name] = block
        return block

    def add_residual_block(self, residual: ResidualBlock, loss: Loss | None = None) -> None:
        """Add a residual block.

        Args:
            residual: The residual block.
            loss: Robust loss applied to each of its residual groups (None = plain squares).
        """
        self._residuals.append(residual)
        self._losses.append(loss)

    def remove_residual_blocks(self) -> None:
        """Drop every residual block (e.g. before re-associating points in a new round)."""
        self._residuals.clear()
        self._losses.clear()

    @property
    def parameter_blocks(self) -> tuple[ParameterBlock, ...]:
        """All parameter blocks in insertion order."""
        return tuple(self._blocks.values())

    @property
    def residual_blocks(self) -> tuple[ResidualBlock, ...]:
        """All residual blocks in insertion order."""
        return tuple(self._residuals)

    def __getitem__(self, name: str) -> ParameterBlock:
        """The parameter block called ``name``."""
        return self._blocks[name]

    def __contains__(self, name: object) -> bool:
        """Whether a parameter block called ``name`` exists."""
        return name in self._blocks

    # ------------------------------------------------------------------------------- state
    def values(self) -> dict[str, F64]:
        """Block name -> current value."""
        return {name: b.value for name, b in self._blocks.items()}

    def set_values(self, values: Mapping[str, npt.ArrayLike]) -> None:
        """Set the values of the named blocks."""
        for name, v in values.items():
            self._blocks[name].set_value(v)

    def layout(self) -> Layout:
        """The reduced-coordinate layout for the current fixed masks."""
        order = [b for b in self._blocks.values() if b.group == "trajectory"]
        order += [b for b in self._blocks.values() if b.group == "calibration"]
        index: dict[str, IntArray] = {}
        names: list[str] = []
        scales: list[F64] = []
        owner: list[str] = []
        offset = 0
        nt = 0
        for block in order:
            free = ~block.fixed_mask
            idx = np.full(block.size, -1, dtype=np.intp)
            k = int(np.count_nonzero(free))
            idx[free] = np.arange(offset, offset + k)
            index[block.name] = idx
            names.extend(np.asarray(block.coord_names, dtype=object)[free].tolist())
            scales.append(block.scale[free])
            owner.extend([block.name] * k)
            offset += k
            if block.group == "trajectory":
                nt = offset
        scale = np.concatenate(scales) if scales else np.zeros(0)
        return Layout(
            block_names=tuple(b.name for b in order),
            index=index,
            num_trajectory=nt,
            num_calibration=offset - nt,
            names=tuple(names),
            scale=scale,
            owner=tuple(owner),
        )

    def retracted_values(self, dx: F64, layout: Layout) -> dict[str, F64]:
        """Block values after a step in reduced coordinates (the problem is not changed).

        Args:
            dx: (Nt + Nc,) step in solver order.
            layout: The layout ``dx`` refers to.

        Returns:
            Block name -> stepped value (unchanged blocks keep their current value).
        """
        out = self.values()
        for name in layout.block_names:
            idx = layout.index[name]
            free = idx >= 0
            if not np.any(free):
                continue
            delta = np.zeros(idx.size)
            delta[free] = dx[idx[free]]
            out[name] = self._blocks[name].retracted(delta)
        return out

    # -------------------------------------------------------------------------- evaluation
    def evaluate(
        self,
        values: Mapping[str, F64] | None = None,
        *,
        jacobians: bool = True,
        residual_blocks: Iterable[ResidualBlock] | None = None,
    ) -> Evaluation:
        """Evaluate residual blocks.

        Args:
            values: Block values to use (default: the current values).
            jacobians: Whether Jacobians are requested.
            residual_blocks: Subset of the problem's residual blocks (default: all).

        Returns:
            The evaluation with costs.
        """
        vals = self.values() if values is None else dict(values)
        if residual_blocks is None:
            chosen = list(zip(self._residuals, self._losses, strict=True))
        else:
            loss_of = {id(r): loss for r, loss in zip(self._residuals, self._losses, strict=True)}
            chosen = [(r, loss_of.get(id(r))) for r in residual_blocks]
        evals: list[ResidualEval] = []
        losses: list[Loss | None] = []
        costs: list[float] = []
        num = 0
        for residual, loss in chosen:
            ev = residual.evaluate(vals, jacobians=jacobians)
            s = np.einsum("ij,ij->i", ev.residuals, ev.residuals)
            rho = s if loss is None else loss(s)[0]
            evals.append(ev)
            losses.append(loss)
            costs.append(0.5 * float(np.sum(rho)))
            num += ev.residuals.size
        cost = float(np.sum(costs)) if costs else 0.0
        return Evaluation(vals, tuple(evals), tuple(losses), tuple(costs), cost, num)

    def linearize(self, evaluation: Evaluation, layout: Layout | None = None) -> Linearization:
        """Assemble ``H`` and ``g`` from an evaluation with Jacobians.

        Args:
            evaluation: Output of :meth:`evaluate` with ``jacobians=True``.
            layout: Coordinate layout (default: :meth:`layout`).

        Returns:
            The normal equations.

        Raises:
            ValueError: When a Jacobian names an unknown block or has the wrong tangent size.
        """
        layout = self.layout() if layout is None else layout
        g = np.zeros(layout.num_free)
        acc = _Accumulator(layout.num_trajectory, layout.num_calibration, self._tt_pattern)
        for ev, loss in zip(evaluation.evals, evaluation.losses, strict=True):
            r = ev.residuals
            if r.shape[0] == 0:
                continue
            sqrt_w: F64 | None = None
            if loss is not None:
                sqrt_w = np.sqrt(loss(np.einsum("ij,ij->i", r, r))[1])
            if any(isinstance(j, SparseJacobian) for j in ev.jacobians):
                r_w = r if sqrt_w is None else r * sqrt_w[:, None]
                self._linearize_sparse(ev, r_w, sqrt_w, layout, g, acc)
            else:
                self._linearize_dense(ev, sqrt_w, layout, g, acc)
        h_tt, h_tc, h_cc = acc.result()
        self._tt_pattern = acc.pattern
        return Linearization(layout, evaluation.cost, evaluation.num_residuals, h_tt, h_tc, h_cc, g)

    def _block_index(self, jac: DenseJacobian | SparseJacobian, layout: Layout) -> IntArray | None:
        if jac.block not in self._blocks:
            msg = f"A Jacobian refers to the unknown parameter block {jac.block!r}."
            raise ValueError(msg)
        block = self._blocks[jac.block]
        if isinstance(jac, DenseJacobian) and jac.values.shape[3] != block.tangent_dim:
            msg = (
                f"The Jacobian for {jac.block!r} has {jac.values.shape[3]} columns per element; "
                f"the block's tangent dimension is {block.tangent_dim}."
            )
            raise ValueError(msg)
        idx = layout.index[jac.block]
        if not np.any(idx >= 0):
            return None
        return idx

    def _linearize_dense(
        self,
        ev: ResidualEval,
        sqrt_w: F64 | None,
        layout: Layout,
        g: F64,
        acc: _Accumulator,
    ) -> None:
        """Add the contribution of a residual block whose Jacobians are all dense.

        Jacobian pieces with the same element pattern form a part group; groups whose element
        tuple is the same for every measurement (extrinsics, time offset, IMU intrinsics) are
        *constant* (``C``). Every keyed group ``K`` (spline segments, LiDAR beams) has its values
        stacked as ``[K | C | r]`` and one per-group Gram product gives ``K^T K``, ``K^T C`` and
        the gradient ``K^T r`` (and, for the first group, ``C^T C`` and ``C^T r`` summed over its
        groups). Two keyed groups are coupled either by one sparse product whose rows encode the
        second group (when it is calibration-only, the coupling lands in the dense blocks) or by
        the partition refining both. ``r`` and every Jacobian column are reweighted by
        ``sqrt_w``.
        """
        r = ev.residuals
        n, m = r.shape
        patterns: list[tuple[npt.NDArray[np.intp], list[_Part]]] = []
        for jac in ev.jacobians:
            assert isinstance(jac, DenseJacobian)
            idx = self._block_index(jac, layout)
            if idx is None:
                continue
            block = self._blocks[jac.block]
            a, d = jac.values.shape[2:]
            part = _Part(
                jac.elements,
                idx.reshape(block.num_elements, d),
                jac.values.reshape(n, m, a * d),
                block.group == "trajectory",
            )
            for elements, parts in patterns:
                if elements is jac.elements or (
                    elements.shape == jac.elements.shape and np.array_equal(elements, jac.elements)
                ):
                    parts.append(part)
                    break
            else:
                patterns.append((jac.elements, [part]))
        if not patterns:
            return
        keyed: list[_PartGroup] = []
        constant: list[_Part] = []
        for elements, parts in patterns:
            key = _element_key(elements)
            if key.key is None:
                constant.extend(parts)
                continue
            for group in keyed:
                if group.key.same_partition(key):
                    group.parts.extend(parts)
                    break
            else:
                keyed.append(_PartGroup(key, parts))
        const = _PartGroup(_single_group(n), constant)
        pc = const.width
        c_cols = const.cols_at(np.zeros(1, dtype=np.intp))  # (1, pc): the same in every row
        c_traj = const.traj

        def add_constant(blocks: F64) -> None:
            """``C^T C`` and ``C^T r`` from their (pc, pc + 1) sums over all measurements."""
            if pc:
                acc.add_block(c_cols, c_cols, blocks[None, :, :pc], c_traj, c_traj, True)
                _add_gradient(g, c_cols, blocks[:, pc])

        if not keyed:
            plan = _GroupPlan(const.key, n, m, pc, pc + 1)
            buf = plan.pad(_stack([*const.values, r], sqrt_w))
            add_constant(plan.gram(buf, slice(0, pc), slice(None)).sum(axis=0))
            return
        stacks: list[F64] = []
        reps: list[IntArray] = []
        for i, group in enumerate(keyed):
            pk = group.width
            left = pk + pc if i == 0 else pk
            stacked = _stack([*group.values, *const.values, r], sqrt_w)  # (n, m, pk + pc + 1)
            width = stacked.shape[2]
            num_groups = group.key.num_groups
            if pk <= _ONE_HOT_MAX_WIDTH and num_groups * left * width <= _ONE_HOT_MAX_OUTPUT:
                blocks = _one_hot_gram(group.key, stacked, left)
                rep = _first_of_each_group(group.key)
            else:
                plan = _GroupPlan(group.key, n, m, left, width)
                blocks = plan.gram(plan.pad(stacked), slice(0, left), slice(None))
                rep = plan.rep
            stacks.append(stacked)
            reps.append(rep)
            k_cols = group.cols_at(rep)
            k_traj = group.traj
            acc.add_block(k_cols, k_cols, blocks[:, :pk, :pk], k_traj, k_traj, True)
            if pc:
                c_rep = np.broadcast_to(c_cols, (num_groups, pc))
                acc.add_block(k_cols, c_rep, blocks[:, :pk, pk:-1], k_traj, c_traj, False)
            _add_gradient(g, k_cols, blocks[:, :pk, -1])
            if i == 0:
                add_constant(blocks[:, pk:, pk:].sum(axis=0))
        for i, p in enumerate(keyed):
            for j in range(i + 1, len(keyed)):
                q = keyed[j]
                a, b = (i, j) if not np.any(q.traj) else (j, i)
                if not np.any(keyed[b].traj) and _encoded_size(layout, keyed[b]) <= (
                    _ONE_HOT_MAX_OUTPUT
                ):
                    _add_encoded_pair(
                        keyed[a], stacks[a], keyed[b], stacks[b], reps[b], layout, acc
                    )
                    continue
                plan = _GroupPlan(_joint_key(p.key, q.key), n, m, p.width, q.width)
                stacked = np.concatenate(
                    [stacks[i][:, :, : p.width], stacks[j][:, :, : q.width]], 2
                )
                blocks = plan.gram(plan.pad(stacked), slice(0, p.width), slice(p.width, None))
                acc.add_block(
                    p.cols_at(plan.rep), q.cols_at(plan.rep), blocks, p.traj, q.traj, False
                )

    def _linearize_sparse(
        self,
        ev: ResidualEval,
        r: F64,
        sqrt_w: F64 | None,
        layout: Layout,
        g: F64,
        acc: _Accumulator,
    ) -> None:
        n, m = r.shape
        rows_l, cols_l, vals_l = [], [], []
        for jac in ev.jacobians:
            idx = self._block_index(jac, layout)
            if idx is None:
                continue
            coo = jac.to_coo() if isinstance(jac, DenseJacobian) else jac
            gcols = idx[coo.cols]
            keep = gcols >= 0
            vals = coo.values[keep]
            rows = coo.rows[keep]
            if sqrt_w is not None:
                vals = vals * sqrt_w[rows // m]
            rows_l.append(rows)
            cols_l.append(gcols[keep])
            vals_l.append(vals)
        if not rows_l:
            return
        jmat = sp.csr_matrix(
            (np.concatenate(vals_l), (np.concatenate(rows_l), np.concatenate(cols_l))),
            shape=(n * m, g.size),
        )
        g += jmat.T @ r.reshape(-1)
        acc.add_full((jmat.T @ jmat).tocoo())
