"""Point-to-plane residual block (method.md section 4, paper eq. point2planedis).

For point ``k`` with raw measurement ``(beam, rho, theta)``, LiDAR time ``tau_k`` (LiDAR-clock
seconds relative to the problem's reference time) and associated plane ``n^T x + d = 0`` in
``{G}`` (held fixed within an optimisation round)::

    p_L = lidar_point(intrinsics, beam, rho, theta)
    t   = tau_k + t_c
    p_G = R(t) (R_IL p_L + t_IL) + p(t)
    r   = (n^T p_G + d) / (s0_i sigma_k)

``s0_i`` is the range scale of the point's beam when the block was built (the start of a
round), a constant of the block: the noise is the raw range's, ``s_i sigma_k`` in metres, and
whitening in raw-range units keeps the cost invariant when the world and every length of the
LiDAR model scale together (in metres a smaller range scale would shrink the residuals with the
map). Whitening with the current ``s_i`` instead rewards a larger range scale for shrinking
every residual: its derivative ``-r / s_i`` times the residual sums to about ``-N / s_i``, which
pushed the beams' common range scale up by 1.6e-4 to 2.5e-4 in ten rounds of the paper's
sinusoid. Held constant within a round, the weights are those of a weighted least-squares fit.

One scalar robust-loss group per point (use the solver's Huber loss). Jacobians: ``traj.so3``
and ``traj.r3`` (4 control points around ``t``), ``ext.rotation`` (right perturbation of
``R_IL``), ``ext.translation``, ``ext.time_offset`` (``n^T (R hat(w) p_I + v)``) and
``lidar.intrinsics`` (the 6 coordinates of the point's own beam).

The derivatives w.r.t. the beam intrinsics are taken at the range the model predicts, where
the point's ray meets its plane, not at the measured range. The derivatives of the elevation,
azimuth and range scale grow with the range; at the measured range they carry the range noise,
which is also the residual's, and the product of the two does not average out: freeing the
elevations under 15 mm of range noise moved the LiDAR's translation by millimetres along its z
axis (``benchmarks/study_range_noise_bias.py``). At the predicted range the derivatives are
those of the noise-free point, as far as the estimate is right. The derivatives w.r.t. the
trajectory's and the extrinsic's rotation and the time offset depend on the point as well
(``p x n`` and ``w . (p_I x n_I)``) and are taken there too: at the measured point they biased
the time offset of 10 s sinusoids by +0.15 ms under 3 cm of range noise (six seeds, all
positive; +0.04 ms with this). With this, the Jacobian is not the residual's exact derivative
away from zero residuals; ``intrinsics_at_predicted_range=False`` and
``motion_at_predicted_range=False`` give the exact one.

If a time-offset step moves a query time outside the spline range, that point's residual is
``inf`` so that the solver rejects the step (the builder checks the initial state).

The points are evaluated in blocks of the splines' block size (8192), each from the spline
evaluation to its whitened derivatives, written into its own rows of preallocated outputs; the
blocks share the threads of :mod:`licalib_cli.parallel.threads` and give bit-for-bit what one
evaluation of all points gives.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import fields, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry.so3 import quat_to_matrix
from licalib_cli.geometry.vectors import cross_rows
from licalib_cli.models.lidar import (
    NUM_BEAM_INTRINSICS,
    BeamIntrinsic,
    LidarPointTerms,
    PointToPlaneGeometry,
    lidar_point_terms,
    nominal_intrinsics_array,
    point_to_plane,
)
from licalib_cli.parallel.threads import map_slices
from licalib_cli.residuals import (
    EXT_ROTATION,
    EXT_TRANSLATION,
    LIDAR_INTRINSICS,
    POINT_TIME_SCALE,
    TIME_DRIFT,
    TIME_OFFSET,
    TRAJ_R3,
    TRAJ_SO3,
)
from licalib_cli.solver.problem import DenseJacobian, ResidualEval
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

__all__ = ["PointToPlaneResidual"]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

_OFFSETS = np.arange(4, dtype=np.intp)


class PointToPlaneResidual:
    """Whitened signed distances of LiDAR points to their associated planes in ``{G}``."""

    def __init__(
        self,
        knots: UniformKnots,
        t_lidar_s: npt.ArrayLike,
        beam: npt.ArrayLike,
        rho: npt.ArrayLike,
        theta: npt.ArrayLike,
        normal: npt.ArrayLike,
        d: npt.ArrayLike,
        sigma: float | npt.ArrayLike,
        nominal_elevation: npt.ArrayLike,
        *,
        model_gap: npt.ArrayLike | None = None,
        t_ref_s: float = 0.0,
        sweep_start_s: npt.ArrayLike | None = None,
        intrinsics_at_predicted_range: bool = True,
        motion_at_predicted_range: bool = True,
        whitening_range_scale: npt.ArrayLike | None = None,
        name: str = "lidar.point_to_plane",
    ) -> None:
        """Create the block.

        Args:
            knots: knot vector of the trajectory splines.
            t_lidar_s: (N,) point times ``tau_k``, LiDAR-clock seconds relative to the reference.
            beam: (N,) beam index of each point, in ``[0, B)``.
            rho: (N,) raw range, m.
            theta: (N,) raw azimuth, rad.
            normal: (N, 3) unit normal of each point's plane, ``{G}``.
            d: (N,) offset ``d`` of each point's plane ``n^T x + d = 0``, m.
            sigma: (N,) or scalar standard deviation of the distance, m (e.g. the range noise,
                a conservative bound: the distance noise is the range noise times the cosine of
                the incidence angle).
            nominal_elevation: (B,) nominal beam elevations ``phi_i``, rad.
            model_gap: (N, 3) what the driver's published point adds to the LiDAR model's point
                (LiDAR frame, m), added to the modelled point; None for zero.
            t_ref_s: reference time of a clock drift (the IMU time of a point is
                ``tau + t_c + k_drift (tau - t_ref)``).
            sweep_start_s: (N,) time of each point's sweep start, LiDAR-clock seconds, for an
                error of the per-point times within a sweep (``tau - k_point (tau - start)``);
                None: that term is not available.
            intrinsics_at_predicted_range: take the derivatives w.r.t. the beam intrinsics at
                the range the model predicts (where the point's ray meets its plane) instead of
                the measured range (see the module docstring); False gives the exact
                derivatives of the residual.
            motion_at_predicted_range: the same for the derivatives w.r.t. the trajectory's
                and the extrinsic's rotation and the time (they depend on the point too).
            whitening_range_scale: (B,) range scales ``s0`` of the whitening (see the module
                docstring); None for ones.
            name: residual block name.

        Raises:
            ValueError: on inconsistent shapes, beam indices out of range or bad sigmas.
        """
        self.name = name
        self.knots = knots
        self.t_s = np.ascontiguousarray(t_lidar_s, dtype=np.float64).reshape(-1)
        n = self.t_s.shape[0]
        self.beam = np.ascontiguousarray(beam, dtype=np.intp).reshape(-1)
        self.rho = np.ascontiguousarray(rho, dtype=np.float64).reshape(-1)
        self.theta = np.ascontiguousarray(theta, dtype=np.float64).reshape(-1)
        self._cos_sin_theta = (np.cos(self.theta), np.sin(self.theta))
        self.normal = np.ascontiguousarray(normal, dtype=np.float64)
        self.d = np.ascontiguousarray(d, dtype=np.float64).reshape(-1)
        self.nominal_elevation = np.ascontiguousarray(nominal_elevation, dtype=np.float64)
        sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (n,))
        if not (
            self.beam.shape == self.rho.shape == self.theta.shape == self.d.shape == (n,)
            and self.normal.shape == (n, 3)
        ):
            msg = (
                "point arrays disagree in length "
                "(need t, beam, rho, theta, d (N,) and normal (N, 3))"
            )
            raise ValueError(msg)
        if n and (self.beam.min() < 0 or self.beam.max() >= self.nominal_elevation.shape[0]):
            msg = f"beam indices must lie in [0, {self.nominal_elevation.shape[0]})"
            raise ValueError(msg)
        if not np.all(np.isfinite(sig) & (sig > 0.0)):
            msg = "point-to-plane sigmas must be positive and finite"
            raise ValueError(msg)
        self.inv_sigma = 1.0 / sig
        self.model_gap = (
            None
            if model_gap is None
            else np.ascontiguousarray(model_gap, dtype=np.float64).reshape(n, 3)
        )
        self.since_ref = self.t_s - float(t_ref_s)
        self.into_sweep = (
            None
            if sweep_start_s is None
            else self.t_s - np.ascontiguousarray(sweep_start_s, dtype=np.float64).reshape(n)
        )
        self.intrinsics_at_predicted_range = bool(intrinsics_at_predicted_range)
        self.motion_at_predicted_range = bool(motion_at_predicted_range)
        b = self.nominal_elevation.shape[0]
        self.whitening_range_scale = (
            np.ones(b)
            if whitening_range_scale is None
            else np.array(whitening_range_scale, dtype=np.float64).reshape(b)
        )
        if not np.all(np.isfinite(self.whitening_range_scale) & (self.whitening_range_scale > 0)):
            msg = "the whitening's range scales must be positive and finite"
            raise ValueError(msg)
        self._zeros = np.zeros((n, 1), dtype=np.intp)
        self._beam_elements = self.beam[:, None].copy()
        # (intrinsics, sigmas, what they give) of the last evaluation: see _model_terms
        self._terms_cache: tuple[F64, F64, tuple[LidarPointTerms, F64, F64]] | None = None

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def query_times(
        self, time_offset_s: float, time_drift: float = 0.0, point_time_scale: float = 0.0
    ) -> F64:
        """(N,) IMU-clock query times ``tau_k + t_c [+ k_drift (tau - t_ref)]
        [- k_point (tau - sweep start)]``, seconds."""
        t = self.t_s + time_offset_s
        if time_drift:
            t = t + time_drift * self.since_ref
        if point_time_scale and self.into_sweep is not None:
            t = t - point_time_scale * self.into_sweep
        return t

    def whitening(self) -> F64:
        """(N,) what a distance in metres is multiplied by to give the residual:
        ``1 / (s0_i sigma_k)``, the same for every state."""
        return self.inv_sigma / self.whitening_range_scale[self.beam]

    def distances(self, params: Mapping[str, F64]) -> F64:
        """(N,) signed point-to-plane distances in metres (not whitened)."""
        ev = self.evaluate(params, jacobians=False)
        return ev.residuals[:, 0] / self.whitening()

    def _model_terms(self, intr: F64) -> tuple[LidarPointTerms, F64, F64]:
        """The LiDAR model's terms, the modelled points (model gap added) and each point's
        whitening ``1 / (s0_i sigma_k)`` for the (B, 6) intrinsics ``intr``.

        They depend on the intrinsics and the sigmas only, so they are kept from one evaluation
        to the next while both stay the same (every iteration of a solve that holds the
        intrinsics fixed). The arrays it computes are read-only.
        """
        cached = self._terms_cache
        if cached is not None and cached[1] is self.inv_sigma and np.array_equal(cached[0], intr):
            return cached[2]
        n = self.rho.shape[0]
        terms = LidarPointTerms(np.empty((n, 3)), self.rho, *(np.empty(n) for _ in range(5)))
        cos_theta, sin_theta = self._cos_sin_theta

        def block(sl: slice) -> None:
            # the same per-point values as one call over all points, on the block threads
            part = lidar_point_terms(
                self.nominal_elevation,
                intr,
                self.beam[sl],
                self.rho[sl],
                self.theta[sl],
                (cos_theta[sl], sin_theta[sl]),
            )
            for f in fields(part):
                if f.name != "rho":
                    getattr(terms, f.name)[sl] = getattr(part, f.name)

        map_slices(block, n)
        point = terms.point if self.model_gap is None else terms.point + self.model_gap
        w = self.whitening()
        for a in (point, w, *(getattr(terms, f.name) for f in fields(terms) if f.name != "rho")):
            a.flags.writeable = False  # (rho is the block's own input array)
        out = (terms, point, w)
        self._terms_cache = (intr.copy(), self.inv_sigma, out)
        return out

    def evaluate(self, params: Mapping[str, F64], jacobians: bool = True) -> ResidualEval:
        """Whitened residuals (N, 1) and their Jacobians (see the module docstring)."""
        n = self.t_s.shape[0]
        tc = float(np.asarray(params.get(TIME_OFFSET, 0.0)).reshape(-1)[0])
        drift = float(np.asarray(params.get(TIME_DRIFT, 0.0)).reshape(-1)[0])
        k_point = float(np.asarray(params.get(POINT_TIME_SCALE, 0.0)).reshape(-1)[0])
        t = self.query_times(tc, drift, k_point)
        inside = self.knots.contains(t)
        all_inside = bool(np.all(inside))
        if not all_inside:
            logger.debug("%d point times outside the spline range", n - int(inside.sum()))
            t = self.knots.clamp(t)
        intr = params.get(LIDAR_INTRINSICS)
        if intr is None:
            intr = nominal_intrinsics_array(self.nominal_elevation.shape[0])
        want_time = jacobians and any(
            b in params for b in (TIME_OFFSET, TIME_DRIFT, POINT_TIME_SCALE)
        )
        intr = np.asarray(intr, dtype=np.float64).reshape(-1, NUM_BEAM_INTRINSICS)
        terms, point, w = self._model_terms(intr)
        so3_spline = SO3Spline(self.knots, params[TRAJ_SO3])
        r3_spline = R3Spline(self.knots, params[TRAJ_R3])
        r_il = quat_to_matrix(params[EXT_ROTATION])
        t_il = np.asarray(params[EXT_TRANSLATION], dtype=np.float64)
        order = 1 if want_time else 0
        want_intr = jacobians and LIDAR_INTRINSICS in params
        r = np.empty(n)
        elements = np.empty((n, 4), dtype=np.intp) if jacobians else None
        j_so3 = np.empty((n, 1, 4, 3)) if jacobians else None
        j_r3 = np.empty((n, 1, 4, 3)) if jacobians else None
        d_ext_rotation = np.empty((n, 3)) if jacobians and EXT_ROTATION in params else None
        d_ext_translation = np.empty((n, 3)) if jacobians and EXT_TRANSLATION in params else None
        d_time = np.empty(n) if want_time else None
        d_int = np.empty((n, NUM_BEAM_INTRINSICS)) if want_intr else None
        intr_shift = want_intr and self.intrinsics_at_predicted_range
        range_scale = intr[self.beam, BeamIntrinsic.RANGE_SCALE] if intr_shift else None
        motion_shift = jacobians and self.motion_at_predicted_range

        def block(sl: slice) -> None:
            """Points ``sl``: splines, geometry and whitened derivatives, written into their
            rows of the outputs."""
            tb, wb = t[sl], w[sl]
            rot_ev = so3_spline.evaluate(tb, order=order, rotation_vjp=jacobians)
            pos_ev = r3_spline.evaluate(tb, order=order)
            geo = point_to_plane(
                rot_ev.rotation,
                pos_ev.position,
                r_il,
                t_il,
                point[sl],
                self.normal[sl],
                self.d[sl],
                rot_ev.angular_velocity,
                pos_ev.velocity,
            )
            # whitened in raw-range units (the module docstring)
            np.multiply(geo.distance, wb, out=r[sl])
            if not jacobians:
                return
            assert rot_ev.rotation_vjp is not None and elements is not None
            assert j_so3 is not None and j_r3 is not None
            wc = wb[:, None]
            moved: F64 | None = None  # metres from each range to where its ray meets its plane
            if motion_shift or intr_shift:
                ray, along = _rays(terms, sl, geo.d_point)
                moved = _predicted_range_shift(along, geo.distance, 1.0 / wb)
                if motion_shift:
                    geo = _at_predicted_range(geo, ray, moved, r_il, rot_ev.angular_velocity)
            np.add(rot_ev.index[:, None], _OFFSETS, out=elements[sl])
            j_so3[sl, 0] = rot_ev.rotation_vjp(geo.d_rotation * wc)
            # outer products of the weighted blending weights and the normals (einsum is about
            # twice as fast as broadcasting over the short trailing axes)
            np.einsum("ni,nj->nij", pos_ev.weights * wc, self.normal[sl], out=j_r3[sl, 0])
            if d_ext_rotation is not None:
                np.multiply(geo.d_ext_rotation, wc, out=d_ext_rotation[sl])
            if d_ext_translation is not None:
                np.multiply(geo.d_ext_translation, wc, out=d_ext_translation[sl])
            if d_time is not None:
                assert geo.d_time is not None
                np.multiply(geo.d_time, wb, out=d_time[sl])
            if d_int is not None:
                # v^T d p_L / d intrinsics of each point, here while its rows are in cache
                d_int[sl] = terms.rows(sl).vjp(
                    geo.d_point * wc,
                    moved if intr_shift else None,
                    range_scale[sl] if range_scale is not None else None,
                )

        # Blocks of the spline evaluations' size, each from the splines to its whitened
        # derivatives while its arrays are in cache, shared by the threads of
        # licalib_cli.parallel.threads (the splines evaluate each block serially there).
        map_slices(block, n)
        if not all_inside:
            r = np.where(inside, r, np.inf)
        if not jacobians:
            return ResidualEval(r[:, None])
        assert elements is not None and j_so3 is not None and j_r3 is not None
        jacs: list[DenseJacobian] = [
            DenseJacobian(TRAJ_SO3, elements, j_so3),
            DenseJacobian(TRAJ_R3, elements, j_r3),
        ]
        if d_ext_rotation is not None:
            jacs.append(DenseJacobian(EXT_ROTATION, self._zeros, d_ext_rotation[:, None, None]))
        if d_ext_translation is not None:
            jacs.append(
                DenseJacobian(EXT_TRANSLATION, self._zeros, d_ext_translation[:, None, None])
            )
        if d_time is not None:
            d_t = d_time
            if TIME_OFFSET in params:
                jacs.append(DenseJacobian(TIME_OFFSET, self._zeros, d_t[:, None, None, None]))
            if TIME_DRIFT in params:
                j = (d_t * self.since_ref)[:, None, None, None]
                jacs.append(DenseJacobian(TIME_DRIFT, self._zeros, j))
            if POINT_TIME_SCALE in params and self.into_sweep is not None:
                j = (-d_t * self.into_sweep)[:, None, None, None]
                jacs.append(DenseJacobian(POINT_TIME_SCALE, self._zeros, j))
        if d_int is not None:
            jacs.append(DenseJacobian(LIDAR_INTRINSICS, self._beam_elements, d_int[:, None, None]))
        return ResidualEval(r[:, None], tuple(jacs))


#: Smallest cosine between a ray and its plane's normal at which the predicted range is used
#: (about 75 deg of incidence; beyond, a small distance moves the intersection far).
_MIN_RAY_COSINE = 0.25
#: Largest shift from the measured to the predicted range, in noise sigmas (outliers keep theirs).
_MAX_SHIFT_SIGMAS = 3.0


def _rays(terms: LidarPointTerms, sl: slice, n_lidar: F64) -> tuple[F64, F64]:
    """(n, 3) unit rays ``u`` of the points ``sl`` in ``{L}`` and (n,) ``n_L . u``."""
    cp = terms.cos_phi[sl]
    ray = np.empty((cp.shape[0], 3))
    np.multiply(cp, terms.cos_theta[sl], out=ray[:, 0])
    np.multiply(cp, terms.sin_theta[sl], out=ray[:, 1])
    ray[:, 2] = terms.sin_phi[sl]
    return ray, np.einsum("ni,ni->n", ray, n_lidar)


def _predicted_range_shift(along: F64, distance: F64, sigma_m: F64) -> F64:
    """(n,) metres from each measured corrected range to where its ray meets its plane.

    The distance changes by ``along = n_L . u`` per metre of range along the ray ``u``, so the
    model predicts the range ``rho_bar - distance / (n_L . u)``. Rays within about 15 deg of
    their plane keep the measured range; the shift is clipped to ``_MAX_SHIFT_SIGMAS`` noise
    sigmas ``sigma_m`` (m).
    """
    steep = np.abs(along) >= _MIN_RAY_COSINE
    limit = _MAX_SHIFT_SIGMAS * sigma_m
    return np.where(steep, np.clip(-distance / np.where(steep, along, 1.0), -limit, limit), 0.0)


def _at_predicted_range(
    geo: PointToPlaneGeometry, ray: F64, moved: F64, r_il: F64, angular_velocity: F64 | None
) -> PointToPlaneGeometry:
    """``geo`` with the derivatives that depend on the point (the trajectory's and the
    extrinsic's rotation, the time) taken at the point moved ``moved`` metres along its ray
    ``ray`` (``{L}``): they are linear in the point, so each gains ``moved`` times its value
    for the ray. The distance and the other derivatives stay."""
    step = moved[:, None]
    ray_imu = ray @ r_il.T
    along_rotation = cross_rows(ray_imu, geo.d_ext_translation)  # u_I x n_I
    d_rotation = geo.d_rotation + step * along_rotation
    d_ext_rotation = geo.d_ext_rotation + step * cross_rows(ray, geo.d_point)
    d_time = geo.d_time
    if d_time is not None and angular_velocity is not None:
        d_time = d_time + moved * np.einsum("ni,ni->n", angular_velocity, along_rotation)
    return replace(geo, d_rotation=d_rotation, d_ext_rotation=d_ext_rotation, d_time=d_time)
