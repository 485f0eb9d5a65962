"""Uniform cubic B-spline on SO(3) in cumulative form (paper eq. q_curve_cumu, spline_omega).

Conventions:

* ``R(t) = R_G_I(t)`` maps IMU-frame vectors into the global frame ``{G}``. Control points are
  unit quaternions ``[x, y, z, w]`` (stored also as matrices ``R_k``).
* With active control points ``R_i .. R_{i+3}`` and cumulative blending functions ``lambda_j(u)``
  (:func:`~licalib_cli.spline.knots.cumulative_blending`)::

      d_j  = Log(R_{i+j-1}^T R_{i+j})            j = 1, 2, 3
      A_j  = Exp(lambda_j(u) d_j)
      R(t) = R_i A_1 A_2 A_3

* Angular velocity and acceleration are in the body (IMU) frame: ``w = vee(R^T R_dot)`` in rad/s,
  ``alpha = w_dot`` in rad/s^2. They follow the recursions of Sommer et al. 2020 ("Efficient
  Derivative Computation for Cumulative B-Splines on Lie Groups", as in basalt)::

      w^(j)     = A_j^T w^(j-1) + lambda_j' d_j
      alpha^(j) = A_j^T alpha^(j-1) + lambda_j'' d_j + lambda_j' w^(j) x d_j

  with time derivatives ``lambda' = (d lambda / du) / dt``.
* Jacobians use right perturbations: of a control point ``R_k <- R_k Exp(delta_k)`` and of the
  output rotation ``R(t) <- R(t) Exp(eps)``. The Jacobians with respect to the query time are
  ``d eps / dt = w`` and ``d w / dt = alpha``.
* Limit: there is no query-time derivative of the angular acceleration (``d alpha / dt``, the
  angular jerk) and no evaluation of it. Nothing in licalib needs it (no residual uses
  ``alpha`` together with the time offset); a residual built on ``alpha`` whose query time
  depends on an estimated parameter would have to add it first.
* Times are float seconds relative to the problem's reference time.

Evaluation is vectorised over queries; internally arrays are stored component-major (``(3, 3, M)``,
C-contiguous: gathers use ``np.take`` because fancy indexing would return transposed layouts) and
processed in blocks of ``threads.BLOCK`` (8192) queries: temporaries of a few hundred kB stay in
cache, and numpy's per-call overhead is spread over enough queries (smaller blocks were measured
slower). The only Python loops are over the 3 segments of a cubic spline and over those blocks. The
blocks are independent (each writes its own slices of preallocated outputs, and the VJP terms are
collected in block order), so with two or more blocks they are shared between the threads of
:mod:`licalib_cli.parallel.threads` (numpy releases the GIL in its loops); every block computes what
the serial loop computes, so the results are bit-for-bit the same. ``LICALIB_THREADS=1`` runs the
serial loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from licalib_cli.geometry import so3
from licalib_cli.geometry.so3 import (
    _jr_inv_coefficient,
    _one_minus_cos_over_theta2,
    _sin_over_theta,
    _theta_minus_sin_over_theta3,
)
from licalib_cli.parallel.threads import map_blocks, map_slices
from licalib_cli.spline.knots import UniformKnots, cumulative_blending

__all__ = ["SO3EvaluationCache", "SO3RotationVJP", "SO3Spline", "SO3SplineEval"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_OFFSETS = np.arange(4, dtype=np.int64)


# --------------------------------------------------------------------------------------------
# Component-major (structure of arrays) 3x3 algebra: matrices (3, 3, m), vectors (3, m).
# --------------------------------------------------------------------------------------------


# The 3x3 products go through einsum: its sum-of-products loop runs along the contiguous query
# axis without temporaries, several times faster than broadcasting (3, 3, m) products.


def _mm(a: FloatArray, b: FloatArray) -> FloatArray:
    """a @ b."""
    return np.einsum("ikm,kjm->ijm", a, b)


def _mtm(a: FloatArray, b: FloatArray) -> FloatArray:
    """a^T @ b."""
    return np.einsum("kim,kjm->ijm", a, b)


def _mtv(a: FloatArray, v: FloatArray) -> FloatArray:
    """a^T @ v."""
    out = a[0] * v[0]
    out += a[1] * v[1]
    out += a[2] * v[2]
    return out


def _mv(a: FloatArray, v: FloatArray) -> FloatArray:
    """a @ v."""
    out = a[:, 0] * v[0]
    out += a[:, 1] * v[1]
    out += a[:, 2] * v[2]
    return out


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """a x b for (3, m) vectors."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.multiply(a[1], b[2], out=out[0])
    out[0] -= a[2] * b[1]
    np.multiply(a[2], b[0], out=out[1])
    out[1] -= a[0] * b[2]
    np.multiply(a[0], b[1], out=out[2])
    out[2] -= a[1] * b[0]
    return out


