"""The joint problem of multi-segment calibration: one problem over several segments.

The segments share the extrinsic and every intrinsic the model estimates; each keeps its own
trajectory spline, IMU biases, gravity and time offset (and clock or bias drifts when
estimated). Each segment's residual blocks keep their own parameter block names; its own blocks
are renamed ``seg<k>:<name>`` by a thin adapter (:class:`RenamedBlock`) that also renames the
Jacobians, shared blocks keep their name, so the solver's Schur complement, truncated SVD and
sigmas apply unchanged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from licalib_cli.estimation import (
    BLOCK_SPECS,
    CalibrationState,
    FreeParameters,
    build_problem,
)
from licalib_cli.pipeline.round import RoundInputs
from licalib_cli.pipeline.settings import model_priors
from licalib_cli.residuals import ACCEL_BIAS_DRIFT, GYRO_BIAS_DRIFT, TIME_DRIFT, TIME_OFFSET
from licalib_cli.solver.parameters import ParameterBlock
from licalib_cli.solver.problem import Problem, ResidualBlock, ResidualEval

__all__ = [
    "RenamedBlock",
    "joint_problem",
    "per_segment_blocks",
    "segment_name",
    "segment_values",
    "values_of_segment",
]

F64 = npt.NDArray[np.float64]

_PER_SEGMENT_CALIBRATION = (TIME_OFFSET, TIME_DRIFT, GYRO_BIAS_DRIFT, ACCEL_BIAS_DRIFT)
"""Calibration-group blocks that belong to a segment, not to the sensors."""


def per_segment_blocks() -> frozenset[str]:
    """Names of the blocks every segment has its own copy of (the rest is shared)."""
    own = {s.name for s in BLOCK_SPECS if s.group == "trajectory"}
    return frozenset(own | set(_PER_SEGMENT_CALIBRATION))


def segment_name(index: int, block: str) -> str:
    """The joint problem's name of segment ``index``'s own copy of ``block``."""
    return f"seg{index + 1}:{block}"


class RenamedBlock:
    """A segment's residual block in the joint problem: parameter names mapped both ways."""

    def __init__(self, inner: ResidualBlock, rename: Mapping[str, str], prefix: str) -> None:
        self.inner = inner
        self.rename = dict(rename)
        self.name = f"{prefix}{inner.name}"

    def evaluate(self, params: Mapping[str, F64], jacobians: bool = True) -> ResidualEval:
        local = {own: params[joint] for own, joint in self.rename.items() if joint in params}
        ev = self.inner.evaluate(local, jacobians)
        jac = tuple(replace(j, block=self.rename.get(j.block, j.block)) for j in ev.jacobians)
        return ResidualEval(ev.residuals, jac)


def joint_problem(
    states: Sequence[CalibrationState],
    inputs: Sequence[RoundInputs],
    free: FreeParameters,
    fix_shared: bool = False,
) -> Problem:
    """One problem over the segments: shared extrinsic and intrinsics, the rest per segment.

    The shared blocks take their values from the first state.

    Args:
        states: each segment's estimate.
        inputs: each segment's IMU data, associated points, planes and weights.
        free: what is estimated (as in a single-segment round).
        fix_shared: hold the shared blocks (to compare with the segments alone).
    """
    own = per_segment_blocks()
    problem = Problem()
    for k, (state, data) in enumerate(zip(states, inputs, strict=True)):
        single = build_problem(
            state,
            data.imu,
            data.lidar,
            data.planes,
            data.noise,
            free,
            extra_residuals=model_priors(state, free) if k == 0 else (),
        )
        rename: dict[str, str] = {}
        mine = {segment_name(k, b) for b in own}
        for block in single.parameter_blocks:
            name = segment_name(k, block.name) if block.name in own else block.name
            rename[block.name] = name
            if name in problem:
                continue
            coords = block.coord_names
            if name in mine and block.group == "calibration":
                coords = tuple(f"seg{k + 1}:{c}" for c in coords)
            fixed = block.fixed_mask
            if fix_shared and name not in mine:
                fixed[:] = True
            problem.add_parameter_block(
                ParameterBlock(
                    name,
                    block.value,
                    manifold=block.manifold,
                    group=block.group,
                    coord_names=coords,
                    scale=block.scale,
                    fixed=fixed,
                )
            )
        for residual, loss in zip(single.residual_blocks, single.losses, strict=True):
            problem.add_residual_block(RenamedBlock(residual, rename, f"seg{k + 1}:"), loss)
    return problem


def segment_values(problem: Problem, k: int) -> dict[str, F64]:
    """Segment ``k``'s values under their single-segment block names."""
    return values_of_segment(problem.values(), k)


def values_of_segment(values: Mapping[str, F64], k: int) -> dict[str, F64]:
    """Segment ``k``'s entries of the joint problem's ``values``, under their single-segment
    block names."""
    own = per_segment_blocks()
    out = {}
    for name in (spec.name for spec in BLOCK_SPECS):
        joint = segment_name(k, name) if name in own else name
        if joint in values:
            out[name] = values[joint]
    return out
