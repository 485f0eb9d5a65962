"""Does the fitted model explain the data? Noise measured from the data, residual statistics.

Numeric only (no I/O): the pipeline's checks stage supplies residuals and features and turns
these statistics into findings and a verdict.
"""

from licalib_cli.consistency.noise import NoiseEstimate, imu_noise, line_range_noise, range_noise
from licalib_cli.consistency.patterns import (
    Chi2,
    Pattern,
    group_pattern,
    normalised_chi2,
    regression_pattern,
)
from licalib_cli.consistency.score import (
    EffectScore,
    EffectSelection,
    explained_shares,
    measured_shift,
    score_effects,
    select_effects,
)

__all__ = [
    "Chi2",
    "EffectScore",
    "EffectSelection",
    "NoiseEstimate",
    "Pattern",
    "explained_shares",
    "group_pattern",
    "imu_noise",
    "line_range_noise",
    "measured_shift",
    "normalised_chi2",
    "range_noise",
    "regression_pattern",
    "score_effects",
    "select_effects",
]