def _hat_mm(v: FloatArray, b: FloatArray) -> FloatArray:
    """hat(v) @ b for (3, m) v and (3, 3, m) b (column-wise cross products)."""
    out = np.empty_like(b)
    np.multiply(v[1], b[2], out=out[0])
    out[0] -= v[2] * b[1]
    np.multiply(v[2], b[0], out=out[1])
    out[1] -= v[0] * b[2]
    np.multiply(v[0], b[1], out=out[2])
    out[2] -= v[1] * b[0]
    return out


def _add_diag(m: FloatArray, s: FloatArray | float) -> FloatArray:
    """m += s * I (in place)."""
    m[0, 0] += s
    m[1, 1] += s
    m[2, 2] += s
    return m


def _add_hat(m: FloatArray, v: FloatArray, s: FloatArray | float) -> FloatArray:
    """m += s * hat(v) (in place)."""
    x, y, z = s * v[0], s * v[1], s * v[2]
    m[0, 1] -= z
    m[0, 2] += y
    m[1, 0] += z
    m[1, 2] -= x
    m[2, 0] -= y
    m[2, 1] += x
    return m


def _fn_of_hat(
    d: FloatArray,
    outer: FloatArray,
    theta2: FloatArray,
    f0: FloatArray | float,
    f1: FloatArray | float,
    f2: FloatArray | float,
) -> FloatArray:
    """``f0 I + f1 hat(d) + f2 hat(d)^2`` using ``hat(d)^2 = d d^T - |d|^2 I``.

    Args:
        d: (3, m) vectors.
        outer: (3, 3, m) ``d d^T``.
        theta2: (m,) ``|d|^2``.
        f0: scalar or (m,) coefficient of ``I``.
        f1: scalar or (m,) coefficient of ``hat(d)``.
        f2: scalar or (m,) coefficient of ``hat(d)^2``.

    Returns:
        (3, 3, m) matrices.
    """
    out = f2 * outer
    _add_diag(out, f0 - f2 * theta2)
    return _add_hat(out, d, f1)


def _store(out: FloatArray, val: FloatArray) -> None:
    """Write component-major ``val`` (..., m) into query-major ``out`` (m, ...).

    Vectors are written column by column; matrices (more than 3 components) by one transposing
    copy, about twice as fast as their 9 or 12 narrow column writes (measured).
    """
    m = out.shape[0]
    o = out.reshape(m, -1)
    v = val.reshape(-1, m)
    if v.shape[0] > 3:
        o[...] = v.T
        return
    for k in range(v.shape[0]):
        o[:, k] = v[k]


def _soa(m: FloatArray) -> FloatArray:
    """(N, 3, 3) -> contiguous (3, 3, N); (N, 3) -> (3, N)."""
    return np.ascontiguousarray(np.moveaxis(m, 0, -1))


# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _VJPBlock:
    """Terms of :class:`SO3RotationVJP` for one evaluation block (component-major, m queries).

    Attributes:
        rows: The block's queries.
        d: The three (3, m) ``d_j``.
        q0: (3, 3, m) ``A_1 A_2``.
        q1: (3, 3, m) ``A_2``.
        coef: (6, 3, m) ``(a, b, c)`` of ``C_0, F_0^+, F_1^-, F_1^+, F_2^-, F_2^+``.
    """

    rows: slice
    d: tuple[FloatArray, FloatArray, FloatArray]
    q0: FloatArray
    q1: FloatArray
    coef: FloatArray


@dataclass(frozen=True)
class SO3RotationVJP:
    """Row-vector products with the rotation Jacobians, without forming the Jacobians.

    For (M, 3) vectors ``v`` (e.g. the derivative of a scalar residual with respect to the
    rotation perturbation ``eps``), ``vjp(v)[m, k] = v_m^T d eps / d delta_{i+k}`` equals
    ``np.einsum("mi,mkil->mkl", v, jac_rotation)`` at a fraction of the cost: with the
    factorisation ``J_k = Q^T F`` of the evaluation, ``J_k^T v = F^T (Q v)`` where every ``F`` is
    ``a I + b hat(d_j) + c d_j d_j^T``. The terms are kept per evaluation block.

    Attributes:
        size: Number of queries ``M``.
        blocks: The terms of each evaluation block.
    """

    size: int
    blocks: tuple[_VJPBlock, ...]

    def __call__(self, v: npt.ArrayLike) -> FloatArray:
        """(M, 4, 3) products ``v_m^T J_{m,k}`` for (M, 3) row vectors ``v``."""
        vt = np.ascontiguousarray(np.asarray(v, dtype=np.float64).T)
        if vt.shape != (3, self.size):
            msg = f"v must have shape ({self.size}, 3), got {np.shape(v)}"
            raise ValueError(msg)
        out = np.empty((self.size, 4, 3))

        def product(k: int) -> None:
            """Block ``k``'s products into its rows of ``out``."""
            block = self.blocks[k]
            _store(out[block.rows], _vjp_block(block, vt[:, block.rows]))

        map_blocks(product, len(self.blocks))
        return out


