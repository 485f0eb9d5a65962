"""Typed sections of the result file (schema v1), beyond the extrinsic and the intrinsics.

Every section ``calibrate`` writes is a frozen dataclass with ``to_dict`` / ``from_dict``; the
YAML keys are the field names. Numbers are plain floats (rounded for the file), vectors are
tuples. A section a file does not carry is ``None`` in :class:`~licalib_cli.results.
CalibrationResult`.

=================  =============================================================================
section            content
=================  =============================================================================
``uncertainty``    1-sigma of the extrinsic and the time offset (``inf``: not observable)
``observability``  scaled singular values, the TSVD threshold, unobservable directions in words
``verdict``        ``pass`` / ``warn`` / ``fail`` and one sentence per finding
``consistency``    the fit checks: noise, normalised residuals and patterns per sensor, score
                   tests of the effects the model holds fixed, split-half agreement, how the
                   sigmas were inflated
``initialization`` where the initial guess came from
``fit``            rounds, points, residual RMS, convergence
``recording``      the data used
``factory_extrinsic`` the sensor's factory extrinsic (Ouster metadata) and the calibration's
                   difference from it, when the bag carries one
``provenance``     licalib version, bag fingerprint, creation time
``segments``       multi-segment calibration: each segment's own estimate next to the joint one
``extra_terms``    the terms beyond the paper's model that the model estimated (clock drift, bias
                   drifts, per-point time scale) and the stamp at which the time offset holds
=================  =============================================================================
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

import numpy as np

from licalib_cli.filetypes import FileValueError, field_types, joined, typed

__all__ = [
    "SPLIT_LABELS",
    "AddedEffect",
    "Consistency",
    "EffectCheck",
    "ExtraTerms",
    "FactoryExtrinsicSection",
    "FitSection",
    "InitializationSection",
    "IntrinsicsUncertainty",
    "ModelInfo",
    "Observability",
    "PatternCheck",
    "Provenance",
    "RecordingSection",
    "Section",
    "SegmentEstimate",
    "SegmentsSection",
    "SensorCheck",
    "SplitHalf",
    "Uncertainty",
    "UncheckedPriorCheck",
    "VerdictSection",
    "p_is",
    "p_text",
]

T = TypeVar("T")

P_FLOOR = 1e-300
"""Smallest p-value printed as a number: below it the chi-square tail underflows (returns 0)."""


def p_text(p: float, digits: int = 2) -> str:
    """A p-value as printed: ``digits`` significant digits, or ``< 1e-300`` where it underflows
    (a statistic so far in the tail that, printed as a number, it would read as a probability of
    exactly zero)."""
    return f"< {P_FLOOR:.0e}" if p < P_FLOOR else f"{p:.{digits}g}"


def p_is(p: float, digits: int = 2) -> str:
    """``p = 0.12``, or ``p < 1e-300`` where the p-value underflows (:func:`p_text`)."""
    text = p_text(p, digits)
    return f"p {text}" if text.startswith("<") else f"p = {text}"


def _num(x: Any, digits: int = 6) -> Any:
    """A float for YAML: ``significant`` digits, ``inf``/``nan`` kept."""
    if x is None:
        return None
    v = float(x)
    if not math.isfinite(v) or v == 0.0:
        return v
    return float(f"{v:.{digits}g}")


def _nums(xs: Any, digits: int = 6) -> list[Any]:
    return [_num(x, digits) for x in xs]


def _plain(value: Any, digits: int | None) -> Any:
    if hasattr(value, "to_dict"):
        return value.to_dict()
    if isinstance(value, tuple | list):
        return [_plain(v, digits) for v in value]
    if isinstance(value, float | np.floating):
        return _num(value, digits) if digits else float(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


class Section:
    """``to_dict`` over the dataclass fields, in order, and ``from_dict`` back.

    ``_digits`` rounds floats to that many significant digits (None: as they are; statistics
    set it, stamps and clock offsets must not). ``from_dict`` checks every value against its
    field's annotation (:mod:`licalib_cli.filetypes`): a field holding another section (or a
    tuple of them) reads that section.
    """

    _digits: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            f.name: _plain(getattr(self, f.name), self._digits)
            for f in fields(self)  # type: ignore[arg-type]
        }

    @classmethod
    def from_dict(cls: type[T], d: dict[str, Any], key: str = "") -> T:
        """Read the section from its mapping ``d`` (keys it does not know are left aside).

        Args:
            d: the mapping.
            key: its dotted key in the file, for the messages.

        Raises:
            FileValueError: a required key is missing, or a value is not of its field's type.
        """
        kwargs: dict[str, Any] = {}
        for name, (hint, required) in field_types(cls).items():
            if name in d:
                kwargs[name] = typed(d[name], hint, joined(key, name))
            elif required:
                raise FileValueError(joined(key, name), "is missing")
        return cls(**kwargs)


@dataclass(frozen=True)
class Uncertainty(Section):
    """1-sigma of the extrinsic (``inf`` where not observable).

    Attributes:
        translation_std_m: per IMU-frame axis, m.
        rotation_std_deg: per LiDAR-frame axis, deg.
        time_offset_std_s: s.
    """

    translation_std_m: tuple[float, float, float]
    rotation_std_deg: tuple[float, float, float]
    time_offset_std_s: float

    def vector(self) -> np.ndarray:
        """(7,) the sigmas as translation (m), rotation (rad), time offset (s)."""
        return np.concatenate(
            [
                np.asarray(self.translation_std_m, dtype=np.float64),
                np.radians(np.asarray(self.rotation_std_deg, dtype=np.float64)),
                [float(self.time_offset_std_s)],
            ]
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "translation_std_m": [float(x) for x in self.translation_std_m],
            "rotation_std_deg": [float(x) for x in self.rotation_std_deg],
            "time_offset_std_s": float(self.time_offset_std_s),
        }


@dataclass(frozen=True)
class Observability(Section):
    """Spectrum of the scaled calibration information, the truncated directions and the
    weakly determined ones (below the threshold, at least ``weak_floor`` of it, estimated,
    their sigma reported; ``weak_floor`` 0: none can be)."""

    scaling: str
    threshold: float
    singular_values: tuple[float, ...]
    unobservable: tuple[str, ...] = ()
    weakly_determined: tuple[str, ...] = ()
    weak_floor: float = 0.1


@dataclass(frozen=True)
class VerdictSection(Section):
    """``pass`` / ``warn`` / ``fail`` and one sentence per finding."""

    status: str
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class PatternCheck(Section):
    """Structure of one sensor's residuals against a feature.

    Attributes:
        feature: e.g. ``angular rate``, ``beam``, ``time within sweep``.
        explained: share of the residual variance the feature explains.
        p_value: F test.
        size: RMS of the explained part, in the residuals' unit.
        material: whether it counts against the fit.
    """

    _digits = 6

    feature: str
    explained: float
    p_value: float
    size: float
    material: bool = False


@dataclass(frozen=True)
class SensorCheck(Section):
    """How well the model explains one sensor.

    Attributes:
        sensor: ``gyro``, ``accelerometer`` or ``lidar``.
        unit: unit of ``rms`` and ``noise``.
        noise: noise standard deviation the fit was weighted with (per axis, or the median per
            beam for the LiDAR's point-to-plane distance along the ray).
        noise_source: ``config`` or ``data`` (measured, see docs/checks.md).
        chi2_per_sample: sum of squared residuals over the noise variance, per scalar residual
            (about 1 when the model explains the data).
        rms: residual RMS.
        samples: scalar residuals.
        status: ``ok`` or ``excess`` (residuals larger than the noise).
        patterns: structure left in the residuals.
    """

    _digits = 6

    sensor: str
    unit: str
    noise: tuple[float, ...]
    noise_source: str
    chi2_per_sample: float
    rms: float
    samples: int
    status: str
    patterns: tuple[PatternCheck, ...] = ()


@dataclass(frozen=True)
class EffectCheck(Section):
    """Score test of one effect the model holds fixed.

    Attributes:
        name: e.g. ``gyro_scale`` (issue names of the effects).
        sensor: ``imu`` or ``lidar``.
        statistic: score statistic (chi-square under "no such effect").
        dof: its degrees of freedom.
        p_value: significance.
        shift_translation_m: how the translation would move if the effect were estimated.
        shift_rotation_deg: how the rotation would move (LiDAR axes).
        shift_time_offset_s: how the time offset would move.
        selected: added by the forward selection (significant beyond the stronger effects;
            the statistic of an effect not selected is conditional on the selected ones).
        material: selected (or measured) and moving the extrinsic by more than its sigma.
        covered: the reported sigmas include its shift (material, or hinted at: p below
            ``inflation.COVER_P_VALUE``) and the spread its estimate would add.
        refitted: the shift was measured by refitting with the effect estimated (an effect
            the data show beyond doubt), not only predicted from one linear step.
        measured: the shift is that of holding the effect at zero at a size measured apart
            from the fit, whatever its score test says (the IMU clock drift, at the rate of the
            stamps against the record times when that rate is material).
    """

    _digits = 6

    name: str
    sensor: str
    statistic: float
    dof: int
    p_value: float
    shift_translation_m: tuple[float, float, float]
    shift_rotation_deg: tuple[float, float, float]
    shift_time_offset_s: float
    selected: bool = False
    material: bool = False
    covered: bool = False
    refitted: bool = False
    measured: bool = False


@dataclass(frozen=True)
class SplitHalf(Section):
    """The extrinsic estimated on the two halves of the segment, compared.

    Attributes:
        status: ``agree``, ``disagree`` or ``not run``.
        reason: why it was not run, or which coordinate disagrees most.
        halves_s: duration of each half, s.
        max_z: largest difference of a coordinate over its combined sigma.
        chi2: chi-square of the difference with the halves' combined covariance.
        dof: its degrees of freedom.
        p_value: probability of a chi-square at least this large if the halves agree.
        difference_translation_m: second half minus first.
        difference_rotation_deg: second half relative to the first, about the LiDAR axes.
        difference_time_offset_s: second half minus first.
        compared: the coordinates both halves determine, which the chi-square compares
            (``translation.x`` ... ``rotation.z`` about the LiDAR axes, ``time_offset``); a half
            that does not determine one holds it, so it says nothing about a change there.
    """

    _digits = 6

    status: str
    reason: str = ""
    halves_s: float = 0.0
    max_z: float = 0.0
    chi2: float = 0.0
    dof: int = 0
    p_value: float = 1.0
    difference_translation_m: tuple[float, ...] = ()
    difference_rotation_deg: tuple[float, ...] = ()
    difference_time_offset_s: float = 0.0
    compared: tuple[str, ...] = ()

    def compared_text(self) -> str:
        """``""`` when every coordinate was compared (or the list is unknown), else which were:
        ``"only t_y, t_z, time offset: a half does not determine the others"``."""
        if not self.compared or len(self.compared) == len(SPLIT_LABELS):
            return ""
        names = ", ".join(SPLIT_LABELS.get(n, n) for n in self.compared)
        return f"only {names}: a half does not determine the others"


SPLIT_LABELS = {
    "translation.x": "t_x",
    "translation.y": "t_y",
    "translation.z": "t_z",
    "rotation.x": "roll (LiDAR x)",
    "rotation.y": "pitch (LiDAR y)",
    "rotation.z": "yaw (LiDAR z)",
    "time_offset": "time offset",
}
"""How the checks name each split-half coordinate (``SplitHalf.compared``'s names) to a user."""


@dataclass(frozen=True)
class UncheckedPriorCheck(Section):
    """A block held fixed whose prior (``model.imu_prior``, ``model.lidar_prior``) the
    recording cannot check: it would name the block's effect only from several times the prior.
    With ``prior`` 0, an effect held fixed without a prior, taken as exact, that could move a
    coordinate by at least three of its sigmas unseen (listed, never warns).

    Attributes:
        name: the block (``accel_scale``, ``lidar_azimuth``, ...).
        unit: the unit of ``prior`` and ``detectable`` (``ppm``, ``deg``, ...).
        prior: the prior's sigma per coordinate (0: none, taken as exact).
        detectable: the RMS per coordinate from which the recording names the effect nine
            times in ten (``inf``: some direction of it not at all).
        coordinate: the coordinate an effect of that size moves most (``t_x`` ... ``yaw``,
            ``time offset``).
        hidden_shift_sigmas: how far it moves that coordinate, in its reported sigmas.
        warns: far enough for the verdict to warn (at least 3 sigmas).
    """

    _digits = 4

    name: str
    unit: str
    prior: float
    detectable: float
    coordinate: str
    hidden_shift_sigmas: float
    warns: bool = False

    @property
    def assumed(self) -> bool:
        """Taken as exact: held without a prior (``prior`` 0)."""
        return self.prior <= 0.0


@dataclass(frozen=True)
class Consistency(Section):
    """Whether the fitted model explains the data (the fit checks).

    Attributes:
        sensors: one check per sensor.
        effects: score tests of the effects the model holds fixed.
        split_half: the two halves compared.
        inflation: how the reported sigmas were enlarged, one sentence each (empty: as
            computed).
        unchecked_priors: the blocks held fixed whose priors the recording cannot check and
            whose error could move the extrinsic by more than its sigma unseen, and those taken
            as exact (prior 0) whose error could move it by three sigmas unseen, the one that
            could move it most first.
    """

    sensors: tuple[SensorCheck, ...] = ()
    effects: tuple[EffectCheck, ...] = ()
    split_half: SplitHalf = field(default_factory=lambda: SplitHalf("not run"))
    inflation: tuple[str, ...] = ()
    unchecked_priors: tuple[UncheckedPriorCheck, ...] = ()

    @property
    def assumed_exact(self) -> tuple[str, ...]:
        """The effects the result takes as exact though the recording cannot check them (the
        ``unchecked_priors`` without a prior), as the verdict names them."""
        return tuple(u.name for u in self.unchecked_priors if u.assumed)

    def rows(self) -> list[tuple[str, str, str, bool]]:
        """One row per fit check, as the console table and the report show them:
        ``(check, figure, outcome, warn)``; ``warn`` marks an outcome to highlight."""
        names = {"gyro": "gyro", "accelerometer": "accelerometer", "lidar": "LiDAR"}
        out = []
        for s in self.sensors:
            patterns = [p.feature for p in s.patterns if p.material]
            misfit = s.status != "ok" or bool(patterns)
            outcome = "misfit" if misfit else "ok"
            if patterns:
                outcome += " (depends on " + ", ".join(patterns) + ")"
            figure = f"chi2/sample {s.chi2_per_sample:.2f}, noise {_noise_text(s)}"
            out.append((f"{names.get(s.sensor, s.sensor)} residuals", figure, outcome, misfit))
        material = [e for e in self.effects if e.material]
        if material:
            worst = max(material, key=lambda e: e.statistic)
            size = (
                "its size from the stamps"
                if worst.measured
                else f"score {worst.statistic:.0f} (dof {worst.dof})"
            )
            figure = (
                f"{worst.name}: {size}, moves "
                f"{1e3 * float(np.linalg.norm(worst.shift_translation_m)):.1f} mm / "
                f"{float(np.linalg.norm(worst.shift_rotation_deg)):.3f} deg"
            )
            out.append(("effects held fixed", figure, ", ".join(e.name for e in material), True))
        elif self.effects:
            strongest = min(self.effects, key=lambda e: e.p_value)
            figure = f"strongest {strongest.name}: {p_is(strongest.p_value)}"
            hinted = [e.name for e in self.effects if e.covered]
            outcome = (
                "hinted at: " + ", ".join(hinted) + " (shift in the sigmas)"
                if hinted
                else "none that moves the extrinsic"
            )
            out.append(("effects held fixed", figure, outcome, False))
        sh = self.split_half
        if sh.status == "not run":
            out.append(("split halves", sh.reason, "not run", True))
        else:
            figure = (
                f"{sh.halves_s:.1f} s each, chi-square {sh.chi2:.1f} on {sh.dof} "
                f"({p_is(sh.p_value)})"
            )
            compared = sh.compared_text()
            if compared:
                figure += f"; {compared}"
            agree = sh.status == "agree"
            out.append(("split halves", figure, "agree" if agree else "disagree", not agree))
        priors = [u for u in self.unchecked_priors if not u.assumed]
        assumed = [u for u in self.unchecked_priors if u.assumed]
        for items, label, state in (
            (priors, _priors_label(priors), "unchecked"),
            (assumed, "taken as exact", "assumed"),
        ):
            if not items:
                continue
            # as the result file holds it: a report made from the file says the same
            u = UncheckedPriorCheck.from_dict(items[0].to_dict())
            of = "" if u.assumed else f" (prior {u.prior:.2g})"
            shown = (
                f"{u.name} shows from {u.detectable:.2g} {u.unit}{of}"
                if math.isfinite(u.detectable)
                else f"{u.name} not in every direction{of}"
            )
            more = len(items) - 1
            figure = shown + (f"; {more} more" if more else "")
            outcome = (
                f"{state}: could move {u.coordinate} {u.hidden_shift_sigmas:.1f} sigma"
                if math.isfinite(u.hidden_shift_sigmas)
                else f"{state}: could move {u.coordinate} unseen"
            )
            out.append((label, figure, outcome, u.warns))
        return out


def _priors_label(items: Sequence[UncheckedPriorCheck]) -> str:
    """``IMU priors``, ``LiDAR priors`` or ``priors``: whose priors ``items`` are."""
    lidar = {u.name.startswith("lidar_") for u in items}
    return "priors" if len(lidar) > 1 else ("LiDAR priors" if lidar == {True} else "IMU priors")


def _noise_text(s: SensorCheck) -> str:
    """A sensor's noise level (RMS over axes) in display units, and where it came from."""
    scale, unit = (1e3, "mm") if s.unit == "m" else (1.0, s.unit)
    value = float(np.sqrt(np.mean(np.square(s.noise)))) * scale if s.noise else float("nan")
    return f"{value:.3g} {unit} ({'measured' if s.noise_source == 'data' else s.noise_source})"


@dataclass(frozen=True)
class AddedEffect(Section):
    """An effect ``calibrate`` estimated because the data showed it beyond doubt.

    Attributes:
        effect: its candidate name (``gyro_scale``, ``lidar_range_offset`` ...).
        statistic: its score test on the fit without it.
        dof: the test's degrees of freedom.
        delta_bic: the BIC change of the refit that added it (negative: it paid).
        moved_translation_m: how far that refit moved the translation.
        moved_rotation_deg: ... the rotation.
        moved_time_offset_s: ... the time offset (signed).
        refit: which refit added it (1, 2): effects added together share its BIC change and
            move.
        rival: a candidate that could stand in for it (freed with it, it explained most of its
            score), refitted in its place and compared with it on the same data; empty when
            none was.
        rival_delta_bic: this effect's BIC minus the rival's on the same data (negative: it fit
            better); 0 without a rival.
        not_told_apart: the rival, when the recording does not tell the two apart (neither
            one's score test is significant on the refit with the other): the data show an
            effect of this kind, not which of the two it is.
    """

    _digits = 6

    effect: str
    statistic: float
    dof: int
    delta_bic: float
    moved_translation_m: float
    moved_rotation_deg: float
    moved_time_offset_s: float
    refit: int = 1
    rival: str = ""
    rival_delta_bic: float = 0.0
    not_told_apart: tuple[str, ...] = ()


@dataclass(frozen=True)
class ModelInfo(Section):
    """Which intrinsics were estimated.

    Attributes:
        imu: IMU blocks estimated (``gyro_scale`` ...; names of the config's ``model.imu``).
        lidar: per-beam LiDAR intrinsics estimated (``elevation`` ...).
        gauge_beam: the beam whose angles and offsets were held (the gauge), or -1.
        held_beams: beams with too few points, held at nominal.
        lidar_spread: per-beam intrinsics estimated with a configured spread across beams
            (``model.lidar_spread``, the config's keys and units: ``range_scale``,
            ``elevation_deg`` ...); empty when each took the weak default prior.
        expected_size: blocks estimated at a configured expected size instead of the built-in
            characteristic scale (``model.expected_size``, its keys and units); empty otherwise.
        added: the effects estimated beyond the config's model because the data showed them
            beyond doubt (``model.add_evident_effects``), in the order added.
        undetermined: IMU blocks of the model the recording determined none of: estimated,
            the sigmas include how far holding them at nominal moves the extrinsic.
    """

    imu: tuple[str, ...] = ()
    lidar: tuple[str, ...] = ()
    gauge_beam: int = -1
    held_beams: tuple[int, ...] = ()
    lidar_spread: dict[str, float] = field(default_factory=dict)
    expected_size: dict[str, float] = field(default_factory=dict)
    added: tuple[AddedEffect, ...] = ()
    undetermined: tuple[str, ...] = ()


@dataclass(frozen=True)
class IntrinsicsUncertainty(Section):
    """1-sigma of every estimated intrinsic, by block (``None``: held or not observable).

    ``values`` maps ``gyro_scale``, ``gyro_misalignment``, ``gyro_rotation_deg``,
    ``accel_scale``, ``accel_misalignment``, ``g_sensitivity`` (rad/s per m/s^2, row-major),
    ``elevation_deg``, ``azimuth_deg``, ``vertical_offset_m``, ``horizontal_offset_m``,
    ``range_scale``, ``range_offset_m`` (one entry per beam) to lists of sigmas.
    """

    values: dict[str, tuple[float | None, ...]] = field(default_factory=dict)

    _digits = 4

    def to_dict(self) -> dict[str, Any]:
        return {
            k: [None if (x is None or not math.isfinite(x)) else _num(x, 4) for x in v]
            for k, v in self.values.items()
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], key: str = "") -> IntrinsicsUncertainty:
        return cls(typed(d, dict[str, tuple[float | None, ...]], key))


@dataclass(frozen=True)
class ExtraTerms(Section):
    """The estimates of the terms beyond the paper's model (config ``model.imu`` /
    ``model.lidar``: ``clock_drift``, ``gyro_bias_walk``, ``accel_bias_walk``, ``point_time``),
    written only when the model holds one; their 1-sigma are in ``intrinsics_uncertainty`` under
    the same keys. A term the model does not hold is ``None``.

    With a clock drift ``k`` the time offset changes over the recording::

        t_imu = t_lidar + time_offset_s + k (t_lidar - reference_ns 1e-9)

    so ``extrinsic.time_offset_s`` is the offset at ``reference_ns``; likewise the biases of
    ``imu_intrinsics`` hold at ``reference_ns`` and change by the bias drifts per second.

    Attributes:
        reference_ns: the stamp (the segment's middle) at which the time offset and the biases
            hold, ns: the time offset of a LiDAR stamp equal to it (the formula above), the
            biases of an IMU stamp equal to it.
        clock_drift: ``k``, s/s (``1e-6`` = 1 ppm; positive: the IMU clock runs fast).
        gyro_bias_walk: the gyro bias's drift per axis, rad/s^2; with ``bias_walk_pieces``
            one drift per axis and piece (``x, y, z`` of the first piece, then of the second,
            ...; their sigmas under the same key, in the same order).
        accel_bias_walk: the accelerometer bias's drift per axis (and piece), m/s^3.
        bias_walk_pieces: the number of equal pieces of the segment over which a bias walk is
            linear (``model.bias_walk_piece_s``), written when more than one: the bias is
            continuous, its value at ``reference_ns`` that of ``imu_intrinsics``, and it changes
            by each piece's drift per second within that piece.
        point_time: the fraction by which the per-point times within a sweep are off (a point
            stamped ``tau`` was measured at ``tau - k_point (tau - sweep start)``).
    """

    reference_ns: int
    clock_drift: float | None = None
    gyro_bias_walk: tuple[float, ...] | None = None
    accel_bias_walk: tuple[float, ...] | None = None
    point_time: float | None = None
    bias_walk_pieces: int | None = None

    _digits = 8


@dataclass(frozen=True)
class InitializationSection(Section):
    """Where the initial guess came from."""

    rotation_source: str
    time_offset_source: str
    coarse_time_offset_s: float
    angular_speed_correlation: float | None = None
    hand_eye_conditioning: float | None = None
    translation_source: str = "zero"
    initial_translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class FitSection(Section):
    """The rounds and the last fit.

    Attributes:
        rounds: rounds run (the denser final round included).
        converged: whether the estimate settled before ``schedule.max_rounds``.
        last_change_translation_m: how far the last regular round moved the translation.
        last_change_rotation_deg: ... the rotation.
        last_change_time_offset_s: ... the time offset.
        points: associated points of the last round.
        surfels: surfels of the last round.
        point_rms_m: RMS point-to-plane distance.
        variance_factor: chi-square per degree of freedom of the whole fit.
    """

    rounds: int
    converged: bool
    last_change_translation_m: float
    last_change_rotation_deg: float
    last_change_time_offset_s: float
    points: int
    surfels: int
    point_rms_m: float
    variance_factor: float


@dataclass(frozen=True)
class RecordingSection(Section):
    """The data used.

    Attributes:
        bag: the bag's path as given.
        imu_topic: the IMU topic.
        lidar_topic: the LiDAR topic.
        imu_samples: IMU samples in the segment.
        scans: sweeps in the segment.
        duration_s: length of the segment, s.
        start_ns: first stamp of the segment (IMU clock), ns.
        clock_offset_s: the coarse clock offset ``t_imu - t_lidar`` of the two sensors'
            clocks, measured from stamps and record times before calibrating, s.
        lidar_clock_shift_s: the clock shift added to every LiDAR time before calibrating
            (the clock offset when it is 1 s or more, else 0); the time offset is on top of
            it, s.
    """

    bag: str
    imu_topic: str
    lidar_topic: str
    imu_samples: int
    scans: int
    duration_s: float
    start_ns: int
    clock_offset_s: float
    lidar_clock_shift_s: float
    imu_unreadable_messages: int = 0
    """IMU messages of the segment that could not be read (damaged bag), skipped."""
    lidar_unreadable_messages: int = 0
    """LiDAR messages of the segment that could not be read (damaged bag), skipped."""
    imu_samples_dropped: int = 0
    """IMU samples dropped for NaN or infinite values."""
    scans_skipped: int = 0
    """Clouds of the segment skipped as unusable (empty, corrupt, too few points, ...)."""
    imu_frame: str = ""
    """``header.frame_id`` of the IMU messages ("" when unknown)."""
    lidar_frame: str = ""
    """``header.frame_id`` of the LiDAR messages ("" when unknown)."""
    gravity_turn_deg: float | None = None
    """How far gravity turned in the IMU frame over the segment, deg RMS (the accelerometer's
    0.5 s mean direction; :func:`licalib_cli.inspection.gravity_turn_deg`): tens of degrees
    tell the accelerometer's frame from the extrinsic rotation when the IMU intrinsics are
    estimated. None in results written before it was recorded."""
    clock_rate_ppm: float | None = None
    """How fast the IMU's stamps ran against the LiDAR's, measured from each topic's stamps
    against the recorder's record times before calibrating, ppm (positive: the IMU's fast, as
    ``extra_terms.clock_drift``; :mod:`licalib_cli.io.clock_rate`). None when unknown (too few
    messages, or results written before it was recorded)."""
    clock_rate_sigma_ppm: float | None = None
    """Its 1-sigma, ppm."""


@dataclass(frozen=True)
class FactoryExtrinsicSection(Section):
    """The factory extrinsic the bag carries (Ouster metadata) and how far the calibration
    lies from it.

    Attributes:
        source: where it was read, e.g. ``Ouster metadata on /ouster/metadata``.
        sensor: product line and serial number the metadata names ("" when none).
        cloud_frame: the frame the clouds are in (``os_lidar`` or ``os_sensor``), which the
            factory ``T_imu_lidar`` maps from.
        translation: factory ``t`` (``p_imu = R p_lidar + t``), m.
        rotation_quaternion: factory ``R`` as ``[x, y, z, w]``.
        rotation_rpy_deg: factory ``R`` as roll, pitch, yaw, deg.
        difference_translation_m: calibrated minus factory ``t``, IMU frame, m.
        difference_translation_norm_m: its length, m.
        difference_rotation_deg: angle of ``R_factory^T R_calibrated``, deg.
        difference_rotation_vector_deg: rotation vector of ``R_factory^T R_calibrated``
            (about the LiDAR axes), deg.
    """

    source: str
    sensor: str
    cloud_frame: str
    translation: tuple[float, float, float]
    rotation_quaternion: tuple[float, float, float, float]
    rotation_rpy_deg: tuple[float, float, float]
    difference_translation_m: tuple[float, float, float]
    difference_translation_norm_m: float
    difference_rotation_deg: float
    difference_rotation_vector_deg: tuple[float, float, float]


@dataclass(frozen=True)
class Provenance(Section):
    """Who made the file from what.

    Attributes:
        licalib_version: the version that wrote the file.
        bag_fingerprint: :func:`licalib_cli.pipeline.assemble.bag_fingerprint` of the bag.
        created_utc: when, ISO 8601.
        config_fingerprint: :func:`licalib_cli.config.config_fingerprint` of the resolved
            configuration (segment options included; ``batch`` writes
            :func:`licalib_cli.batch.plan.job_fingerprint`, which adds its segments choice);
            None in files written before it existed (not written then).
    """

    licalib_version: str
    bag_fingerprint: str
    created_utc: str
    config_fingerprint: str | None = None

    def to_dict(self) -> dict[str, Any]:
        out = super().to_dict()
        if self.config_fingerprint is None:
            del out["config_fingerprint"]
        return out


@dataclass(frozen=True)
class SegmentEstimate(Section):
    """One segment of a multi-segment calibration.

    Attributes:
        start_s: start, seconds after the bag start.
        end_s: end, seconds after the bag start.
        translation: the segment's own estimate of ``t`` (calibrated alone), m.
        rotation_rpy_deg: its own rotation, roll/pitch/yaw in degrees.
        time_offset_s: its own time offset, s.
        translation_std_m: its own 1-sigma per IMU axis, m.
        rotation_std_deg: its own 1-sigma per LiDAR axis, deg.
        time_offset_std_s: its own time-offset 1-sigma, s.
        joint_time_offset_s: its time offset in the joint problem, s.
        joint_time_offset_std_s: that time offset's 1-sigma, s.
        disagreement_sigmas: largest difference of its own estimate from the joint one on a
            translation or rotation axis, in its own sigmas.
        disagrees: above the section's threshold.
        verdict: the segment's own verdict.
        started_from: the 1-based segment whose estimate this segment's own calibration
            started from, when its own motion could not give an initial guess (None: it
            started on its own).
    """

    _digits = 9

    start_s: float
    end_s: float
    translation: tuple[float, float, float]
    rotation_rpy_deg: tuple[float, float, float]
    time_offset_s: float
    translation_std_m: tuple[float, float, float]
    rotation_std_deg: tuple[float, float, float]
    time_offset_std_s: float
    joint_time_offset_s: float
    joint_time_offset_std_s: float
    disagreement_sigmas: float
    disagrees: bool
    verdict: str
    started_from: int | None = None


@dataclass(frozen=True)
class SegmentsSection(Section):
    """The segments of a multi-segment calibration (``calibrate --segments``).

    Attributes:
        reference: 1-based segment whose own sections (``recording``, ``fit``,
            ``consistency``, ``initialization``) the file carries.
        disagreement_threshold_sigmas: a segment further than this from the joint estimate
            (in its own sigmas) is flagged.
        segments: one entry per segment, in time order.
    """

    reference: int
    disagreement_threshold_sigmas: float
    segments: tuple[SegmentEstimate, ...] = ()
