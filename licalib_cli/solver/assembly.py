"""Assembly of the normal equations ``H = J^T J``, ``g = J^T r`` from Jacobian pieces.

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
one LM iteration to the next). Residual blocks with a sparse Jacobian piece go through
``scipy.sparse`` instead.

:class:`~licalib_cli.solver.problem.Problem` resolves each Jacobian piece to reduced columns
(:class:`DensePart`, or COO triplets) and calls :func:`add_dense_split` (:func:`add_dense` on
two halves of a large block, on the block threads) / :func:`add_sparse` per residual block; an
:class:`Accumulator` collects the result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from licalib_cli.parallel.threads import map_blocks

if TYPE_CHECKING:
    from licalib_cli.solver.problem import Layout

__all__ = [
    "MAP_ENTRIES",
    "SPLIT_PARTS",
    "SPLIT_ROWS",
    "Accumulator",
    "DensePart",
    "GroupCache",
    "TrajectoryPattern",
    "add_dense",
    "add_dense_gradient",
    "add_dense_split",
    "add_sparse",
    "add_sparse_gradient",
    "first_with_same_elements",
    "same_elements",
]

F64 = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

# Upper bound of m * n * k of one BLAS product in the grouped Gram assembly; OpenBLAS starts
# threads above 4 * 65536.
_BLAS_PRODUCT_LIMIT = 200_000


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


def same_elements(a: npt.NDArray[np.intp], b: npt.NDArray[np.intp]) -> bool:
    """Whether two Jacobian pieces touch the same elements for every measurement (the same
    array, or equal ones)."""
    return a is b or (a.shape == b.shape and np.array_equal(a, b))


def first_with_same_elements(parts: list[DensePart]) -> list[int]:
    """For each part, the index of the first part touching the same elements (its own index when
    no part before it does): the parts that can share their groupings."""
    firsts: list[int] = []
    for i, part in enumerate(parts):
        earlier = (
            j for j in dict.fromkeys(firsts) if same_elements(parts[j].elements, part.elements)
        )
        firsts.append(next(earlier, i))
    return firsts


class GroupCache:
    """Groupings and Gram plans of the dense residual blocks, kept from one assembly to the next.

    They depend only on the elements each measurement touches, which stay the same from one
    iteration of a solve to the next (unless a step of the time offset moves a query into
    another spline segment): the cache compares the elements and reuses what was computed for
    equal ones. Only what the previous assembly used is kept.
    """

    def __init__(self) -> None:
        self._keys: list[tuple[npt.NDArray[np.intp], _GroupKey]] = []
        self._plans: list[tuple[_GroupKey, tuple[int, int, int, int], _GroupPlan]] = []
        self._used_keys: list[tuple[npt.NDArray[np.intp], _GroupKey]] = []
        self._used_plans: list[tuple[_GroupKey, tuple[int, int, int, int], _GroupPlan]] = []

    def key(self, elements: npt.NDArray[np.intp]) -> _GroupKey:
        """:func:`_element_key` of ``elements``."""
        entry = next(
            (e for e in (*self._used_keys, *self._keys) if same_elements(e[0], elements)),
            None,
        )
        if entry is None:
            entry = (elements.copy(), _element_key(elements))
        self._used_keys.append(entry)
        return entry[1]

    def plan(self, key: _GroupKey, n: int, m: int, left: int, right: int) -> _GroupPlan:
        """``_GroupPlan(key, n, m, left, right)`` for a key returned by :meth:`key`."""
        shape = (n, m, left, right)
        entry = next(
            (e for e in (*self._used_plans, *self._plans) if e[0] is key and e[1] == shape),
            None,
        )
        if entry is None:
            entry = (key, shape, _GroupPlan(key, n, m, left, right))
        self._used_plans.append(entry)
        return entry[2]

    def done(self) -> None:
        """End of an assembly: keep what it used, drop the rest."""
        self._keys, self._used_keys = self._used_keys, []
        self._plans, self._used_plans = self._used_plans, []


@dataclass
class DensePart:
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
    parts: list[DensePart]

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
    if sqrt_w is None:
        return np.concatenate(cols, axis=2) if len(cols) > 1 else np.ascontiguousarray(cols[0])
    out = np.concatenate(cols, axis=2)
    _scale_rows(out, sqrt_w)
    return out


def _scale_rows(values: F64, w: F64) -> None:
    """``values[i] *= w[i]`` in place for C-contiguous (rows, ...) ``values``.

    One product over rows of ``m * W`` contiguous values: far fewer inner loops than scaling
    each narrow part (a few columns wide) before stacking, and the same products.
    """
    flat = values.reshape(values.shape[0], -1)
    flat *= w[:, None]


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
        dest: (n,) buffer row of each measurement.
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
        # buffer row of each measurement
        self.dest = dest if order is None else np.empty(n, dtype=np.intp)
        if order is not None:
            self.dest[order] = dest
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

    def pad_stacked(self, blocks: list[F64], sqrt_w: F64 | None) -> F64:
        """``pad(_stack(blocks, sqrt_w))``, the values written into the buffer directly.

        With weights each value is copied once (not stacked and scaled first, then gathered
        into the buffer), and the buffer holds the same numbers. Unweighted values are stacked
        and gathered: copying the narrow parts row by row into the buffer was measured slower
        than the two contiguous copies.
        """
        if self.identity or sqrt_w is None:
            return self.pad(_stack(blocks, sqrt_w))
        cols = [b[:, :, None] if b.ndim == 2 else b for b in blocks]
        m = cols[0].shape[1]
        width = sum(c.shape[2] for c in cols)
        rows = self.source.shape[0]
        out = np.empty((rows, m, width))
        out[self.padding] = 0.0
        start = 0
        for c in cols:
            out[self.dest, :, start : start + c.shape[2]] = c
            start += c.shape[2]
        w = np.zeros(rows)
        w[self.dest] = sqrt_w
        _scale_rows(out, w)
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
class TrajectoryPattern:
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


class Accumulator:
    """Collects ``H`` contributions: ``H_tt`` as index/value blocks, dense ``H_tc`` and ``H_cc``.

    ``H_tt`` contributions are kept as broadcastable ``(rows, cols, values)`` blocks; the CSC
    matrix is formed once at the end, reusing the sparsity pattern of the previous assembly
    (``pattern``) when the contributions have the same indices.
    """

    def __init__(self, nt: int, nc: int, pattern: TrajectoryPattern | None = None) -> None:
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
            uniq, slots = _unique_entries(flat, nt)
            col_u = (uniq // nt).astype(np.intp)
            indptr = np.zeros(nt + 1, dtype=np.intp)
            np.cumsum(np.bincount(col_u, minlength=nt), out=indptr[1:])
            pattern = TrajectoryPattern(
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


MAP_ENTRIES = 2**28
"""Matrices of at most this many entries (``H_tt`` of up to 16 384 coordinates, about a 50 s
bag) find their pattern through an index map over every entry (:func:`_unique_entries`)."""


def _unique_entries(flat: npt.NDArray[np.int64], n: int) -> tuple[npt.NDArray[np.int64], IntArray]:
    """``np.unique(flat, return_inverse=True)`` for entries ``col * n + row`` of an (n, n) matrix.

    Up to :data:`MAP_ENTRIES` entries of the matrix, an index map over all of them finds one
    occurrence of each entry (the map is allocated but only its pages that entries fall in are
    touched: a band and the border's rows), and only those are sorted; the pattern of ``H_tt``
    has about a million contributions and a quarter million entries on a 15 s bag (0.02-0.07 s
    against 0.04-0.13 s for the radix sorts of the contributions). Beyond, with ``n`` below
    2**16, two stable radix sorts of 16-bit keys (row, then column), linear in the number of
    contributions; beyond that, a comparison sort.
    """
    if flat.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.intp)
    if n * n <= MAP_ENTRIES and flat.size < np.iinfo(np.int32).max:
        index = np.arange(flat.size, dtype=np.int32)
        at = np.empty(n * n, dtype=np.int32)
        at[flat] = index  # of repeated entries one write is kept, whichever
        uniq = np.sort(flat[at[flat] == index])
        at[uniq] = np.arange(uniq.size, dtype=np.int32)  # the map now gives each entry's rank
        return uniq, at[flat].astype(np.intp)
    if n > np.iinfo(np.uint16).max:
        uniq, inverse = np.unique(flat, return_inverse=True)
        return uniq, inverse.reshape(-1)
    col, row = np.divmod(flat, n)
    order = np.argsort(row.astype(np.uint16), kind="stable")
    order = order[np.argsort(col.astype(np.uint16)[order], kind="stable")]
    ordered = flat[order]
    starts = np.empty(ordered.size, dtype=bool)
    starts[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=starts[1:])
    inverse = np.empty(ordered.size, dtype=np.intp)
    inverse[order] = np.cumsum(starts) - 1
    return ordered[starts], inverse


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
    acc: Accumulator,
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


def add_dense(
    parts: list[DensePart],
    r: F64,
    sqrt_w: F64 | None,
    layout: Layout,
    g: F64,
    acc: Accumulator,
    cache: GroupCache | None = None,
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

    Args:
        parts: the Jacobian pieces on free coordinates.
        r: (n, m) whitened residuals.
        sqrt_w: (n,) IRLS weights, or None.
        layout: the coordinate layout.
        g: (Nt + Nc,) gradient, added to.
        acc: receives the ``H`` contributions.
        cache: groupings and plans of earlier assemblies to reuse (see :class:`GroupCache`).
    """
    n, m = r.shape
    element_key = _element_key if cache is None else cache.key
    group_plan = _GroupPlan if cache is None else cache.plan
    sharing: dict[int, list[DensePart]] = {}
    for part, first in zip(parts, first_with_same_elements(parts), strict=True):
        sharing.setdefault(first, []).append(part)
    patterns = [(parts[first].elements, members) for first, members in sharing.items()]
    if not patterns:
        return
    keyed: list[_PartGroup] = []
    constant: list[DensePart] = []
    for elements, members in patterns:
        key = element_key(elements)
        if key.key is None:
            constant.extend(members)
            continue
        for group in keyed:
            if group.key.same_partition(key):
                group.parts.extend(members)
                break
        else:
            keyed.append(_PartGroup(key, members))
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
        plan = group_plan(const.key, n, m, pc, pc + 1)
        buf = plan.pad_stacked([*const.values, r], sqrt_w)
        add_constant(plan.gram(buf, slice(0, pc), slice(None)).sum(axis=0))
        return
    # the couplings of two keyed groups need the stacked values in measurement order
    keep_stacks = len(keyed) > 1
    stacks: list[F64] = []
    reps: list[IntArray] = []
    for i, group in enumerate(keyed):
        pk = group.width
        left = pk + pc if i == 0 else pk
        values = [*group.values, *const.values, r]
        width = pk + pc + 1
        num_groups = group.key.num_groups
        if pk <= _ONE_HOT_MAX_WIDTH and num_groups * left * width <= _ONE_HOT_MAX_OUTPUT:
            stacked = _stack(values, sqrt_w)  # (n, m, pk + pc + 1)
            blocks = _one_hot_gram(group.key, stacked, left)
            rep = _first_of_each_group(group.key)
        else:
            plan = group_plan(group.key, n, m, left, width)
            if keep_stacks:
                stacked = _stack(values, sqrt_w)
                buf = plan.pad(stacked)
            else:
                buf = plan.pad_stacked(values, sqrt_w)
            blocks = plan.gram(buf, slice(0, left), slice(None))
            rep = plan.rep
        if keep_stacks:
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
                _add_encoded_pair(keyed[a], stacks[a], keyed[b], stacks[b], reps[b], layout, acc)
                continue
            plan = _GroupPlan(_joint_key(p.key, q.key), n, m, p.width, q.width)
            stacked = np.concatenate([stacks[i][:, :, : p.width], stacks[j][:, :, : q.width]], 2)
            blocks = plan.gram(plan.pad(stacked), slice(0, p.width), slice(p.width, None))
            acc.add_block(p.cols_at(plan.rep), q.cols_at(plan.rep), blocks, p.traj, q.traj, False)


SPLIT_ROWS = 40_000
"""A dense residual block with at least this many measurements is assembled in
:data:`SPLIT_PARTS` parts on the block threads (:func:`add_dense_split`). Most of its assembly
moves values into the padded buffers of the Gram products; a block of 450 000 points took 0.43 s
on one core, 0.22 s in two parts on two."""

SPLIT_PARTS = 2
"""Parts of a large dense block, whatever the number of threads (the sums are then the same)."""


def add_dense_split(
    parts: list[DensePart],
    r: F64,
    sqrt_w: F64 | None,
    layout: Layout,
    g: F64,
    acc: Accumulator,
    cache: GroupCache | None = None,
) -> None:
    """:func:`add_dense` of :data:`SPLIT_PARTS` consecutive parts of the measurements, shared by
    the block threads, each into its own accumulator, then summed into ``acc`` and ``g``.

    ``H`` and ``g`` are sums over the measurements, so the parts' sums add up to the whole. The
    parts are the same whatever the number of threads and their timing, and so is the result,
    bit for bit. Below :data:`SPLIT_ROWS` measurements it is :func:`add_dense`.
    """
    n = r.shape[0]
    pieces = SPLIT_PARTS
    if n < SPLIT_ROWS or pieces < 2:
        add_dense(parts, r, sqrt_w, layout, g, acc, cache)
        return
    bounds = np.linspace(0, n, pieces + 1).astype(np.intp)
    accs = [Accumulator(acc.nt, acc.nc) for _ in range(pieces)]
    grads = [np.zeros_like(g) for _ in range(pieces)]

    def part(k: int) -> None:
        rows = slice(int(bounds[k]), int(bounds[k + 1]))
        views: dict[int, npt.NDArray[np.intp]] = {}  # parts sharing elements keep sharing them
        sliced = []
        for p in parts:
            elements = views.setdefault(id(p.elements), p.elements[rows])
            sliced.append(DensePart(elements, p.table, p.values[rows], p.traj))
        w = None if sqrt_w is None else sqrt_w[rows]
        add_dense(sliced, r[rows], w, layout, grads[k], accs[k], cache)

    map_blocks(part, pieces)
    for a, gk in zip(accs, grads, strict=True):
        acc.tt.extend(a.tt)
        acc.h_tc += a.h_tc
        acc.h_cc += a.h_cc
        g += gk


def add_dense_gradient(parts: list[DensePart], r_w: F64, g: F64) -> None:
    """Add ``J^T r_w`` of a residual block whose Jacobians are all dense: the gradient alone,
    as :func:`add_dense` adds it with the curvature.

    Args:
        parts: the Jacobian pieces on free coordinates.
        r_w: (n, m) whitened residuals times the IRLS weights (not their square roots).
        g: (Nt + Nc,) gradient, added to.
    """
    n = r_w.shape[0]

    def part_gradient(i: int) -> F64:
        # each piece on a block thread (the spline's rotation and position pieces are most of
        # it), added in order: the same sums whatever the threads
        part = parts[i]
        out = np.zeros_like(g)
        values = np.einsum("nmw,nm->nw", part.values, r_w)
        _add_gradient(out, part.table[part.elements].reshape(n, -1), values)
        return out

    for piece in map_blocks(part_gradient, len(parts)):
        g += piece


def add_sparse_gradient(pieces: list[tuple[IntArray, IntArray, F64]], r_w: F64, g: F64) -> None:
    """Add ``J^T r_w`` of a residual block with sparse Jacobian pieces (arguments as
    :func:`add_dense_gradient`'s; ``pieces`` as :func:`add_sparse`'s)."""
    flat = r_w.reshape(-1)
    for rows, cols, values in pieces:
        _add_gradient(g, cols, values * flat[rows])


def add_sparse(
    pieces: list[tuple[IntArray, IntArray, F64]],
    r: F64,
    sqrt_w: F64 | None,
    g: F64,
    acc: Accumulator,
) -> None:
    """Add the contribution of a residual block with sparse Jacobian pieces (via scipy.sparse).

    Args:
        pieces: COO ``(rows, reduced columns (-1 fixed), values)`` of each Jacobian piece.
        r: (n, m) whitened residuals, already reweighted by ``sqrt_w``.
        sqrt_w: (n,) IRLS weights, or None.
        g: (Nt + Nc,) gradient, added to.
        acc: receives the ``H`` contributions.
    """
    n, m = r.shape
    rows_l, cols_l, vals_l = [], [], []
    for rows, gcols, values in pieces:
        keep = gcols >= 0
        vals = values[keep]
        rows = rows[keep]
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