def _vjp_block(block: _VJPBlock, v: FloatArray) -> FloatArray:
    """(4, 3, m) products for one block of (3, m) vectors."""
    d, coef = block.d, block.coef
    us = (_mv(block.q0, v), _mv(block.q1, v), v)
    xs = [_cross(d[j], us[j]) for j in range(3)]
    dots = [d[j][0] * us[j][0] + d[j][1] * us[j][1] + d[j][2] * us[j][2] for j in range(3)]

    def ft(slot: int, j: int) -> FloatArray:
        """``F_slot^T u_j = a u - b (d_j x u) + c (d_j . u) d_j``."""
        a, b, c = coef[slot]
        res = a * us[j]
        res -= b * xs[j]
        res += (c * dots[j]) * d[j]
        return res

    out = np.empty((4, 3, v.shape[1]))
    out[0] = ft(0, 0)
    np.subtract(ft(1, 0), ft(2, 1), out=out[1])
    np.subtract(ft(3, 1), ft(4, 2), out=out[2])
    out[3] = ft(5, 2)
    return out


@dataclass(frozen=True)
class SO3SplineEval:
    """Rotation, body rates and Jacobians of an :class:`SO3Spline` at M query times.

    Attributes:
        index: (M,) int64 first active control point ``i``; Jacobian slot ``k`` refers to
            control point ``i + k``.
        rotation: (M, 3, 3) ``R_G_I(t)``.
        angular_velocity: (M, 3) body rate ``w_I(t)``, rad/s, or None when not requested.
        angular_acceleration: (M, 3) ``alpha_I(t) = w_dot``, rad/s^2, or None. Its derivative
            with respect to the query time is not available (see the module docstring).
        jac_rotation: (M, 4, 3, 3) ``d eps / d delta_{i+k}`` (right perturbations), or None.
        jac_angular_velocity: (M, 4, 3, 3) ``d w / d delta_{i+k}``, rad/s, or None.
        jac_angular_acceleration: (M, 4, 3, 3) ``d alpha / d delta_{i+k}``, rad/s^2, or None.
        rotation_vjp: products of row vectors with ``jac_rotation`` (see
            :class:`SO3RotationVJP`), or None when not requested.

    The Jacobian arrays are (M, 4, 3, 3) views of component-major (4, 3, 3, M) storage (the
    layout the evaluation computes in); ``np.ascontiguousarray`` gives a query-major copy.
    """

    index: IntArray
    rotation: FloatArray
    angular_velocity: FloatArray | None
    angular_acceleration: FloatArray | None
    jac_rotation: FloatArray | None
    jac_angular_velocity: FloatArray | None
    jac_angular_acceleration: FloatArray | None
    rotation_vjp: SO3RotationVJP | None = None

    def quaternions(self) -> FloatArray:
        """(M, 4) rotations as unit quaternions ``[x, y, z, w]`` with ``w >= 0``."""
        return so3.matrix_to_quat(self.rotation)


