"""What one step of the model selection records (:mod:`licalib_cli.pipeline.diagnose`): the
candidate effects, the gap of a sensor, the step itself, and why a significant effect that was
not added did not pay."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from scipy import optimize

from licalib_cli.pipeline import CalibrationRun
from licalib_cli.pipeline.fitcheck import CANDIDATES, EFFECT_P_VALUE
from licalib_cli.pipeline.twin import Twin

__all__ = [
    "CANDIDATES",
    "COORDINATE_PREFIX",
    "GAP_NOISE_SIGMAS",
    "LIDAR_SUFFIX",
    "DiagnosisStep",
    "Gap",
    "Unpaid",
    "closed_share",
    "data_to_pay",
    "unpaid_effect",
]

COORDINATE_PREFIX = {
    "gyro_scale": "imu.gyro_scale.",
    "gyro_misalignment": "imu.gyro_misalignment.",
    "gyro_rotation": "imu.gyro_rotation.",
    "accel_scale": "imu.accel_scale.",
    "accel_misalignment": "imu.accel_misalignment.",
    "g_sensitivity": "imu.gyro_g_sensitivity.",
    "gyro_bias_walk": "imu.gyro_bias_drift.",
    "accel_bias_walk": "imu.accel_bias_drift.",
    "imu_clock_drift": "ext.time_drift",
    "lidar_point_time": "lidar.point_time_scale",
}
LIDAR_SUFFIX = {
    "lidar_range_offset": ".drho",
    "lidar_range_scale": ".s",
    "lidar_elevation": ".dphi",
    "lidar_azimuth": ".dtheta",
    "lidar_vertical_offset": ".V",
    "lidar_horizontal_offset": ".H",
}


GAP_NOISE_SIGMAS = 3.0
"""A gap counts (and its shrink is measured) above this many of its noise sigmas."""


@dataclass(frozen=True)
class Gap:
    """How far one sensor's residuals are from what a model that explains them leaves.

    Attributes:
        sensor: ``gyro``, ``accelerometer`` or ``lidar``.
        chi2_per_sample: residual sum of squares over the noise variance, per residual.
        expected: the analytic value a model that explains the data leaves (below 1 for the
            IMU: the trajectory spline absorbs some of its noise).
        rms: residual RMS in the sensor's unit.
        map_entropy: mean map entropy of the fit's last round (LiDAR), nats.
        twin_chi2_per_sample: the same on the fit's twin recordings (NaN without a twin).
        twin_spread: 1-sigma of that figure (from the twins' spread).
        twin_rms: the twin's residual RMS.
        samples: residuals behind ``chi2_per_sample``.
    """

    sensor: str
    chi2_per_sample: float
    expected: float
    rms: float
    map_entropy: float = float("nan")
    twin_chi2_per_sample: float = float("nan")
    twin_spread: float = float("nan")
    twin_rms: float = float("nan")
    samples: int = 0

    @property
    def sigma(self) -> float:
        """1-sigma of :attr:`excess` from noise alone: the measured chi-square per sample
        varies by ``sqrt(2 reference / samples)`` between recordings, the twin's by its spread.
        """
        if self.samples <= 0:
            return float("nan")
        spread = self.twin_spread if math.isfinite(self.twin_spread) else 0.0
        return math.sqrt(2.0 * max(self.reference, 0.0) / self.samples + spread**2)

    @property
    def reference(self) -> float:
        """What the fitted model itself would leave: the twin's chi-square per sample, or the
        analytic ``expected`` without a twin."""
        if math.isfinite(self.twin_chi2_per_sample):
            return self.twin_chi2_per_sample
        return self.expected

    @property
    def reference_source(self) -> str:
        """``twin`` or ``analytic``."""
        return "twin" if math.isfinite(self.twin_chi2_per_sample) else "analytic"

    @property
    def excess(self) -> float:
        """``chi2_per_sample - reference`` (the gap; about 0 or below when explained)."""
        return self.chi2_per_sample - self.reference


@dataclass(frozen=True)
class DiagnosisStep:
    """One candidate tried.

    Attributes:
        effect: its name (:data:`CANDIDATES`).
        statistic: score test statistic before it was added (tested against the estimated
            coordinates only).
        dof: its degrees of freedom.
        p_value: the test's p-value.
        delta_bic: BIC with the effect minus without (negative: the effect is worth it).
        kept: whether the effect stays in the model.
        estimate: coordinate name -> (value, 1-sigma) after the refit (``inf``: undetermined).
        gap_before: the effect's sensor before the refit.
        gap_after: the same after it.
        moved_translation_m: how far the refit moved the translation.
        moved_rotation_deg: ... the rotation.
        moved_time_offset_s: ... the time offset.
        not_told_apart: rivals refitted with it that this bag does not tell apart from it (each
            one's score test with the other freed is not significant): the data show an effect
            of this kind, not which of them it is.
        rival_delta_bic: BIC of the effect minus that of its rival on the same data (negative:
            it fits better; NaN without a rival), see
            :func:`~licalib_cli.pipeline.rivals.rival_delta_bic`.
        held: the effect's coordinates the refit could not estimate (mostly in directions the
            data determine worse than their characteristic scale, which the truncated SVD holds
            near where they started): their sigma is that scale, not a measurement, and the BIC
            sees no gain from them.
        before: the fit the effect was tested on.
        after: the refit with the effect.
        after_twin: the twin recordings of the refit.
        dropped_for: the effects added after it that made it redundant (the backward check
            dropped it: :func:`drop_redundant`); ``kept`` is then False.
        drop_delta_bic: the BIC with it minus without it on the final fit's data when it was
            dropped (positive), NaN otherwise.
        bic_log_n: ``ln n`` of its BIC penalty (``n`` the residuals of its sensor): what each
            of its coordinates costs; NaN when not computed.
        rival_named: the rival refitted with it that was picked in its place (empty when it
            was the pick, or had no rival).
        final_p_value: its score test's p-value on the final fit when it is not in the final
            model (NaN otherwise): above :data:`EFFECT_P_VALUE`, the effects added after it
            explain what it showed.
        spread: for a per-beam effect whose free numbers did not pay, the spread across beams
            of its refit as one random effect (:mod:`licalib_cli.consistency.spread`, solver
            units; NaN when not tried). Kept so, ``delta_bic`` stays that of the free numbers
            and ``estimate``, the gaps and the moves are the spread's refit's.
        spread_delta_bic: the BIC change of that refit (one parameter, the spread; NaN when
            not tried).
        share_before: when the final model holds other effects too and this step closed less
            than :data:`SHARE_BELOW` of its sensor's gap, that sensor's gap on the final model
            refitted without this effect (:func:`share_of`); None otherwise.
        share_after: ... and on the final fit, against the same twin.
        pieces: for a bias walk, the number of equal pieces of the segment over which its bias
            is linear (1: one linear drift; more when finer pieces paid their BIC,
            :mod:`licalib_cli.pipeline.walk_pieces`); the estimate, the gaps and the moves are
            that refit's.
        linear_delta_bic: with more than one piece, the BIC change of the one-drift refit (the
            pieces' is ``delta_bic``); NaN otherwise.
        expected_size: when its refit held coordinates its score test put far above their
            characteristic scale, the size per coordinate (solver units) it was refitted
            expecting (``model.expected_size``, :mod:`licalib_cli.pipeline.effect_size`); NaN
            when not tried. Kept so, the estimate, the gaps, the moves and ``delta_bic`` are
            that refit's.
        held_delta_bic: with ``expected_size``, the BIC change of the refit at the built-in
            scale (NaN otherwise).
        sized_delta_bic: with ``expected_size``, the BIC change of the refit expecting it.
        rival_of: the step's leading candidate when this one was refitted as its rival (it
            explains most of the leader's score: :func:`~licalib_cli.pipeline.rivals.rivals_of`);
            empty for the leader and a step without rivals.
        rival_share: with ``rival_of``, the share of the leader's score it explains when freed
            with it (NaN otherwise).
        retried_after: the effect this one lost to as its rival at an earlier step, when it
            was tried again once that effect was kept (its test then conditional on it:
            :class:`~licalib_cli.pipeline.rivals.CandidatePool`); empty otherwise.
    """

    effect: str
    statistic: float
    dof: int
    p_value: float
    delta_bic: float
    kept: bool
    estimate: dict[str, tuple[float, float]]
    gap_before: Gap
    gap_after: Gap
    moved_translation_m: float
    moved_rotation_deg: float
    moved_time_offset_s: float
    not_told_apart: tuple[str, ...] = ()
    rival_delta_bic: float = float("nan")
    held: tuple[str, ...] = ()
    before: CalibrationRun | None = field(default=None, repr=False, compare=False)
    after: CalibrationRun | None = field(default=None, repr=False, compare=False)
    after_twin: Twin | None = field(default=None, repr=False, compare=False)
    dropped_for: tuple[str, ...] = ()
    drop_delta_bic: float = float("nan")
    bic_log_n: float = float("nan")
    rival_named: str = ""
    final_p_value: float = float("nan")
    spread: float = float("nan")
    spread_delta_bic: float = float("nan")
    share_before: Gap | None = None
    share_after: Gap | None = None
    pieces: int = 1
    linear_delta_bic: float = float("nan")
    expected_size: float = float("nan")
    held_delta_bic: float = float("nan")
    sized_delta_bic: float = float("nan")
    rival_of: str = ""
    rival_share: float = float("nan")
    retried_after: str = ""

    @property
    def unpaid(self) -> Unpaid | None:
        """Why a significant effect was not added (None unless its refit did not pay, it was
        the pick among its rivals, and the final fit still shows it: a rival picked in its
        place, or an effect added later, explains its score otherwise)."""
        if self.kept or self.dropped_for or self.rival_named or not self.delta_bic >= 0.0:
            return None
        if self.final_p_value >= EFFECT_P_VALUE:
            return None
        return unpaid_effect(
            self.delta_bic, self.dof, len(self.estimate), self.bic_log_n, self.p_value
        )

    @property
    def shrink(self) -> float:
        """Fraction of the sensor's gap the effect closed (1: all; NaN without a gap, or with
        one below :data:`GAP_NOISE_SIGMAS` times its noise, which no refit can be seen to
        close: the score test is the evidence of such an effect)."""
        return closed_share(self.gap_before, self.gap_after)

    @property
    def share(self) -> float:
        """Fraction of its sensor's gap that the effect closes with the final model's other
        effects in (:attr:`share_before` -> :attr:`share_after`, as :attr:`shrink`); NaN when
        not measured (:data:`SHARE_BELOW`) or without such a gap.

        :attr:`shrink` measures the effect when it was added, against whatever the model then
        lacked: a per-beam elevation added before a gyro-to-IMU rotation of 4.5 deg closed 15 %
        of a LiDAR gap that was mostly the rotation's (the trajectory the gyro bent), and the
        rotation, added next, the rest.
        """
        if self.share_before is None or self.share_after is None:
            return float("nan")
        return closed_share(self.share_before, self.share_after)


def closed_share(before: Gap, after: Gap) -> float:
    """Fraction of ``before``'s excess that ``after`` no longer has (NaN when that excess is
    within :data:`GAP_NOISE_SIGMAS` of its noise)."""
    if not before.excess > GAP_NOISE_SIGMAS * before.sigma:
        return float("nan")
    return 1.0 - max(after.excess, 0.0) / before.excess


@dataclass(frozen=True)
class Unpaid:
    """A significant effect whose refit did not pay its BIC penalty, in terms a user can act on.

    Attributes:
        coordinates: its free coordinates (each costs ``log_n`` in the BIC).
        log_n: ``ln n``, ``n`` the residuals of its sensor.
        gain: how much the refit lowered the sum of squares (``coordinates * log_n`` minus its
            BIC change).
        sigmas_each: how far each coordinate is from nominal on average, in its sigmas (how
            well the bag shows it): ``sqrt((gain - dof) / dof)``, the refit's gain beyond what
            fitting noise with ``dof`` directions gives, spread over them.
        sigmas_to_pay: what a coordinate needs to pay its penalty, ``sqrt(log_n - 1)`` sigmas
            (its term of the gain is ``1 + (value / sigma)^2``).
        data_factor: how many times this bag's information about the effect (the points or
            samples that see it) it needs before it pays (:func:`data_to_pay`); ``inf``: the
            refit gained nothing beyond noise.
    """

    coordinates: int
    log_n: float
    gain: float
    sigmas_each: float
    sigmas_to_pay: float
    data_factor: float


def data_to_pay(gain: float, dof: int, coordinates: int, log_n: float) -> float:
    """The smallest ``m >= 1`` with ``dof + m (gain - dof) >= coordinates (log_n + ln m)``.

    An effect of fixed size seen by ``m`` times the points or samples: the part of the refit's
    gain beyond noise (``gain - dof``, the non-centrality) grows ``m`` times, the noise part
    stays ``dof``, and the BIC penalty grows with ``ln (m n)``. (A longer recording of the same
    motion gives that only while the points per scan are kept: ``surfels.max_points`` caps a
    round's points.) ``inf`` when nothing is beyond noise
    or more than a million times the data would be needed.
    """
    signal = gain - dof
    if signal <= 0.0 or coordinates <= 0:
        return float("inf")

    def short(m: float) -> float:
        return dof + m * signal - coordinates * (log_n + math.log(m))

    if short(1.0) >= 0.0:
        return 1.0
    # convex in m, least at coordinates / signal: from there on it only grows
    lo = max(1.0, coordinates / signal)
    hi = 2.0 * lo
    while short(hi) < 0.0:
        hi *= 2.0
        if hi > 1e6:
            return float("inf")
    return float(optimize.brentq(short, lo, hi))


def unpaid_effect(
    delta_bic: float, dof: int, coordinates: int, log_n: float, p_value: float
) -> Unpaid | None:
    """:class:`Unpaid` for a significant effect (``p_value`` below
    :data:`~licalib_cli.pipeline.fitcheck.EFFECT_P_VALUE`) whose refit changed the BIC by
    ``delta_bic >= 0``; None otherwise or without the penalty's ``log_n``."""
    if not (delta_bic >= 0.0 and p_value < EFFECT_P_VALUE and math.isfinite(log_n)):
        return None
    if coordinates <= 0 or dof <= 0:
        return None
    gain = coordinates * log_n - delta_bic
    return Unpaid(
        coordinates=coordinates,
        log_n=log_n,
        gain=gain,
        sigmas_each=math.sqrt(max(gain - dof, 0.0) / dof),
        sigmas_to_pay=math.sqrt(max(log_n - 1.0, 0.0)),
        data_factor=data_to_pay(gain, dof, coordinates, log_n),
    )
