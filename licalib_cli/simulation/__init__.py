"""Synthetic LiDAR-IMU data with exact ground truth (the paper's Sec. VI simulation and more).

``simulate(spec, out_dir)`` writes a bag and ``truth.yaml``; the generators give the same data in
memory. Conventions: ``T_imu_lidar`` maps LiDAR points into the IMU frame; quaternions
``[x, y, z, w]``; ``t_imu = t_lidar + time_offset_s``; stamps are int64 ns.
"""

from __future__ import annotations

from licalib_cli.simulation.effects import EFFECT_SIZES, Effect, EffectSize
from licalib_cli.simulation.ground_truth import SimulationSetup, build_setup
from licalib_cli.simulation.imu import ImuTruth, generate_imu
from licalib_cli.simulation.lidar import ScanTruth, SimulatedScan, generate_scans, num_scans
from licalib_cli.simulation.lidar_models import LidarModel, lidar_model
from licalib_cli.simulation.scenarios import ScenarioMotion, figure8, make_motion, sinusoid
from licalib_cli.simulation.simulate import (
    ProgressCallback,
    SimulationOutput,
    build_truth,
    simulate,
)
from licalib_cli.simulation.spec import (
    IntrinsicsMode,
    LidarKind,
    LidarStamp,
    Mounting,
    Scenario,
    SimulationSpec,
)
from licalib_cli.simulation.trajectories import EulerTrajectory, Signal, TrajectoryState
from licalib_cli.simulation.world import World, default_world

__all__ = [
    "EFFECT_SIZES",
    "Effect",
    "EffectSize",
    "EulerTrajectory",
    "ImuTruth",
    "IntrinsicsMode",
    "LidarKind",
    "LidarModel",
    "LidarStamp",
    "Mounting",
    "ProgressCallback",
    "ScanTruth",
    "Scenario",
    "ScenarioMotion",
    "Signal",
    "SimulatedScan",
    "SimulationOutput",
    "SimulationSetup",
    "SimulationSpec",
    "TrajectoryState",
    "World",
    "build_setup",
    "build_truth",
    "default_world",
    "figure8",
    "generate_imu",
    "generate_scans",
    "lidar_model",
    "make_motion",
    "num_scans",
    "simulate",
    "sinusoid",
]