@dataclass(frozen=True)
class SO3Spline:
    """Uniform cubic cumulative B-spline on SO(3).

    Attributes:
        knots: knot vector shared with the position spline.
        control_quats: (N, 4) unit quaternions ``[x, y, z, w]`` of ``R_G_I`` at the control
            points (normalised on construction, canonical ``w >= 0``).
    """

    knots: UniformKnots
    control_quats: FloatArray
    _R: FloatArray = field(init=False, repr=False, compare=False)
    _R_soa: FloatArray = field(init=False, repr=False, compare=False)
    _d_soa: FloatArray = field(init=False, repr=False, compare=False)
    _theta2: FloatArray = field(init=False, repr=False, compare=False)
    _jr_inv_coef: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        q = np.asarray(self.control_quats, dtype=np.float64)
        if q.shape != (self.knots.num_control_points, 4):
            msg = (
                f"control_quats must have shape ({self.knots.num_control_points}, 4), got {q.shape}"
            )
            raise ValueError(msg)
        if not np.all(np.isfinite(q)) or np.any(np.linalg.norm(q, axis=1) < 1e-12):
            msg = "control_quats must be finite and non-zero"
            raise ValueError(msg)
        q = so3.quat_normalize(q)
        q.setflags(write=False)
        rot = so3.quat_to_matrix(q)
        d = so3.log(np.swapaxes(rot[:-1], -1, -2) @ rot[1:])  # (N-1, 3)
        theta = np.linalg.norm(d, axis=1)
        for name, value in (
            ("control_quats", q),
            ("_R", rot),
            ("_R_soa", _soa(rot)),
            ("_d_soa", _soa(d)),
            ("_theta2", theta * theta),
            ("_jr_inv_coef", _jr_inv_coefficient(theta)),
        ):
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, name, value)

    # ---- construction helpers -----------------------------------------------------------

    @classmethod
    def from_matrices(cls, knots: UniformKnots, control_rotations: npt.ArrayLike) -> SO3Spline:
        """Spline from (N, 3, 3) control rotation matrices ``R_G_I``."""
        return cls(knots, so3.matrix_to_quat(control_rotations))

    @classmethod
    def identity(cls, knots: UniformKnots) -> SO3Spline:
        """Spline whose control points are all the identity rotation."""
        q = np.zeros((knots.num_control_points, 4))
        q[:, 3] = 1.0
        return cls(knots, q)

    @property
    def control_rotations(self) -> FloatArray:
        """(N, 3, 3) control points as rotation matrices (read-only)."""
        return self._R

    def retract(self, delta: npt.ArrayLike) -> SO3Spline:
        """New spline with right-perturbed control points ``R_k Exp(delta_k)``.

        Args:
            delta: (N, 3) tangent increments, radians.

        Returns:
            The updated spline (same knots).
        """
        delta = np.asarray(delta, dtype=np.float64)
        dq = so3.quat_exp(delta)
        return SO3Spline(self.knots, so3.quat_multiply(self.control_quats, dq))

    # ---- evaluation ---------------------------------------------------------------------

    def rotation(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M, 3, 3) ``R_G_I(t)``."""
        return self.evaluate(t_s, order=0).rotation

    def quaternion(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M, 4) ``R_G_I(t)`` as unit quaternions ``[x, y, z, w]``, ``w >= 0``."""
        return self.evaluate(t_s, order=0).quaternions()

    def angular_velocity(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M, 3) body angular velocity ``w_I(t)``, rad/s."""
        w = self.evaluate(t_s, order=1).angular_velocity
        assert w is not None
        return w

    def angular_acceleration(self, t_s: npt.ArrayLike) -> FloatArray:
        """(M, 3) body angular acceleration ``alpha_I(t)``, rad/s^2.

        Its derivative with respect to ``t`` (the angular jerk) is not provided.
        """
        a = self.evaluate(t_s, order=2).angular_acceleration
        assert a is not None
        return a

    def evaluate(
        self,
        t_s: npt.ArrayLike,
        order: int = 1,
        jacobians: bool = False,
        *,
        jacobian_order: int | None = None,
        rotation_vjp: bool = False,
    ) -> SO3SplineEval:
        """Evaluate rotation, body rates and optionally their control-point Jacobians.

        Args:
            t_s: (M,) query times, seconds.
            order: 0 rotation only, 1 + angular velocity, 2 + angular acceleration.
            jacobians: also return the (M, 4, 3, 3) Jacobians with respect to right
                perturbations of the 4 active control points.
            jacobian_order: highest derivative whose Jacobians are returned (default
                ``order``); e.g. ``order=1, jacobian_order=0`` gives the angular velocity but
                only the rotation Jacobians, which costs about half of the velocity Jacobians.
            rotation_vjp: also return :class:`SO3RotationVJP`, the products of row vectors with
                the rotation Jacobians (independent of ``jacobians``; much cheaper than forming
                and contracting ``jac_rotation`` when only such products are needed).

        Returns:
            :class:`SO3SplineEval`; fields not requested are None. The Jacobians are
            (M, 4, 3, 3) views of component-major storage.

        Raises:
            ValueError: if a time is outside the spline range, ``order`` is not 0, 1 or 2, or
                ``jacobian_order`` is not in ``[0, order]``.
        """
        if order not in (0, 1, 2):
            msg = f"order must be 0, 1 or 2, got {order}"
            raise ValueError(msg)
        jac_order = order if jacobian_order is None else jacobian_order
        if not 0 <= jac_order <= order:
            msg = f"jacobian_order must lie in [0, order={order}], got {jacobian_order}"
            raise ValueError(msg)
        index, u = self.knots.locate(t_s)
        m = index.shape[0]
        rot = np.empty((m, 3, 3))
        vel = np.empty((m, 3)) if order >= 1 else None
        acc = np.empty((m, 3)) if order >= 2 else None
        # Jacobians are stored component-major (4, 3, 3, M) and returned as (M, 4, 3, 3) views.
        jac_buf = [
            np.empty((4, 3, 3, m)) if jacobians and jac_order >= k else None for k in range(3)
        ]

        def block(sl: slice) -> _VJPBlock | None:
            """Evaluate the queries ``sl`` into their slices of the outputs; their VJP terms if
            asked."""
            jac_out = [None if b is None else b[..., sl] for b in jac_buf]
            vjp_block: list[_VJPBlock] | None = [] if rotation_vjp else None
            res = self._evaluate_block(index[sl], u[sl], order, jac_out, vjp_block, sl)
            for out, val in zip((rot, vel, acc), res, strict=True):
                if out is not None and val is not None:
                    _store(out[sl], val)
            return vjp_block[0] if vjp_block else None

        # blocks write disjoint slices, so they may run on the shared pool in any order; the
        # VJP terms come back in block order
        vjp_blocks = map_slices(block, m)
        j_rot, j_vel, j_acc = (None if b is None else np.moveaxis(b, -1, 0) for b in jac_buf)
        vjp = (
            SO3RotationVJP(m, tuple(b for b in vjp_blocks if b is not None))
            if rotation_vjp
            else None
        )
        return SO3SplineEval(index, rot, vel, acc, j_rot, j_vel, j_acc, vjp)

    def _evaluate_block(
        self,
        index: IntArray,
        u: FloatArray,
        order: int,
        jac_out: Sequence[FloatArray | None],
        vjp_blocks: list[_VJPBlock] | None = None,
        rows: slice | None = None,
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        """Component-major evaluation of one block; see :meth:`evaluate` for the quantities.

        Every matrix that is a function of a single ``d_j`` (``A_j``, ``Jr(lambda_j d_j)``,
        ``Jr_inv(d_j)``, ``Jl_inv(d_j)`` and their products) is written as
        ``f0 I + f1 hat(d_j) + f2 hat(d_j)^2`` with per-query scalar coefficients, which saves
        most of the 3x3 products of the generic chain rule.

        Args:
            index: (m,) first active control points.
            u: (m,) normalised times.
            order: highest derivative (0, 1, 2).
            jac_out: three (4, 3, 3, m) arrays (or None) receiving the Jacobians of rotation,
                angular velocity and angular acceleration.
            vjp_blocks: receives the block's :class:`_VJPBlock` (for ``rows``), or None.
            rows: the block's queries.

        Returns:
            ``(R (3, 3, m), w (3, m) or None, alpha (3, m) or None)``.
        """
        jacobians = any(j is not None for j in jac_out)
        dt = self.knots.dt_s
        m = index.shape[0]
        # (m, 4) views of contiguous (4, m) storage: the columns lam[:, j] are contiguous
        lam = cumulative_blending(u, 0)
        dlam = cumulative_blending(u, 1) / dt if order >= 1 else None
        ddlam = cumulative_blending(u, 2) / (dt * dt) if order >= 2 else None
        d = [np.take(self._d_soa, index + j, axis=-1) for j in range(3)]
        th2 = [self._theta2[index + j] for j in range(3)]
        ecoef = [self._jr_inv_coef[index + j] for j in range(3)]
        outer = [dj[:, None] * dj[None, :] for dj in d]

        a_mats: list[FloatArray] = []
        coef_a: list[FloatArray] = []
        coef_b: list[FloatArray] = []
        angle: list[FloatArray] = []  # |lambda_j d_j|
        for j in range(3):
            lj = lam[:, j + 1]
            x = lj * np.sqrt(th2[j])
            angle.append(x)
            a = _sin_over_theta(x)
            b = _one_minus_cos_over_theta2(x)
            coef_a.append(a)
            coef_b.append(b)
            a_mats.append(_fn_of_hat(d[j], outer[j], th2[j], 1.0, a * lj, b * lj * lj))
        q1 = a_mats[2]  # Q_j = A_{j+1} ... A_2 (0-based), Q_2 = I
        q0 = _mm(a_mats[1], a_mats[2])
        rot = _mm(np.take(self._R_soa, index, axis=-1), _mm(a_mats[0], q0))

        vel = acc = None
        pre_w: list[FloatArray] = []  # A_j^T w^(j-1)
        post_w: list[FloatArray] = []  # w^(j)
        pre_a: list[FloatArray] = []  # A_j^T alpha^(j-1)
        if order >= 1:
            assert dlam is not None
            w = np.zeros((3, m))
            alpha = np.zeros((3, m))
            for j in range(3):
                pw = _mtv(a_mats[j], w) if j > 0 else w
                w = pw + dlam[:, j + 1] * d[j]
                pre_w.append(pw)
                post_w.append(w)
                if order >= 2:
                    assert ddlam is not None
                    pa = _mtv(a_mats[j], alpha) if j > 0 else alpha
                    alpha = pa + ddlam[:, j + 1] * d[j] + dlam[:, j + 1] * _cross(w, d[j])
                    pre_a.append(pa)
            vel = w
            acc = alpha if order >= 2 else None
        coef_out = None
        if vjp_blocks is not None:
            assert rows is not None
            coef_out = np.empty((6, 3, m))
            vjp_blocks.append(_VJPBlock(rows, (d[0], d[1], d[2]), q0, q1, coef_out))
        if not (jacobians or coef_out is not None):
            return rot, vel, acc

        # d eps / d d_j = lambda_j Q_j^T Jr(lambda_j d_j); d d_j / d delta_{i+j+1} = Jr_inv(d_j),
        # d d_j / d delta_{i+j} = -Jl_inv(d_j). With Jinv^s = I + s hat(d) + e hat(d)^2
        # (s = +1/2: Jr_inv, s = -1/2: Jl_inv) and hat^3 = -theta^2 hat, the products
        # F_j^s = lambda_j Jr(lambda_j d_j) Jinv^s(d_j) are again functions of hat(d_j).
        f_plus: list[FloatArray] = []
        f_minus: list[FloatArray] = []
        coef_c: list[FloatArray] = []
        c0: FloatArray | None = None
        for j in range(3):
            lj = lam[:, j + 1]
            c = _theta_minus_sin_over_theta3(angle[j])
            coef_c.append(c)
            p1 = -coef_b[j] * lj
            p2 = c * lj * lj
            e = ecoef[j]
            for s, dest in ((0.5, f_plus), (-0.5, f_minus)):
                # slots C_0, F_0^+, F_1^-, F_1^+, F_2^-, F_2^+ receive (a, b, c) of F in place
                coef = None if coef_out is None else coef_out[2 * j + int(s > 0)]
                first = j == 0 and s < 0
                into = None if coef is None or first else coef
                g1 = np.multiply(
                    lj, p1 + s - th2[j] * (p1 * e + p2 * s), out=None if into is None else into[1]
                )
                g2 = np.multiply(
                    lj, p2 + e + p1 * s - th2[j] * p2 * e, out=None if into is None else into[2]
                )
                if first:
                    # Only A_0^T - F_0^- is needed: the direct dependence on R_i
                    # (P^T = Q_0^T A_0^T) folded with the d_0 term.
                    f = (
                        1.0 - lj,
                        np.subtract(-coef_a[0] * lj, g1, out=None if coef is None else coef[1]),
                        np.subtract(coef_b[0] * lj * lj, g2, out=None if coef is None else coef[2]),
                    )
                    if jacobians:
                        dest.append(np.empty(0))  # placeholder, F_0^- itself is never used
                        c0 = _fn_of_hat(d[0], outer[0], th2[0], *f)
                else:
                    f = (lj, g1, g2)
                    if jacobians:
                        dest.append(_fn_of_hat(d[j], outer[j], th2[j], *f))
                if coef is not None:
                    np.subtract(f[0], f[2] * th2[j], out=coef[0])
        if not jacobians:
            return rot, vel, acc
        assert c0 is not None

        def combine(
            x_plus: list[FloatArray],
            x_first: FloatArray,
            x_minus: list[FloatArray],
            out: FloatArray,
        ) -> None:
            """J_0 = Q_0^T x_first, J_k = Q_{k-1}^T X_{k-1}^+ - Q_k^T X_k^- (k = 1, 2, 3)."""
            out[0] = _mtm(q0, x_first)
            out[1] = _mtm(q0, x_plus[0])
            out[1] -= _mtm(q1, x_minus[1])
            out[2] = _mtm(q1, x_plus[1])
            out[2] -= x_minus[2]
            out[3] = x_plus[2]

        assert jac_out[0] is not None
        combine(f_plus, c0, f_minus, jac_out[0])
        if jac_out[1] is None:
            return rot, vel, acc

        # d w / d d_j = Q_j^T (lambda_j' I + lambda_j hat(A_j^T w^(j-1)) Jr(lambda_j d_j)), so
        # times Jinv^s(d_j): X_j^s = lambda_j' Jinv^s(d_j) + hat(A_j^T w^(j-1)) F_j^s.
        assert dlam is not None
        x_plus: list[FloatArray] = []
        x_minus: list[FloatArray] = []
        for j in range(3):
            dl = dlam[:, j + 1]
            for s, fs, dest in ((0.5, f_plus[j], x_plus), (-0.5, f_minus[j], x_minus)):
                x = _fn_of_hat(d[j], outer[j], th2[j], dl, s * dl, dl * ecoef[j])
                if j > 0:  # w^(-1) = 0
                    x += _hat_mm(pre_w[j], fs)
                dest.append(x)
        assert jac_out[1] is not None
        combine(x_plus, -x_minus[0], x_minus, jac_out[1])
        if jac_out[2] is None:
            return rot, vel, acc

        # Angular acceleration: derivatives w.r.t. d_j propagated forward through the
        # recursion, then the chain rule through Jr_inv / Jl_inv (generic form).
        assert ddlam is not None
        g_a: list[FloatArray] = []
        for j in range(3):
            lj = lam[:, j + 1]
            jr = _fn_of_hat(d[j], outer[j], th2[j], 1.0, -coef_b[j] * lj, coef_c[j] * lj * lj)
            loc_w = _add_diag(lj * _hat_mm(pre_w[j], jr), dlam[:, j + 1])
            la = lj * _hat_mm(pre_a[j], jr)
            # + lambda_j'' I + lambda_j' (hat(w^(j)) - hat(d_j) dw^(j)/dd_j)
            la -= dlam[:, j + 1] * _hat_mm(d[j], loc_w)
            _add_hat(la, post_w[j], dlam[:, j + 1])
            _add_diag(la, ddlam[:, j + 1])
            gw = loc_w
            for k in range(j + 1, 3):
                gw = _mtm(a_mats[k], gw)
                la = _mtm(a_mats[k], la) - dlam[:, k + 1] * _hat_mm(d[k], gw)
            g_a.append(la)
        jinv = [
            [_fn_of_hat(d[j], outer[j], th2[j], 1.0, s, ecoef[j]) for j in range(3)]
            for s in (0.5, -0.5)
        ]
        j_acc = jac_out[2]
        assert j_acc is not None
        j_acc[0] = -_mm(g_a[0], jinv[1][0])
        j_acc[1] = _mm(g_a[0], jinv[0][0]) - _mm(g_a[1], jinv[1][1])
        j_acc[2] = _mm(g_a[1], jinv[0][1]) - _mm(g_a[2], jinv[1][2])
        j_acc[3] = _mm(g_a[2], jinv[0][2])
        return rot, vel, acc

    # ---- fitting ------------------------------------------------------------------------

    @classmethod
    def from_rotations(
        cls,
        knots: UniformKnots,
        t_s: npt.ArrayLike,
        rotations: npt.ArrayLike,
        iterations: int = 3,
        damping: float = 1e-6,
    ) -> SO3Spline:
        """Fit a spline to sampled rotations ``R_G_I(t_m)`` (initial guess for the optimiser).

        Control points start at the samples interpolated (geodesically) at their peak times
        ``t0 + (k - 1) dt`` (clamped to the sampled interval), then ``iterations`` Gauss-Newton
        steps minimise ``sum_m |Log(R_m^T R(t_m))|^2 + damping |delta|^2``.

        Args:
            knots: knot vector; every sample time must lie in its range.
            t_s: (M,) sample times, seconds (any order).
            rotations: (M, 3, 3) sampled rotations ``R_G_I``.
            iterations: Gauss-Newton iterations (0 returns the interpolated guess).
            damping: Levenberg damping on the increments, keeps control points without data
                at their interpolated value.

        Returns:
            The fitted spline.

        Raises:
            ValueError: on shape mismatches, no samples, or times outside the knot range.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        rots = np.asarray(rotations, dtype=np.float64)
        if rots.shape != (t.shape[0], 3, 3) or t.shape[0] == 0:
            msg = f"rotations must have shape ({t.shape[0]}, 3, 3) with M >= 1, got {rots.shape}"
            raise ValueError(msg)
        order = np.argsort(t, kind="stable")
        t, rots = t[order], rots[order]
        knots.locate(t)  # range check

        tc = np.clip(knots.control_point_times_s(), t[0], t[-1])
        if t.shape[0] == 1:
            ctrl = np.broadcast_to(rots[0], (knots.num_control_points, 3, 3))
        else:
            j = np.clip(np.searchsorted(t, tc, side="right") - 1, 0, t.shape[0] - 2)
            span = t[j + 1] - t[j]
            s = np.where(span > 0, (tc - t[j]) / np.where(span > 0, span, 1.0), 0.0)
            s = np.clip(s, 0.0, 1.0)
            rel = so3.log(np.swapaxes(rots[j], -1, -2) @ rots[j + 1])
            ctrl = rots[j] @ so3.exp(s[:, None] * rel)
        spline = cls.from_matrices(knots, ctrl)

        n = knots.num_control_points
        m = t.shape[0]
        rows = np.arange(m)[:, None, None, None] * 3 + np.arange(3)[None, None, :, None]
        rows = np.broadcast_to(rows, (m, 4, 3, 3))
        for _ in range(iterations):
            r0, jac, index = _fit_residuals(spline, t, rots)
            cols = 3 * (index[:, None, None, None] + _OFFSETS[None, :, None, None])
            cols = np.broadcast_to(cols + np.arange(3)[None, None, None, :], (m, 4, 3, 3))
            J = sp.csr_matrix((jac.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, 3 * n))
            normal = (J.T @ J + damping * sp.identity(3 * n)).tocsc()
            delta = spla.spsolve(normal, -(J.T @ r0.ravel()))
            spline = spline.retract(np.asarray(delta).reshape(n, 3))
        return spline


