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
    (dense). Dense Jacobians are assembled block-wise without forming ``J``: pieces with the same
    element pattern are concatenated, measurements are grouped by their element indices, and each
    group's ``A^T B`` is formed with small BLAS products. Residual blocks that use
    :class:`SparseJacobian` go through ``scipy.sparse`` instead.

The free coordinates are ordered trajectory blocks first (insertion order), then calibration
blocks; fixed coordinates are dropped (:class:`Layout`).

Trajectory elimination
    :func:`schur_complement` factorises ``A_tt = H_tt + damping``. Coordinates whose rows are
    nearly dense (IMU biases, gravity) form a border; the rest, reordered by reverse
    Cuthill-McKee (which interleaves the so3 and r3 control points by knot), is banded with about
    ``6 * 4`` coordinates of bandwidth and gets a banded Cholesky factorisation; the border is
    eliminated by a small dense Schur complement. When the structure is not banded or ``A_tt`` is
    not numerically positive definite, a sparse LU (SuperLU, COLAMD) is used instead.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
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
        X: (Nt, Nc) ``A_tt^-1 H_tc``.
        y_t: (Nt,) ``-A_tt^-1 g_t``.
    """

    S: F64
    b: F64
    X: F64
    y_t: F64

    def back_substitute(self, dc: F64) -> F64:
        """(Nt,) trajectory step for the (Nc,) calibration step ``dc``."""
        return self.y_t - self.X @ dc


def schur_complement(lin: Linearization, trajectory_damping: F64 | float = 0.0) -> SchurSystem:
    """Eliminate the trajectory block.

    ``A_tt`` is factorised by :class:`_BandedCholesky` (banded Cholesky plus a dense border) when
    its structure allows and it is numerically positive definite, and by a sparse LU otherwise.
    Trajectory coordinates that no residual touches (zero diagonal) get a unit diagonal so the
    factorisation exists; their step is zero.

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
        return SchurSystem(lin.H_cc.copy(), -lin.g_c.copy(), np.zeros((0, nc)), np.zeros(0))
    add = _trajectory_diagonal(lin.H_tt, trajectory_damping)
    rhs = np.empty((nt, nc + 1))
    rhs[:, :nc] = lin.H_tc
    rhs[:, nc] = -lin.g_t
    factor = _BandedCholesky.factorize(lin.H_tt, add)
    sol = factor.solve(rhs) if factor is not None else _sparse_lu_solve(lin.H_tt, add, rhs)
    x, y_t = sol[:, :nc], sol[:, nc]
    s = lin.H_cc - lin.H_tc.T @ x
    s = 0.5 * (s + s.T)
    b = -lin.g_c - lin.H_tc.T @ y_t
    return SchurSystem(s, b, x, y_t)


def _trajectory_diagonal(h_tt: sp.spmatrix, trajectory_damping: F64 | float) -> F64:
    """(Nt,) values added to the diagonal of ``H_tt``: the damping, plus 1 where it is zero."""
    nt = h_tt.shape[0]
    add = np.broadcast_to(np.asarray(trajectory_damping, dtype=np.float64), (nt,)).copy()
    add[h_tt.diagonal() <= 0.0] += 1.0
    return add


def _sparse_lu_solve(h_tt: sp.spmatrix, add: F64, rhs: F64) -> F64:
    """``(H_tt + diag(add))^-1 rhs`` by SuperLU (COLAMD ordering).

    Args:
        h_tt: (Nt, Nt) sparse trajectory block.
        add: (Nt,) diagonal addition.
        rhs: (Nt, k) right-hand sides.

    Returns:
        (Nt, k) solution.

    Raises:
        numpy.linalg.LinAlgError: When the matrix is exactly singular.
    """
    a_tt = (h_tt + sp.diags(add, format="csc")).tocsc()
    try:
        lu = spla.splu(a_tt, permc_spec="COLAMD")
    except RuntimeError as err:
        msg = "The trajectory block of the normal equations is singular; add damping or priors."
        raise np.linalg.LinAlgError(msg) from err
    return lu.solve(rhs)


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
    by LAPACK ``pbtrf`` and applied by ``pbtrs``; the border is eliminated with the dense Schur
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
@dataclass
class _Piece:
    """Dense Jacobian columns of one or more blocks sharing an element pattern."""

    elements: npt.NDArray[np.intp]
    cols: IntArray  # (n, p) reduced columns, -1 where fixed
    A: F64  # (n, m, p) reweighted values
    traj: npt.NDArray[np.bool_]  # (p,) whether each column belongs to the trajectory group
    key: IntArray | None = None  # (n,) group index, None when a single group
    num_groups: int = 1


