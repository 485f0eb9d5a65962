"""Gaussian priors on parameter blocks, as residual blocks.

A prior on block ``x`` with mean ``mu`` and standard deviations ``sigma`` contributes, per element
``e`` of the block, the residual group ``r_e = local(mu_e, x_e) / sigma_e`` (``tangent_dim``
residuals): ``x - mu`` for euclidean blocks and ``Log(R(mu)^T R(x))`` for so3 blocks (right
perturbation, Jacobian ``Jr^-1(r)``). Typical uses: keep intrinsics near their nominal values with
a weak sigma, or tie biases to a previous estimate.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry.so3 import Jr_inv
from licalib_cli.solver.parameters import local
from licalib_cli.solver.problem import DenseJacobian, ResidualEval

__all__ = ["GaussianPrior"]

F64 = npt.NDArray[np.float64]


class GaussianPrior:
    """Prior ``N(mean, diag(sigma^2))`` on one euclidean or so3 parameter block."""

    def __init__(
        self,
        block: str,
        mean: npt.ArrayLike,
        sigma: float | npt.ArrayLike,
        *,
        manifold: Literal["euclidean", "so3"] = "euclidean",
        name: str | None = None,
    ) -> None:
        """Create the prior.

        Args:
            block: parameter block name.
            mean: prior mean in the block's value shape (quaternions ``[x, y, z, w]`` for so3).
            sigma: standard deviations in tangent units: a scalar, ``(tangent_dim,)`` or
                ``(num_elements, tangent_dim)``; ``inf`` disables a coordinate.
            manifold: the block's manifold (``"euclidean"`` or ``"so3"``).
            name: residual block name (default ``"prior.<block>"``).

        Raises:
            ValueError: on an unsupported manifold or non-positive sigmas.
        """
        if manifold not in ("euclidean", "so3"):
            msg = f"priors support euclidean and so3 blocks, not {manifold!r}"
            raise ValueError(msg)
        self.block = block
        self.name = name if name is not None else f"prior.{block}"
        self.manifold = manifold
        mean_arr = np.array(mean, dtype=np.float64)
        self.shape = mean_arr.shape
        ambient = (
            4
            if manifold == "so3"
            else (mean_arr.shape[-1] if mean_arr.ndim == 2 else mean_arr.size)
        )
        self.mean = mean_arr.reshape(-1, ambient)
        self.tangent_dim = 3 if manifold == "so3" else ambient
        e = self.mean.shape[0]
        sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (e, self.tangent_dim))
        if np.any(~(sig > 0.0)):
            msg = f"prior sigmas on {block!r} must be positive"
            raise ValueError(msg)
        self.inv_sigma = 1.0 / sig
        self._elements = np.arange(e, dtype=np.intp)[:, None]

    def evaluate(self, params: Mapping[str, F64], jacobians: bool = True) -> ResidualEval:
        """Whitened residuals (E, tangent_dim) and the Jacobian on the block."""
        x = np.asarray(params[self.block], dtype=np.float64).reshape(self.mean.shape)
        delta = local(self.manifold, self.mean, x)
        r = delta * self.inv_sigma
        if not jacobians:
            return ResidualEval(r)
        e, d = r.shape
        if self.manifold == "so3":
            jac = Jr_inv(delta) * self.inv_sigma[:, :, None]
        else:
            jac = np.broadcast_to(np.eye(d), (e, d, d)) * self.inv_sigma[:, :, None]
        return ResidualEval(r, (DenseJacobian(self.block, self._elements, jac[:, :, None, :]),))
