"""Generic nonlinear least-squares solver: parameter blocks on manifolds, residual blocks,
sparse assembly, Levenberg-Marquardt with a Schur complement and a truncated-SVD calibration
update. Knows nothing about splines or sensors; see :mod:`.problem` for the residual interface.
"""

from __future__ import annotations

from licalib_cli.solver.lm import (
    IterationSummary,
    LMParams,
    SolverReport,
    Step,
    compute_step,
    solve,
)
from licalib_cli.solver.loss import CauchyLoss, HuberLoss, Loss
from licalib_cli.solver.parameters import (
    ParameterBlock,
    local,
    retract,
    s2_basis,
    s2_retraction_jacobian,
)
from licalib_cli.solver.problem import (
    DenseJacobian,
    Evaluation,
    Layout,
    Linearization,
    Problem,
    ResidualBlock,
    ResidualEval,
    SparseJacobian,
    dense_to_coo,
)
from licalib_cli.solver.schur import SchurSystem, schur_complement

__all__ = [
    "CauchyLoss",
    "DenseJacobian",
    "Evaluation",
    "HuberLoss",
    "IterationSummary",
    "LMParams",
    "Layout",
    "Linearization",
    "Loss",
    "ParameterBlock",
    "Problem",
    "ResidualBlock",
    "ResidualEval",
    "SchurSystem",
    "SolverReport",
    "SparseJacobian",
    "Step",
    "compute_step",
    "dense_to_coo",
    "local",
    "retract",
    "s2_basis",
    "s2_retraction_jacobian",
    "schur_complement",
    "solve",
]