class _GroupPlan:
    """Grouping of measurements by a key: padding into equal chunks and summation per group.

    Each group's measurements are split into chunks of at most ``chunk`` measurements (zero-padded)
    so that every ``A^T B`` is one small BLAS product; the chunk products are summed per group
    with a sparse indicator matrix. Chunks are kept small enough (``chunk * m * p * q`` below
    OpenBLAS's threading threshold) that no product starts BLAS threads, which on a loaded
    two-core machine cost far more than they save.
    """

    def __init__(self, key: IntArray | None, num_groups: int, n: int, m: int, width: int) -> None:
        if key is None:
            order = np.arange(n, dtype=np.intp)
            counts = np.array([n], dtype=np.intp)
            num_groups = 1
        else:
            order = np.argsort(key, kind="stable")
            counts = np.bincount(key, minlength=num_groups)
        starts = np.zeros(num_groups, dtype=np.intp)
        np.cumsum(counts[:-1], out=starts[1:])
        self.rep = order[starts]
        limit = max(1, _BLAS_PRODUCT_LIMIT // (m * width * width))
        # About half the mean group size: bounded padding, few products per group.
        self.chunk = int(min(max(n // (2 * num_groups), 1), limit))
        if key is None:
            self.chunk = int(min(max(n, 1), limit))
        self.contiguous = key is None
        chunks_per_group = -(-counts // self.chunk)
        chunk_start = np.zeros(num_groups, dtype=np.intp)
        np.cumsum(chunks_per_group[:-1], out=chunk_start[1:])
        self.num_chunks = int(chunks_per_group.sum())
        rank = np.arange(n, dtype=np.intp) - np.repeat(starts, counts)
        self.pos = np.empty(n, dtype=np.intp)
        self.pos[order] = np.repeat(chunk_start * self.chunk, counts) + rank
        group_of_chunk = np.repeat(np.arange(num_groups), chunks_per_group)
        self.summer = sp.csr_matrix(
            (np.ones(self.num_chunks), (group_of_chunk, np.arange(self.num_chunks))),
            shape=(num_groups, self.num_chunks),
        )

    def pad(self, A: F64) -> F64:
        """(n, m, p) -> (num_chunks, chunk * m, p), zero rows padding each group."""
        n, m, p = A.shape
        out = np.zeros((self.num_chunks * self.chunk, m, p))
        if self.contiguous:
            out[:n] = A
        else:
            out[self.pos] = A
        return out.reshape(self.num_chunks, self.chunk * m, p)

    def gram(self, a_pad: F64, b_pad: F64) -> F64:
        """Per-group ``sum A^T B`` -> (G, p, q)."""
        prods = np.matmul(a_pad.transpose(0, 2, 1), b_pad)
        k, p, q = prods.shape
        return np.asarray(self.summer @ prods.reshape(k, p * q)).reshape(-1, p, q)


class _Accumulator:
    """Collects ``H`` contributions: sparse triplets for ``H_tt``, dense ``H_tc`` and ``H_cc``."""

    def __init__(self, nt: int, nc: int) -> None:
        self.nt, self.nc = nt, nc
        self.rows: list[IntArray] = []
        self.cols: list[IntArray] = []
        self.vals: list[F64] = []
        self.h_tc = np.zeros(nt * nc)
        self.h_cc = np.zeros(nc * nc)

    def add_tt(self, rows: IntArray, cols: IntArray, vals: F64, sym: bool) -> None:
        """Add ``H[rows, cols] += vals`` (and the transpose when ``sym``) for trajectory indices."""
        self.rows.append(rows)
        self.cols.append(cols)
        self.vals.append(vals)
        if sym:
            self.rows.append(cols)
            self.cols.append(rows)
            self.vals.append(vals)

    def add_tc(self, rows: IntArray, cols: IntArray, vals: F64) -> None:
        """``H_tc[rows, cols - nt] += vals`` (rows trajectory, cols calibration; no -1)."""
        flat = rows * self.nc + (cols - self.nt)
        self.h_tc += np.bincount(flat.reshape(-1), vals.reshape(-1), self.h_tc.size)

    def add_cc(self, rows: IntArray, cols: IntArray, vals: F64, sym: bool) -> None:
        """``H_cc[rows - nt, cols - nt] += vals`` (and the transpose when ``sym``; no -1)."""
        r, c = rows - self.nt, cols - self.nt
        self.h_cc += np.bincount((r * self.nc + c).reshape(-1), vals.reshape(-1), self.h_cc.size)
        if sym:
            flat = (c * self.nc + r).reshape(-1)
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
                shape = sub.shape
                self.add_tt(
                    np.broadcast_to(r, shape).reshape(-1),
                    np.broadcast_to(c, shape).reshape(-1),
                    sub.reshape(-1),
                    sym,
                )
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
        self.add_tt(r[rt & ct], c[rt & ct], v[rt & ct], False)
        tc, cc = rt & ~ct, ~rt & ~ct
        self.add_tc(r[tc], c[tc], v[tc])
        self.add_cc(r[cc], c[cc], v[cc], False)

    def result(self) -> tuple[sp.csc_matrix, F64, F64]:
        """``(H_tt, H_tc, H_cc)``."""
        nt, nc = self.nt, self.nc
        if self.rows:
            r, c, v = (np.concatenate(x) for x in (self.rows, self.cols, self.vals))
        else:
            r = c = np.zeros(0, dtype=np.intp)
            v = np.zeros(0)
        h_tt = sp.csc_matrix((v, (r, c)), shape=(nt, nt))
        h_tt.sum_duplicates()
        h_cc = self.h_cc.reshape(nc, nc)
        return h_tt, self.h_tc.reshape(nt, nc), 0.5 * (h_cc + h_cc.T)


def _compress(raw: IntArray) -> tuple[IntArray | None, int]:
    """Dense ranks 0..G-1 of integer keys (None when all equal)."""
    uniq, inv = np.unique(raw, return_inverse=True)
    if uniq.size == 1:
        return None, 1
    return inv.reshape(-1).astype(np.intp, copy=False), int(uniq.size)


def _element_key(elements: npt.NDArray[np.intp]) -> tuple[IntArray | None, int]:
    n, a = elements.shape
    if n == 0:
        return None, 1
    lo, hi = elements.min(axis=0), elements.max(axis=0)
    if np.all(lo == hi):
        return None, 1
    if a == 1:
        return _compress(elements[:, 0])
    span = (hi - lo + 1).astype(np.float64)
    if float(np.prod(span)) < 2.0**62:
        radix = np.concatenate([[1], np.cumprod((hi - lo + 1)[:-1])]).astype(np.int64)
        return _compress((elements - lo).astype(np.int64) @ radix)
    _, inv = np.unique(elements, axis=0, return_inverse=True)
    inv = inv.reshape(-1).astype(np.intp)
    return inv, int(inv.max()) + 1


def _pair_key(p: _Piece, q: _Piece) -> tuple[IntArray | None, int]:
    if p.key is None:
        return q.key, q.num_groups
    if q.key is None:
        return p.key, p.num_groups
    return _compress(p.key.astype(np.int64) * q.num_groups + q.key)


class Problem:
    """Parameter blocks plus residual blocks (each with an optional robust loss)."""

    def __init__(self) -> None:
        """Create an empty problem."""
        self._blocks: dict[str, ParameterBlock] = {}
        self._residuals: list[ResidualBlock] = []
        self._losses: list[Loss | None] = []

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
        acc = _Accumulator(layout.num_trajectory, layout.num_calibration)
        for ev, loss in zip(evaluation.evals, evaluation.losses, strict=True):
            r = ev.residuals
            if r.shape[0] == 0:
                continue
            sqrt_w: F64 | None = None
            if loss is not None:
                sqrt_w = np.sqrt(loss(np.einsum("ij,ij->i", r, r))[1])
                r = r * sqrt_w[:, None]
            if any(isinstance(j, SparseJacobian) for j in ev.jacobians):
                self._linearize_sparse(ev, r, sqrt_w, layout, g, acc)
            else:
                self._linearize_dense(ev, r, sqrt_w, layout, g, acc)
        h_tt, h_tc, h_cc = acc.result()
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
        r: F64,
        sqrt_w: F64 | None,
        layout: Layout,
        g: F64,
        acc: _Accumulator,
    ) -> None:
        n, m = r.shape
        pieces: list[_Piece] = []
        for jac in ev.jacobians:
            assert isinstance(jac, DenseJacobian)
            idx = self._block_index(jac, layout)
            if idx is None:
                continue
            block = self._blocks[jac.block]
            a, d = jac.values.shape[2:]
            cols = idx.reshape(block.num_elements, d)[jac.elements].reshape(n, a * d)
            values = jac.values.reshape(n, m, a * d)
            if sqrt_w is not None:
                values = values * sqrt_w[:, None, None]
            traj = np.full(a * d, block.group == "trajectory")
            for piece in pieces:
                if piece.elements.shape == jac.elements.shape and np.array_equal(
                    piece.elements, jac.elements
                ):
                    piece.cols = np.concatenate([piece.cols, cols], axis=1)
                    piece.A = np.concatenate([piece.A, values], axis=2)
                    piece.traj = np.concatenate([piece.traj, traj])
                    break
            else:
                pieces.append(_Piece(jac.elements, cols, values, traj))
        if not pieces:
            return
        for piece in pieces:
            piece.key, piece.num_groups = _element_key(piece.elements)
        # Pieces with a single group (constant elements, e.g. extrinsics) share one super-piece.
        singles = [p for p in pieces if p.key is None]
        merged = [p for p in pieces if p.key is not None]
        if singles:
            merged.append(
                _Piece(
                    singles[0].elements,
                    np.concatenate([p.cols for p in singles], axis=1),
                    np.concatenate([p.A for p in singles], axis=2),
                    np.concatenate([p.traj for p in singles]),
                )
            )
        for piece in merged:
            grad = np.einsum("nm,nmp->np", r, piece.A)
            valid = piece.cols >= 0
            if np.all(valid):
                g += np.bincount(piece.cols.reshape(-1), grad.reshape(-1), g.size)
            else:
                g += np.bincount(piece.cols[valid], grad[valid], g.size)
        width = max(piece.A.shape[2] for piece in merged)
        plans: dict[tuple[int, int], _GroupPlan] = {}
        padded: dict[tuple[int, int, int], F64] = {}
        for i, p in enumerate(merged):
            for j in range(i, len(merged)):
                q = merged[j]
                key, num_groups = (p.key, p.num_groups) if i == j else _pair_key(p, q)
                plan_id = (id(key), num_groups)
                if plan_id not in plans:
                    plans[plan_id] = _GroupPlan(key, num_groups, n, m, width)
                plan = plans[plan_id]
                for k in (i, j):
                    if (*plan_id, k) not in padded:
                        padded[(*plan_id, k)] = plan.pad(merged[k].A)
                blocks = plan.gram(padded[(*plan_id, i)], padded[(*plan_id, j)])
                acc.add_block(p.cols[plan.rep], q.cols[plan.rep], blocks, p.traj, q.traj, i == j)

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
