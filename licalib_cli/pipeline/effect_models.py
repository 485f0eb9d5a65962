"""The models the model selection compares (method.md section 10).

The configuration that estimates exactly a set of candidate effects, a state with one effect
taken back to where the base fit had it, and a model's sum of squares on one fit's data: the
terms every BIC comparison of :mod:`licalib_cli.pipeline.diagnose`, :mod:`.rivals` and
:mod:`.backward` is made of.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from licalib_cli.config import CalibConfig, LidarSpreadSection
from licalib_cli.estimation import CalibrationState
from licalib_cli.pipeline import CalibrationRun
from licalib_cli.pipeline.diagnosis_step import CANDIDATES, COORDINATE_PREFIX, LIDAR_SUFFIX
from licalib_cli.pipeline.settings import free_parameters, lm_params
from licalib_cli.pipeline.walk_pieces import WALKS, with_walk_pieces
from licalib_cli.solver.lm import solve

__all__ = [
    "bic_terms",
    "final_config",
    "of_effect",
    "sensor_samples",
    "sum_of_squares",
    "with_effect",
    "with_effects",
    "with_spread",
    "without_effect",
]


def with_effects(cfg: CalibConfig, effects: tuple[str, ...]) -> CalibConfig:
    """``cfg`` whose ``model:`` section lists exactly ``effects`` (on top of nothing)."""
    imu = [CANDIDATES[e][1] for e in effects if CANDIDATES[e][0] == "imu"]
    lidar = [CANDIDATES[e][1] for e in effects if CANDIDATES[e][0] == "lidar"]
    return cfg.model_copy(
        update={"model": cfg.model.model_copy(update={"imu": imu, "lidar": lidar})}
    )


def with_effect(cfg: CalibConfig, effect: str) -> CalibConfig:
    """``cfg`` whose ``model:`` section estimates ``effect`` too."""
    sensor, block = CANDIDATES[effect][:2]
    current = list(getattr(cfg.model, sensor))
    if block in current:
        return cfg
    update = {sensor: [*current, block]}
    return cfg.model_copy(update={"model": cfg.model.model_copy(update=update)})


def with_spread(cfg: CalibConfig, effect: str, sigma: float) -> CalibConfig:
    """``cfg`` whose ``model.lidar_spread`` gives per-beam ``effect`` the spread ``sigma``
    (solver units)."""
    block = CANDIDATES[effect][1]
    spread = cfg.model.lidar_spread.with_sigma(block, sigma)
    return cfg.model_copy(update={"model": cfg.model.model_copy(update={"lidar_spread": spread})})


def final_config(cfg: CalibConfig, kept: tuple[str, ...]) -> CalibConfig:
    """``cfg`` estimating exactly ``kept``, with the spreads of those among them kept as one
    spread across beams and the expected sizes of those among them sized (the others' unset)."""
    out = with_effects(cfg, kept)
    if not set(kept) & set(WALKS):
        out = with_walk_pieces(out, None)
    blocks = {CANDIDATES[e][1] for e in kept}
    sizes = {b: v for b, v in cfg.model.expected_size.items() if b in blocks}
    out = out.model_copy(update={"model": out.model.model_copy(update={"expected_size": sizes})})
    spread = LidarSpreadSection()
    for effect in kept:
        block = CANDIDATES[effect][1]
        sigma = cfg.model.lidar_spread.sigma_of(block) if effect in LIDAR_SUFFIX else None
        if sigma is not None:
            spread = spread.with_sigma(block, sigma)
    return out.model_copy(update={"model": out.model.model_copy(update={"lidar_spread": spread})})


def of_effect(name: str, effect: str) -> bool:
    """Whether calibration coordinate ``name`` belongs to candidate ``effect``."""
    if effect in LIDAR_SUFFIX:
        return name.startswith("lidar.intrinsics[") and name.endswith(LIDAR_SUFFIX[effect])
    prefix = COORDINATE_PREFIX[effect]
    return name == prefix or name.startswith(prefix)


_IMU_FIELDS = {
    "gyro_scale": "gyro_scale",
    "gyro_misalignment": "gyro_misalignment",
    "gyro_rotation": "gyro_rotation",
    "accel_scale": "accel_scale",
    "accel_misalignment": "accel_misalignment",
    "g_sensitivity": "gyro_g_sensitivity",
}
_STATE_FIELDS = {
    "gyro_bias_walk": "gyro_bias_drift",
    "accel_bias_walk": "accel_bias_drift",
    "imu_clock_drift": "time_drift",
    "lidar_point_time": "point_time_scale",
}
_LIDAR_FIELDS = {
    "lidar_range_offset": "range_offset",
    "lidar_range_scale": "range_scale",
    "lidar_elevation": "elevation_correction",
    "lidar_azimuth": "azimuth_correction",
    "lidar_vertical_offset": "vertical_offset",
    "lidar_horizontal_offset": "horizontal_offset",
}


def without_effect(
    state: CalibrationState, effect: str, start: CalibrationState
) -> CalibrationState:
    """``state`` with ``effect``'s parameters back at their values in ``start`` (the base fit,
    which does not estimate them); everything else as in ``state``."""
    if effect in _IMU_FIELDS:
        name = _IMU_FIELDS[effect]
        return replace(
            state,
            imu_intrinsics=state.imu_intrinsics.with_(
                **{name: getattr(start.imu_intrinsics, name)}
            ),
        )
    if effect in _STATE_FIELDS:
        name = _STATE_FIELDS[effect]
        return replace(state, **{name: getattr(start, name)})
    name = _LIDAR_FIELDS[effect]
    return replace(
        state,
        lidar_intrinsics=state.lidar_intrinsics.with_(
            **{name: getattr(start.lidar_intrinsics, name)}
        ),
    )


def sum_of_squares(run: CalibrationRun, cfg: CalibConfig, refit: bool) -> tuple[float, int, int]:
    """``(sum r^2, residuals, free parameters)`` of ``run``'s model on ``run``'s final data.

    With ``refit``, the model of ``cfg`` is first re-solved (a few iterations) on that data.
    """
    free = free_parameters(cfg, bool(cfg.model.imu or cfg.model.lidar))
    problem = run.fit.inputs.problem(run.state, free=free)
    if refit:
        report = solve(problem, lm_params(cfg, max_iterations=4))
        cost = report.final_cost
        n_res, n_free = report.num_residuals, report.num_parameters
    else:
        ev = problem.evaluate(jacobians=False)
        cost, n_res = ev.cost, ev.num_residuals
        n_free = problem.layout().num_free
    return 2.0 * cost, n_res, n_free


def bic_terms(
    fit: CalibrationRun,
    fit_cfg: CalibConfig,
    others: Sequence[tuple[CalibrationState, CalibConfig]],
) -> list[tuple[float, int]]:
    """``(sum r^2, free parameters)`` of ``fit``'s model (``fit_cfg``) minus those of each other
    model, all on ``fit``'s final data. Each other model is given as its starting estimate and
    its configuration, and is re-solved from that estimate (a few iterations,
    :func:`sum_of_squares`)."""
    ss, _, k = sum_of_squares(fit, fit_cfg, refit=False)
    out = []
    for state, other_cfg in others:
        ss_other, _, k_other = sum_of_squares(replace(fit, state=state), other_cfg, refit=True)
        out.append((ss - ss_other, k - k_other))
    return out


def sensor_samples(run: CalibrationRun, sensor: str) -> int:
    """Residuals of ``sensor`` in ``run``'s final round (the ``n`` of an effect's BIC penalty)."""
    consistency = run.result.consistency
    assert consistency is not None
    return int(next(c.samples for c in consistency.sensors if c.sensor == sensor))
