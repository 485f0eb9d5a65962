"""Test factories: an effect the checks hold fixed (``EffectEvidence`` with its score test)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from licalib_cli.consistency.score import EffectScore
from licalib_cli.pipeline.fitcheck import EffectEvidence


def imu_effect(
    name: str = "accel_scale",
    *,
    p_value: float,
    statistic: float,
    rank: int | None = None,
    selected: bool = False,
    shift: np.ndarray | None = None,
    shift_std: np.ndarray | None = None,
    prior_std: np.ndarray | None = None,
    prior_sigma: float = 0.0,
    information: Sequence[float] | None = None,
) -> EffectEvidence:
    """A three-coordinate IMU effect: its test (``p_value``, ``statistic``; ``information``
    the eigenvalues along the directions the data determine, ``rank`` their number by default,
    and the profiled information diagonal in them) and what it does to the (7,) extrinsic
    (``shift``, ``shift_std``, ``prior_std``; zeros by default)."""
    zeros = np.zeros(7)
    info = np.zeros(0) if information is None else np.asarray(information, dtype=np.float64)
    score = EffectScore(
        name=name,
        statistic=statistic,
        rank=(3 if information is None else info.size) if rank is None else rank,
        p_value=p_value,
        estimate=np.zeros(3),
        sigma=np.ones(3),
        shift=np.zeros(7),
        shift_sigma=np.zeros(7),
        information=info,
        profiled_information=(
            np.zeros((0, 0)) if information is None else np.diag(np.pad(info, (0, 3 - info.size)))
        ),
    )
    moved = zeros if shift is None else np.asarray(shift, dtype=np.float64)
    return EffectEvidence(
        score=score,
        sensor="imu",
        selected=selected,
        shift_translation_m=moved[:3],
        shift_rotation_rad=moved[3:6],
        shift_time_offset_s=float(moved[6]),
        shift_std=zeros if shift_std is None else shift_std,
        prior_std=zeros if prior_std is None else prior_std,
        prior_sigma=prior_sigma,
    )


def scored_effect(
    name: str, per_dof: float, *, rank: int = 3, selected: bool = True, shift_z_mm: float = 3.0
) -> EffectEvidence:
    """An effect (IMU, or LiDAR by its name) scoring ``per_dof`` per degree of freedom (p = 0
    above 10, else 0.5) whose step moves t_z by ``shift_z_mm``."""
    score = EffectScore(
        name=name,
        statistic=per_dof * rank,
        rank=rank,
        p_value=0.0 if per_dof > 10 else 0.5,
        estimate=np.zeros(rank),
        sigma=np.ones(rank),
        shift=np.zeros(7),
        shift_sigma=np.zeros(7),
    )
    return EffectEvidence(
        score=score,
        sensor="lidar" if name.startswith("lidar") else "imu",
        selected=selected,
        shift_translation_m=np.array([0.0, 0.0, 1e-3 * shift_z_mm]),
        shift_rotation_rad=np.zeros(3),
        shift_time_offset_s=0.0,
    )


def prior_held(joint: EffectScore, spread: float) -> EffectEvidence:
    """A one-coordinate block held to its prior, as every coordinate of the extrinsic sees it:
    its own posterior spread ``spread`` and the joint test's (``joint``: the spread and the move
    to the posterior mean of the blocks held together)."""
    return EffectEvidence(
        score=joint,
        sensor="imu",
        selected=False,
        shift_translation_m=np.zeros(3),
        shift_rotation_rad=np.zeros(3),
        shift_time_offset_s=0.0,
        prior_std=np.full(7, spread),
        joint_prior_var=np.full(7, joint.prior_shift_sigma[0] ** 2),
        joint_prior_shift=np.full(7, joint.prior_shift[0]),
        joint_p_value=joint.p_value,
    )
