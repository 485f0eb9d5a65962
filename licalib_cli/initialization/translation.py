"""Initial lever arm, gravity and accelerometer bias by linear least squares.

With the rotation ``R_G_I(t)`` known (the gyro spline) and the extrinsic rotation known, the
LiDAR odometry gives the LiDAR origin ``p_G_L(t_k)`` at the scan times (in ``{G}``, up to a
constant) and the accelerometer gives the specific force. Both are linear in

* the control points ``c`` of the IMU position spline ``p_G_I(t) = B(t) c``,
* the lever arm ``t = t_imu_lidar`` (the LiDAR origin in the IMU frame),
* gravity ``g_G`` (3 free components; its norm is imposed afterwards) and the accelerometer
  bias ``b_a`` (with a loose prior about zero, which decides only what the motion leaves
  undetermined: with rotation about one axis, the bias and gravity along that axis):

    odometry       p_G_I(t_k) + R_G_I(t_k) t            = p_G_L(t_k)       (sigma_p)
    accelerometer  R_G_I(t_i)^T (p_G_I''(t_i) - g_G) + b_a = a_m(t_i)      (sigma_a)

This is the idea of LI-Init's lever-arm step (LiDAR trajectory acceleration against the specific
force, with the angular-rate terms of the lever arm), written on the continuous-time spline: the
accelerometer shapes the position between the 10 Hz odometry poses instead of differentiating
them twice, so it also works when the rig shakes. The lever arm enters through the rotation
only; a direction about which the rig did not turn (``R_G_I(t) t`` constant) is absorbed by the
spline and left at its prior (zero or the configured value) instead of being guessed.

Frames: ``{G}`` is the IMU frame at the first IMU sample, ``{M}`` the odometry map. Times are
float seconds on the IMU clock relative to the problem's reference.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from licalib_cli.errors import ExcitationError
from licalib_cli.geometry.so3 import hat
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

__all__ = ["LeverArmConfig", "LeverArmEstimate", "estimate_lever_arm"]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

_OFFSETS = np.arange(4, dtype=np.intp)

MAX_BIAS_SIGMAS = 4.0
"""An accelerometer bias beyond this many of its prior sigmas means the least squares fitted an
odometry that the accelerometer contradicts: no estimate is returned."""


@dataclass(frozen=True)
class LeverArmConfig:
    """Settings of :func:`estimate_lever_arm`.

    Attributes:
        position_sigma_m: assumed noise of an odometry position, m.
        accel_sigma: assumed noise of an accelerometer sample, m/s^2 (larger than the sensor
            noise: it also covers the spline's and the gyro rotation's errors).
        gravity_norm: norm imposed on gravity, m/s^2.
        max_std_m: a lever-arm direction whose standard deviation exceeds this is not
            determined by the data and stays at the prior.
        accel_bias_sigma: prior standard deviation of the accelerometer bias about zero,
            m/s^2. Loose (a MEMS accelerometer's turn-on bias is a few tenths at most), it
            matters only where the data leave the bias undetermined: rotation about one axis
            ``v`` only (planar motion) leaves the bias along ``v`` and gravity along ``v``
            interchangeable, and without it the split between them is arbitrary (a bias of
            several m/s^2 with gravity turned to match).
        huber_sigmas: Huber threshold of the reweighting, in sigmas (odometry outliers).
        iterations: reweighting iterations.
        smoothing: weight of a curvature penalty on the control points (relative to the data),
            which only matters where no sample constrains the spline (padding).
        min_excitation_deg: a lever-arm direction ``d`` is determined only if ``R_G_I(t) d``
            varies over the poses by at least this RMS angle (the rig turned about an axis
            other than ``d``); otherwise it is left at the prior whatever the least squares
            says (small tilts, drift and odometry errors would make it up).
    """

    position_sigma_m: float = 0.02
    accel_sigma: float = 0.1
    gravity_norm: float = 9.81
    max_std_m: float = 0.05
    accel_bias_sigma: float = 1.0
    huber_sigmas: float = 3.0
    iterations: int = 3
    smoothing: float = 1e-8
    min_excitation_deg: float = 5.0


@dataclass(frozen=True)
class LeverArmEstimate:
    """Result of :func:`estimate_lever_arm`.

    Attributes:
        t_imu_lidar: (3,) lever arm, m (prior components where not determined).
        std_m: (3,) standard deviation of each component, m (``inf`` along an undetermined
            direction).
        undetermined: (k, 3) unit directions (IMU frame) left at the prior.
        gravity_G: (3,) gravity in ``{G}``, norm ``gravity_norm``.
        accel_bias: (3,) accelerometer bias, m/s^2.
        position: spline of the IMU position ``p_G_I(t)``.
        position_rms_m: RMS odometry residual (inliers), m.
        accel_rms: RMS accelerometer residual, m/s^2.
    """

    t_imu_lidar: F64
    std_m: F64
    undetermined: F64
    gravity_G: F64
    accel_bias: F64
    position: R3Spline
    position_rms_m: float
    accel_rms: float


def _block_design(
    knots: UniformKnots, t_s: F64, derivative: int, left: F64 | None
) -> sp.csr_matrix:
    """Sparse (3M, 3N) matrix of ``left_m @ d^k p/dt^k(t_m)`` in the control points.

    ``left`` is (M, 3, 3) (identity when None).
    """
    design = R3Spline(knots, np.zeros((knots.num_control_points, 3))).design_matrix(t_s, derivative)
    design = design.tocoo()
    m = t_s.shape[0]
    # Entry (row m, control point j, weight w) becomes the 3x3 block w * left_m at (3m, 3j).
    rows_m, cols_j, w = design.row, design.col, design.data
    if left is None:
        left = np.broadcast_to(np.eye(3), (m, 3, 3))
    blocks = w[:, None, None] * left[rows_m]
    rows = 3 * rows_m[:, None, None] + np.arange(3)[None, :, None]
    cols = 3 * cols_j[:, None, None] + np.arange(3)[None, None, :]
    rows = np.broadcast_to(rows, blocks.shape)
    cols = np.broadcast_to(cols, blocks.shape)
    return sp.csr_matrix(
        (blocks.ravel(), (rows.ravel(), cols.ravel())),
        shape=(3 * m, 3 * knots.num_control_points),
    )


def _dense_rows(blocks: F64) -> sp.csr_matrix:
    """(M, 3, 3) blocks stacked into a sparse (3M, 3) matrix."""
    return sp.csr_matrix(blocks.reshape(-1, 3))


def _huber_weights(r: F64, k: float) -> F64:
    """Per-sample IRLS weights for (M, 3) whitened residuals (one weight per sample)."""
    norm = np.linalg.norm(r, axis=1)
    return np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-300))


def estimate_lever_arm(
    knots: UniformKnots,
    so3_spline: SO3Spline,
    t_imu_s: npt.ArrayLike,
    accel: npt.ArrayLike,
    t_pose_s: npt.ArrayLike,
    p_G_lidar: npt.ArrayLike,
    prior_m: npt.ArrayLike | None = None,
    cfg: LeverArmConfig | None = None,
) -> LeverArmEstimate:
    """Lever arm, gravity, accelerometer bias and IMU position spline from odometry + IMU.

    Args:
        knots: knots of the position spline to fit (all times must lie inside).
        so3_spline: ``R_G_I(t)`` (from the gyro), same time axis.
        t_imu_s: (N,) accelerometer sample times, s.
        accel: (N, 3) specific force readings, m/s^2 (IMU frame).
        t_pose_s: (K,) odometry pose times on the IMU clock, s.
        p_G_lidar: (K, 3) LiDAR origin positions in ``{G}`` (up to a constant), m.
        prior_m: (3,) lever arm kept along undetermined directions (default zero).
        cfg: settings.

    Returns:
        The estimate.

    Raises:
        ExcitationError: fewer than 4 poses, the system cannot be solved, or the odometry and
            the accelerometer disagree (:data:`MAX_BIAS_SIGMAS`).
    """
    cfg = LeverArmConfig() if cfg is None else cfg
    t_i = np.asarray(t_imu_s, dtype=np.float64).reshape(-1)
    a_m = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
    t_k = np.asarray(t_pose_s, dtype=np.float64).reshape(-1)
    p_k = np.asarray(p_G_lidar, dtype=np.float64).reshape(-1, 3)
    prior = np.zeros(3) if prior_m is None else np.asarray(prior_m, dtype=np.float64).reshape(3)
    if t_k.shape[0] < 4:
        msg = "Fewer than 4 LiDAR poses to initialise the lever arm; use a longer segment."
        raise ExcitationError(msg)
    keep_i = knots.contains(t_i)
    t_i, a_m = t_i[keep_i], a_m[keep_i]
    keep_k = knots.contains(t_k)
    t_k, p_k = t_k[keep_k], p_k[keep_k]

    n_c = 3 * knots.num_control_points
    rot_k = so3_spline.rotation(t_k)  # R_G_I at the poses
    # Excited lever-arm directions: var_k |R_k d - mean| = d^T (I - Rbar^T Rbar) d.
    r_mean = rot_k.mean(axis=0)
    ex_val, ex_vec = np.linalg.eigh(np.eye(3) - r_mean.T @ r_mean)
    excited = ex_vec[:, ex_val > np.radians(cfg.min_excitation_deg) ** 2]
    rot_i = so3_spline.rotation(t_i)
    rot_i_t = np.swapaxes(rot_i, 1, 2)

    # Columns: [c (n_c) | t (3) | phi (3) | g (3) | b_a (3)]; phi is a small rotation of the
    # odometry trajectory into {G} (the error of the initial extrinsic rotation):
    # p_G_L = (I + [phi]x) p0  =>  p0 = p_G_L - [phi]x p0 ~ p_G_I + R t + [p0]x phi.
    a_pos = sp.hstack(
        [
            _block_design(knots, t_k, 0, None),
            _dense_rows(rot_k),
            _dense_rows(hat(p_k - p_k.mean(axis=0))),
            sp.csr_matrix((3 * t_k.shape[0], 6)),
        ]
    ).tocsr()
    eye = np.broadcast_to(np.eye(3), (t_i.shape[0], 3, 3))
    a_acc = sp.hstack(
        [
            _block_design(knots, t_i, 2, rot_i_t),
            sp.csr_matrix((3 * t_i.shape[0], 6)),
            _dense_rows(-rot_i_t),
            _dense_rows(np.ascontiguousarray(eye)),
        ]
    ).tocsr()
    y_pos = (p_k - p_k.mean(axis=0)).reshape(-1)
    y_acc = a_m.reshape(-1)
    n = a_pos.shape[1]
    # Curvature penalty on the control points (third differences of positions, so that the
    # penalty does not fight the accelerations), tiny against the data.
    n_cp = knots.num_control_points
    d3 = sp.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(n_cp - 3, n_cp))
    reg_c = sp.kron(d3.T @ d3, sp.identity(3))
    reg = sp.block_diag([reg_c, sp.csr_matrix((12, 12))]).tocsc()

    w_pos = np.ones(t_k.shape[0])
    w_acc = np.ones(t_i.shape[0])
    x = np.zeros(n)
    t_idx = slice(n_c, n_c + 3)
    g_idx = slice(n_c + 6, n_c + 9)
    b_idx = slice(n_c + 9, n_c + 12)
    # the accelerometer bias's prior (about zero), added to the normal equations below
    prior_weight = np.zeros(n)
    prior_weight[b_idx] = 1.0 / cfg.accel_bias_sigma**2
    bias_prior = sp.diags(prior_weight, format="csc")
    gravity_fixed: F64 | None = None
    info_t = np.zeros((3, 3))
    for it in range(cfg.iterations + 1):
        sw_pos = np.repeat(np.sqrt(w_pos) / cfg.position_sigma_m, 3)
        sw_acc = np.repeat(np.sqrt(w_acc) / cfg.accel_sigma, 3)
        a_w = sp.vstack([sp.diags(sw_pos) @ a_pos, sp.diags(sw_acc) @ a_acc]).tocsr()
        y_w = np.concatenate([sw_pos * y_pos, sw_acc * y_acc])
        normal = (a_w.T @ a_w).tocsc()
        rhs = a_w.T @ y_w
        scale = float(normal.diagonal()[:n_c].max())
        normal = normal + cfg.smoothing * scale * reg + bias_prior
        free = np.ones(n, dtype=bool)
        if gravity_fixed is not None:
            free[g_idx] = False
            rhs = rhs - normal[:, g_idx] @ gravity_fixed
        x_free, info_t = _solve_with_prior(normal, rhs, free, n_c, prior, excited, cfg)
        x = np.zeros(n)
        x[free] = x_free
        if gravity_fixed is not None:
            x[g_idx] = gravity_fixed
        g = x[g_idx]
        if gravity_fixed is None:
            norm = float(np.linalg.norm(g))
            if not np.isfinite(norm) or norm < 1e-6:
                msg = "The accelerometer does not determine gravity; check the IMU data."
                raise ExcitationError(msg)
            gravity_fixed = cfg.gravity_norm * g / norm
        r_pos = ((a_pos @ x - y_pos) / cfg.position_sigma_m).reshape(-1, 3)
        r_acc = ((a_acc @ x - y_acc) / cfg.accel_sigma).reshape(-1, 3)
        if it < cfg.iterations:
            w_pos = _huber_weights(r_pos, cfg.huber_sigmas)
            w_acc = _huber_weights(r_acc, cfg.huber_sigmas)

    bias = float(np.linalg.norm(x[b_idx]))
    if bias > MAX_BIAS_SIGMAS * cfg.accel_bias_sigma:
        # the odometry (drifting, or a map blurred by the LiDAR's errors) and the accelerometer
        # disagree: the fit pushed the bias far beyond its prior and its lever arm means nothing
        msg = (
            "The odometry and the accelerometer disagree: the lever-arm least squares needs an "
            f"accelerometer bias of {bias:.1f} m/s^2."
        )
        raise ExcitationError(msg)
    # Covariance of t from its information, scaled by the a-posteriori variance factor.
    res_pos = (a_pos @ x - y_pos).reshape(-1, 3)
    res_acc = (a_acc @ x - y_acc).reshape(-1, 3)
    inl = w_pos >= 1.0
    pos_rms = float(np.sqrt(np.mean(np.sum(res_pos[inl] ** 2, axis=1)) / 3.0)) if inl.any() else 0.0
    acc_rms = float(np.sqrt(np.mean(res_acc**2)))
    dof = max(3 * (t_k.shape[0] + t_i.shape[0]) - n, 1)
    chi2 = float(
        np.sum(w_pos[:, None] * (res_pos / cfg.position_sigma_m) ** 2)
        + np.sum(w_acc[:, None] * (res_acc / cfg.accel_sigma) ** 2)
    )
    factor = max(chi2 / dof, 1.0)
    proj = excited @ excited.T
    evals, evecs = np.linalg.eigh(0.5 * (proj @ info_t @ proj + (proj @ info_t @ proj).T))
    std_dir = np.sqrt(factor / np.maximum(evals, 1e-300))
    undetermined = std_dir > cfg.max_std_m
    cov = (evecs[:, ~undetermined] * (factor / evals[~undetermined])) @ evecs[:, ~undetermined].T
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    weak = evecs[:, undetermined].T
    if weak.size:
        along = np.sum(weak**2, axis=0) > 1e-4
        std = np.where(along, np.inf, std)
    t_est = x[t_idx]
    logger.info(
        "lever arm from odometry and accelerometer: [%.3f %.3f %.3f] m (std %s), %d direction(s) "
        "left at the prior; odometry RMS %.1f mm, accelerometer RMS %.3f m/s^2",
        *t_est,
        np.array2string(1e3 * std, precision=1),
        int(undetermined.sum()),
        1e3 * pos_rms,
        acc_rms,
    )
    return LeverArmEstimate(
        t_imu_lidar=t_est,
        std_m=std,
        undetermined=weak,
        gravity_G=x[g_idx],
        accel_bias=x[b_idx],
        position=R3Spline(knots, x[:n_c].reshape(-1, 3)),
        position_rms_m=pos_rms,
        accel_rms=acc_rms,
    )


def _solve_with_prior(
    normal: sp.csc_matrix,
    rhs: F64,
    free: npt.NDArray[np.bool_],
    n_c: int,
    prior: F64,
    excited: F64,
    cfg: LeverArmConfig,
) -> tuple[F64, F64]:
    """Solve the free unknowns; the lever arm only along the directions the data determine.

    The control points are eliminated (sparse LU), leaving a small system in the lever arm,
    gravity and bias. Its Schur complement on the lever arm gives the lever arm's information
    matrix; directions with a standard deviation (at unit variance factor) above
    ``cfg.max_std_m``, and directions outside ``excited`` ((3, k) orthonormal columns), are
    held at ``prior``.

    Returns:
        ``(x_free, information_t)`` with ``information_t`` the (3, 3) lever-arm information.
    """
    idx = np.flatnonzero(free)
    sub = normal[idx][:, idx].tocsc()
    b = rhs[idx]
    nc = n_c
    h_cc = sub[:nc, :nc].tocsc()
    h_cx = sub[:nc, nc:].toarray()
    h_xx = sub[nc:, nc:].toarray()
    try:
        lu = spla.splu(h_cc)
    except RuntimeError as err:
        msg = "The lever-arm system is singular; the odometry and IMU do not overlap enough."
        raise ExcitationError(msg) from err
    z = lu.solve(h_cx)
    s = h_xx - h_cx.T @ z
    bs = b[nc:] - z.T @ b[:nc]
    # x = [t (3), (g (3)), b_a (3)]; eliminate everything but t from s.
    k = s.shape[0]
    t_sl = slice(0, 3)
    rest = slice(3, k)
    s_tt, s_tr, s_rr = s[t_sl, t_sl], s[t_sl, rest], s[rest, rest]
    # Pseudo-inverse of the rest (rotation of the odometry, gravity, bias): some of it can be
    # undetermined (rotation about one axis only), which must not spoil the lever arm.
    w, v = np.linalg.eigh(0.5 * (s_rr + s_rr.T))
    if w.size and w[-1] <= 0.0:
        msg = "Gravity and the accelerometer bias cannot be separated; rotate the rig more."
        raise ExcitationError(msg)
    inv_w = np.where(w > 1e-10 * w[-1], 1.0 / np.where(w > 0, w, 1.0), 0.0)
    rr_pinv = (v * inv_w) @ v.T
    rr_inv_rt = rr_pinv @ s_tr.T
    rr_inv_b = rr_pinv @ bs[rest]
    info_t = s_tt - s_tr @ rr_inv_rt
    b_t = bs[t_sl] - s_tr @ rr_inv_b
    proj = excited @ excited.T
    info_ex = proj @ info_t @ proj
    evals, evecs = np.linalg.eigh(0.5 * (info_ex + info_ex.T))
    keep = evals > 1.0 / cfg.max_std_m**2
    t_sol = prior.copy()
    if np.any(keep):
        v = evecs[:, keep]
        # Minimise the quadratic over prior + v y.
        y = np.linalg.solve(v.T @ info_t @ v, v.T @ (b_t - info_t @ prior))
        t_sol = prior + v @ y
    rest_sol = rr_inv_b - rr_inv_rt @ t_sol
    x_small = np.concatenate([t_sol, rest_sol])
    c = lu.solve(b[:nc] - h_cx @ x_small)
    return np.concatenate([c, x_small]), info_t