def _fit_residuals(
    spline: SO3Spline, t_s: FloatArray, rotations: FloatArray
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Residuals of :meth:`SO3Spline.from_rotations` and their control-point Jacobians.

    Args:
        spline: Current spline.
        t_s: (M,) sample times, seconds.
        rotations: (M, 3, 3) sampled ``R_G_I``.

    Returns:
        ``(r, J, index)``: (M, 3) ``r = Log(R_m^T R(t_m))``, (M, 4, 3, 3)
        ``J = d r / d delta_{i+k} = Jr_inv(r) d eps / d delta_{i+k}`` (right perturbations) and
        (M,) first active control points ``i``.
    """
    ev = spline.evaluate(t_s, order=0, jacobians=True)
    assert ev.jac_rotation is not None
    r0 = so3.log(np.swapaxes(rotations, -1, -2) @ ev.rotation)  # (M, 3)
    return r0, so3.Jr_inv(r0)[:, None] @ ev.jac_rotation, ev.index


class SO3EvaluationCache:
    """One :meth:`SO3Spline.evaluate` result shared by residual blocks with the same query times.

    The gyroscope and the accelerometer residuals are evaluated at the same IMU sample times;
    with a common cache the rotation spline (its construction and its evaluation with
    Jacobians) is computed once per state instead of once per block. :meth:`evaluate` returns
    the stored result when the control points and the times are equal to the stored ones and
    the stored evaluation holds everything requested; otherwise it evaluates the union of what
    was asked at these times (the highest order seen, Jacobians when requested) and stores it.
    Results are read-only views shared between the callers.
    """

    def __init__(self) -> None:
        """Create an empty cache."""
        self._t: FloatArray | None = None
        self._quats: FloatArray | None = None
        self._knots: UniformKnots | None = None
        self._spline: SO3Spline | None = None
        self._eval: SO3SplineEval | None = None
        self._order = 0
        self._jacobians = False

    def spline(self, knots: UniformKnots, control_quats: npt.ArrayLike) -> SO3Spline:
        """The spline with these knots and (N, 4) control quaternions (built once per value)."""
        q = np.asarray(control_quats, dtype=np.float64)
        if (
            self._spline is None
            or self._knots != knots
            or self._quats is None
            or self._quats.shape != q.shape
            or not np.array_equal(self._quats, q)
        ):
            self._spline = SO3Spline(knots, q)
            self._knots = knots
            self._quats = q.copy()
            self._eval = None
        return self._spline

    def evaluate(
        self,
        knots: UniformKnots,
        control_quats: npt.ArrayLike,
        t_s: FloatArray,
        order: int,
        jacobians: bool,
    ) -> SO3SplineEval:
        """:meth:`SO3Spline.evaluate` at ``t_s`` (order ``>= order``, Jacobians up to it).

        Args:
            knots: Knot vector of the spline.
            control_quats: (N, 4) control quaternions ``[x, y, z, w]``.
            t_s: (M,) query times, seconds.
            order: Highest derivative needed (0, 1 or 2).
            jacobians: Whether the control-point Jacobians are needed.

        Returns:
            The evaluation (possibly of a higher order, with Jacobians of every returned
            quantity).
        """
        spline = self.spline(knots, control_quats)
        same_times = self._t is not None and (
            self._t is t_s or (self._t.shape == t_s.shape and np.array_equal(self._t, t_s))
        )
        if not same_times:
            self._t = np.array(t_s, dtype=np.float64)
            self._eval = None
            self._order = 0
            self._jacobians = False
        stored = self._eval
        if stored is not None and self._order >= order and (self._jacobians or not jacobians):
            return stored
        self._order = max(self._order, order)
        self._jacobians = jacobians or (stored is not None and self._jacobians)
        self._eval = spline.evaluate(t_s, order=self._order, jacobians=self._jacobians)
        return self._eval
