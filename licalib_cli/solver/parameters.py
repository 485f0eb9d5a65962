"""Parameter blocks on manifolds: the state the solver updates.

A parameter block is an array of ``n`` identical elements living on one manifold, e.g. the 753 SO3
control points of a rotation spline (value ``(753, 4)``), the R3 control points ``(753, 3)``, the
gravity vector (``(3,)``, S2), the extrinsic rotation (``(4,)``, SO3), the time offset (``()``) or
per-beam LiDAR intrinsics ``(B, 6)``. The solver works in the block's *tangent coordinates*: a flat
vector of ``n * tangent_dim`` numbers, element-major (coordinate ``e * tangent_dim + k`` is
component ``k`` of element ``e``).

Manifolds and their retractions ``x <- x [+] delta``:

* ``euclidean``: ``x + delta``; the tangent coordinates are the value's coordinates.
* ``so3``: quaternions ``[x, y, z, w]`` with right perturbation ``R <- R Exp(delta)``; ``delta``
  is a rotation vector in radians in the element's *local* (body) frame.
* ``s2``: a vector of fixed norm (e.g. gravity, m/s^2): ``v <- Exp(B(v) delta) v`` where ``B(v)``
  (3, 2) is an orthonormal basis of the plane orthogonal to ``v`` (:func:`s2_basis`); ``delta`` is
  in radians and the norm never changes. ``d(v [+] delta)/d delta`` at zero is
  ``-hat(v) B(v)`` (:func:`s2_retraction_jacobian`), needed by residuals touching such a block.

Each block belongs to a *group*: ``"trajectory"`` blocks (spline, biases, gravity) are eliminated by
the Schur complement; ``"calibration"`` blocks (extrinsics, time offset, intrinsics) are solved by
the truncated SVD and reported. Each tangent coordinate has a name (``"extrinsic.translation.x"``),
a characteristic *scale* in its own unit (e.g. 0.01 m, 0.001 rad, 0.001 s) used to make the
calibration block dimensionless before singular values are compared, and a *fixed* flag. Fixed
coordinates are removed from the linear system and never move; the mask may change between rounds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry.so3 import hat, quat_exp, quat_log, quat_multiply

__all__ = [
    "GROUPS",
    "MANIFOLDS",
    "Group",
    "ManifoldName",
    "ParameterBlock",
    "local",
    "retract",
    "s2_basis",
    "s2_retraction_jacobian",
]

F64 = npt.NDArray[np.float64]

ManifoldName = Literal["euclidean", "so3", "s2"]
Group = Literal["trajectory", "calibration"]
MANIFOLDS: tuple[str, ...] = ("euclidean", "so3", "s2")
GROUPS: tuple[str, ...] = ("trajectory", "calibration")

_TANGENT_SUFFIXES = {"so3": ("rx", "ry", "rz"), "s2": ("u", "v")}
_EUCLIDEAN_SUFFIXES = {3: ("x", "y", "z")}


def _quat_normalize_keep_sign(q: F64) -> F64:
    """Unit quaternions without the ``w >= 0`` canonicalisation (keeps spline sign continuity)."""
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def s2_basis(v: npt.ArrayLike) -> F64:
    """Orthonormal basis of the plane orthogonal to ``v``.

    The first basis vector is ``normalize(a x u)`` with ``u = v / |v|`` and ``a`` the unit axis
    (z, or x when ``|u_z| > 0.9``); the second is ``u x b1``. The basis is a smooth function of
    ``v`` away from the switch.

    Args:
        v: (..., 3) non-zero vectors.

    Returns:
        (..., 3, 2) basis; columns orthonormal and orthogonal to ``v``.
    """
    v = np.asarray(v, dtype=np.float64)
    u = v / np.linalg.norm(v, axis=-1, keepdims=True)
    use_x = np.abs(u[..., 2:3]) > 0.9
    a = np.where(use_x, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    b1 = np.cross(a, u)
    b1 = b1 / np.linalg.norm(b1, axis=-1, keepdims=True)
    b2 = np.cross(u, b1)
    return np.stack([b1, b2], axis=-1)


def s2_retraction_jacobian(v: npt.ArrayLike) -> F64:
    """Derivative of ``v [+] delta`` with respect to ``delta`` at ``delta = 0``.

    Args:
        v: (..., 3) vectors (any fixed norm).

    Returns:
        (..., 3, 2) ``-hat(v) @ s2_basis(v)``.
    """
    v = np.asarray(v, dtype=np.float64)
    return -hat(v) @ s2_basis(v)


def _rodrigues_rotate(phi: F64, v: F64) -> F64:
    """``Exp(phi) v`` for (..., 3) rotation vectors and vectors."""
    theta = np.linalg.norm(phi, axis=-1, keepdims=True)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    axis = phi / safe
    cos, sin = np.cos(theta), np.sin(theta)
    rotated = (
        v * cos
        + np.cross(axis, v) * sin
        + axis * np.sum(axis * v, axis=-1, keepdims=True) * (1.0 - cos)
    )
    first_order = v + np.cross(phi, v)
    return np.where(small, first_order, rotated)


def retract(manifold: ManifoldName, x: npt.ArrayLike, delta: npt.ArrayLike) -> F64:
    """``x [+] delta`` element-wise.

    Args:
        manifold: ``"euclidean"``, ``"so3"`` or ``"s2"``.
        x: (n, ambient_dim) values (quaternions ``[x, y, z, w]`` for so3).
        delta: (n, tangent_dim) tangent steps (radians for so3 and s2).

    Returns:
        (n, ambient_dim) retracted values.
    """
    x = np.asarray(x, dtype=np.float64)
    delta = np.asarray(delta, dtype=np.float64)
    if manifold == "euclidean":
        return x + delta
    if manifold == "so3":
        return _quat_normalize_keep_sign(quat_multiply(x, quat_exp(delta)))
    if manifold == "s2":
        phi = np.einsum("...ij,...j->...i", s2_basis(x), delta)
        out = _rodrigues_rotate(phi, x)
        norm = np.linalg.norm(x, axis=-1, keepdims=True)
        return out * (norm / np.linalg.norm(out, axis=-1, keepdims=True))
    msg = f"Unknown manifold {manifold!r}; use one of {', '.join(MANIFOLDS)}."
    raise ValueError(msg)


def local(manifold: ManifoldName, x0: npt.ArrayLike, x1: npt.ArrayLike) -> F64:
    """Inverse retraction: ``delta`` with ``x0 [+] delta == x1``.

    Args:
        manifold: ``"euclidean"``, ``"so3"`` or ``"s2"``.
        x0: (n, ambient_dim) base values.
        x1: (n, ambient_dim) target values (same norm as ``x0`` for s2).

    Returns:
        (n, tangent_dim) tangent coordinates (so3: ``Log(R0^T R1)``, ``|delta| <= pi``).
    """
    x0 = np.asarray(x0, dtype=np.float64)
    x1 = np.asarray(x1, dtype=np.float64)
    if manifold == "euclidean":
        return x1 - x0
    if manifold == "so3":
        conj = np.concatenate([-x0[..., :3], x0[..., 3:]], axis=-1)
        return quat_log(_quat_normalize_keep_sign(quat_multiply(conj, x1)))
    if manifold == "s2":
        u0 = x0 / np.linalg.norm(x0, axis=-1, keepdims=True)
        u1 = x1 / np.linalg.norm(x1, axis=-1, keepdims=True)
        axis = np.cross(u0, u1)
        sin = np.linalg.norm(axis, axis=-1, keepdims=True)
        angle = np.arctan2(sin, np.sum(u0 * u1, axis=-1, keepdims=True))
        phi = axis * np.where(sin > 1e-15, angle / np.where(sin > 1e-15, sin, 1.0), 1.0)
        return np.einsum("...ji,...j->...i", s2_basis(x0), phi)
    msg = f"Unknown manifold {manifold!r}; use one of {', '.join(MANIFOLDS)}."
    raise ValueError(msg)


def _tangent_dim(manifold: str, ambient_dim: int) -> int:
    if manifold == "so3":
        return 3
    if manifold == "s2":
        return 2
    return ambient_dim


def _expected_ambient(manifold: str) -> int | None:
    return {"so3": 4, "s2": 3}.get(manifold)


def _default_names(name: str, manifold: str, n: int, tdim: int) -> tuple[str, ...]:
    if manifold in _TANGENT_SUFFIXES:
        suffixes: tuple[str, ...] = _TANGENT_SUFFIXES[manifold]
    elif tdim in _EUCLIDEAN_SUFFIXES:
        suffixes = _EUCLIDEAN_SUFFIXES[tdim]
    elif tdim == 1:
        suffixes = ("",)
    else:
        suffixes = tuple(f"[{k}]" for k in range(tdim))

    def join(prefix: str, suffix: str) -> str:
        if not suffix:
            return prefix
        return prefix + suffix if suffix.startswith("[") else f"{prefix}.{suffix}"

    if n == 1:
        return tuple(join(name, s) for s in suffixes)
    return tuple(join(f"{name}[{e}]", s) for e in range(n) for s in suffixes)


class ParameterBlock:
    """A named array of identical elements on one manifold, with names, scales and a fixed mask.

    The block is the mutable state the solver updates in place (``value`` is replaced by a new
    array at every accepted step; arrays handed out are never modified afterwards).

    Attributes:
        name: Unique block name, e.g. ``"extrinsic.translation"``.
        manifold: ``"euclidean"``, ``"so3"`` or ``"s2"``.
        group: ``"trajectory"`` (eliminated by the Schur complement) or ``"calibration"``.
        shape: Shape of :attr:`value` as given at construction.
        num_elements: Number of elements ``n``.
        ambient_dim: Stored numbers per element (4 for so3, 3 for s2).
        tangent_dim: Tangent coordinates per element (3 for so3, 2 for s2).
        size: ``num_elements * tangent_dim``.
        coord_names: (size,) names of the tangent coordinates.
        scale: (size,) characteristic magnitude of each coordinate in its own unit.
    """

    def __init__(
        self,
        name: str,
        value: npt.ArrayLike,
        *,
        manifold: ManifoldName = "euclidean",
        group: Group = "trajectory",
        coord_names: Sequence[str] | None = None,
        scale: float | npt.ArrayLike = 1.0,
        fixed: bool | npt.ArrayLike = False,
    ) -> None:
        """Create a block.

        Args:
            name: Unique block name.
            value: Initial value: ``()`` or ``(d,)`` for one element, ``(n, d)`` for ``n``
                elements; so3 elements are quaternions ``[x, y, z, w]`` (``d = 4``), s2 elements
                vectors (``d = 3``) whose norm is kept.
            manifold: Manifold of every element.
            group: ``"trajectory"`` or ``"calibration"``.
            coord_names: Names of the ``n * tangent_dim`` tangent coordinates; default
                ``name.x``/``name[e].rx``-style names.
            scale: Characteristic magnitude per tangent coordinate (scalar, ``(tangent_dim,)``
                broadcast over elements, or ``(size,)``), > 0.
            fixed: Whole block fixed (bool) or a ``(size,)`` boolean mask.

        Raises:
            ValueError: On an unknown manifold/group, a wrong value shape, names or scales.
        """
        if manifold not in MANIFOLDS:
            msg = f"Unknown manifold {manifold!r} for block {name!r}; use one of {MANIFOLDS}."
            raise ValueError(msg)
        if group not in GROUPS:
            msg = f"Unknown group {group!r} for block {name!r}; use one of {GROUPS}."
            raise ValueError(msg)
        arr = np.array(value, dtype=np.float64)
        if arr.ndim > 2:
            msg = f"Block {name!r} value must be (), (d,) or (n, d); got shape {arr.shape}."
            raise ValueError(msg)
        self.name = name
        self.manifold: ManifoldName = manifold
        self.group: Group = group
        self.shape: tuple[int, ...] = arr.shape
        elements = arr.reshape(1, -1) if arr.ndim < 2 else arr
        expected = _expected_ambient(manifold)
        if expected is not None and elements.shape[1] != expected:
            msg = (
                f"Block {name!r} on {manifold} needs {expected} numbers per element; "
                f"got value shape {arr.shape}."
            )
            raise ValueError(msg)
        self.num_elements = int(elements.shape[0])
        self.ambient_dim = int(elements.shape[1])
        self.tangent_dim = _tangent_dim(manifold, self.ambient_dim)
        self.size = self.num_elements * self.tangent_dim
        self._elements = self._normalised(elements)
        if coord_names is None:
            coord_names = _default_names(name, manifold, self.num_elements, self.tangent_dim)
        if len(coord_names) != self.size:
            msg = f"Block {name!r} needs {self.size} coordinate names; got {len(coord_names)}."
            raise ValueError(msg)
        self.coord_names: tuple[str, ...] = tuple(coord_names)
        self.scale = self._per_coord(scale, "scale")
        if not np.all(self.scale > 0.0):
            msg = f"Block {name!r} scales must be positive."
            raise ValueError(msg)
        self._fixed = np.zeros(self.size, dtype=bool)
        self.set_fixed(fixed)

    def _normalised(self, elements: F64) -> F64:
        if self.manifold == "so3":
            return _quat_normalize_keep_sign(elements)
        return elements.copy()

    def _per_coord(self, x: float | npt.ArrayLike, what: str) -> F64:
        arr = np.asarray(x, dtype=np.float64)
        if arr.ndim == 0:
            return np.full(self.size, float(arr))
        if arr.shape == (self.tangent_dim,):
            return np.tile(arr, self.num_elements)
        if arr.shape == (self.size,):
            return arr.copy()
        msg = (
            f"Block {self.name!r} {what} must be a scalar, ({self.tangent_dim},) or "
            f"({self.size},); got shape {arr.shape}."
        )
        raise ValueError(msg)

    # ----------------------------------------------------------------------------------- value
    @property
    def value(self) -> F64:
        """Current value in the shape given at construction (a fresh read-only view)."""
        out = self._elements.reshape(self.shape)
        out.flags.writeable = False
        return out

    @property
    def elements(self) -> F64:
        """Current value as ``(num_elements, ambient_dim)`` (read-only view)."""
        out = self._elements.view()
        out.flags.writeable = False
        return out

    def set_value(self, value: npt.ArrayLike) -> None:
        """Replace the value (same shape; so3 quaternions are normalised).

        Args:
            value: Array of shape :attr:`shape` (or ``(num_elements, ambient_dim)``).

        Raises:
            ValueError: On a shape mismatch.
        """
        arr = np.array(value, dtype=np.float64)
        if arr.size != self.num_elements * self.ambient_dim:
            msg = f"Block {self.name!r} expects shape {self.shape}; got {arr.shape}."
            raise ValueError(msg)
        self._elements = self._normalised(arr.reshape(self.num_elements, self.ambient_dim))

    def retracted(self, delta: npt.ArrayLike) -> F64:
        """Value after the tangent step ``delta`` (the block itself is not changed).

        Args:
            delta: (size,) tangent step, element-major. Fixed coordinates must be zero.

        Returns:
            Array of shape :attr:`shape`.
        """
        d = np.asarray(delta, dtype=np.float64).reshape(self.num_elements, self.tangent_dim)
        return retract(self.manifold, self._elements, d).reshape(self.shape)

    def local(self, value: npt.ArrayLike) -> F64:
        """Tangent coordinates of ``value`` relative to the current value.

        Args:
            value: Array of shape :attr:`shape`.

        Returns:
            (size,) ``delta`` with ``current [+] delta == value``.
        """
        x1 = np.asarray(value, dtype=np.float64).reshape(self.num_elements, self.ambient_dim)
        return local(self.manifold, self._elements, x1).reshape(-1)

    # ---------------------------------------------------------------------------------- fixing
    @property
    def fixed_mask(self) -> npt.NDArray[np.bool_]:
        """(size,) True where the tangent coordinate is held fixed (copy)."""
        return self._fixed.copy()

    @property
    def num_free(self) -> int:
        """Number of free tangent coordinates."""
        return int(self.size - np.count_nonzero(self._fixed))

    def set_fixed(self, fixed: bool | npt.ArrayLike) -> None:
        """Set the whole fixed mask.

        Args:
            fixed: A bool for every coordinate, or a (size,) boolean mask.
        """
        arr = np.asarray(fixed, dtype=bool)
        if arr.ndim == 0:
            self._fixed = np.full(self.size, bool(arr))
        elif arr.shape == (self.size,):
            self._fixed = arr.copy()
        else:
            msg = f"Block {self.name!r} fixed mask must be a bool or ({self.size},): {arr.shape}."
            raise ValueError(msg)

    def _select(self, coords: Sequence[int | str] | npt.ArrayLike | None) -> npt.NDArray[np.intp]:
        if coords is None:
            return np.arange(self.size)
        arr = np.asarray(coords)
        if arr.dtype == bool:
            if arr.shape != (self.size,):
                msg = f"Block {self.name!r} coordinate mask must have shape ({self.size},)."
                raise ValueError(msg)
            return np.flatnonzero(arr)
        out = []
        for c in arr.reshape(-1).tolist():
            if isinstance(c, str):
                if c not in self.coord_names:
                    msg = f"Block {self.name!r} has no coordinate named {c!r}."
                    raise ValueError(msg)
                out.append(self.coord_names.index(c))
            else:
                out.append(int(c))
        return np.asarray(out, dtype=np.intp)

    def fix(self, coords: Sequence[int | str] | npt.ArrayLike | None = None) -> None:
        """Fix coordinates (all when ``coords`` is None).

        Args:
            coords: Indices, names, or a (size,) boolean mask of tangent coordinates.
        """
        self._fixed[self._select(coords)] = True

    def free(self, coords: Sequence[int | str] | npt.ArrayLike | None = None) -> None:
        """Free coordinates (all when ``coords`` is None).

        Args:
            coords: Indices, names, or a (size,) boolean mask of tangent coordinates.
        """
        self._fixed[self._select(coords)] = False

    def __repr__(self) -> str:
        return (
            f"ParameterBlock({self.name!r}, shape={self.shape}, manifold={self.manifold!r}, "
            f"group={self.group!r}, free={self.num_free}/{self.size})"
        )
