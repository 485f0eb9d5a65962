"""Priors a recording cannot check, and effects it takes as exact.

The sigmas of the extrinsic include the spread of every IMU intrinsic the model holds fixed,
known to within its prior (``model.imu_prior``: the residual error of the IMU's factory
calibration; ``model.lidar_prior`` likewise for the LiDAR's, when set). They cover the error
while the IMU is within that prior; whether it is, the data can tell only for an effect large
enough to show in the score test. When the recording would
name an effect only at several times its prior, it cannot check the prior, and a worse IMU
moves the extrinsic beyond its sigma unseen: a 10 s OS1-64 shake with accelerometer scale
errors of -4400 / -2900 / +700 ppm (the default prior 1000 ppm; this bag names the effect from
6600 ppm) passed 3.2 of its sigmas off in t_z. The checks say so beside the sigmas.

An effect held fixed without a prior (a LiDAR's factory calibration unless ``model.lidar_prior``
says otherwise, a bias walk, g-sensitivity) is taken as exact, and no recording can check that;
when an error of it this recording cannot show could move a coordinate by three of its sigmas,
the checks say the result assumes it (:func:`assumed_note`): on 30 s trust bags a per-point
time error below 0.075-0.15 % of the sweep time could move the time offset by 4.4-7.6 sigmas.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.config import lidar_key
from licalib_cli.consistency.distributions import chi2_isf
from licalib_cli.consistency.power import (
    detectable_noncentrality,
    detectable_rms,
    display_size,
)
from licalib_cli.pipeline.crawl import COORDINATES
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, EffectEvidence, model_entries
from licalib_cli.sections import UncheckedPriorCheck

__all__ = [
    "HIDDEN_SHIFT",
    "UNCHECKED_FACTOR",
    "UNCHECKED_WARN",
    "UncheckedPrior",
    "assumed_note",
    "combined_unchecked_priors",
    "listed",
    "prior_owner",
    "unchecked_priors",
    "unchecked_sections",
    "unchecked_text",
    "unchecked_warning",
]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

UNCHECKED_FACTOR = 3.0
"""A prior is unchecked when the recording names its effect only from more than this many times
the prior's sigma (RMS per coordinate, along the direction it determines worst)."""

HIDDEN_SHIFT = 1.0
"""Only priors whose effect, at the size the recording names it from, would move some
coordinate of the extrinsic or time offset by at least this many of its reported sigmas are
listed (the others cannot hide an error that matters)."""

UNCHECKED_WARN = 3.0
"""An unchecked prior whose hidden shift is at least this many sigmas makes the verdict warn:
an effect the recording cannot show could then by itself leave the estimate beyond the three
sigmas a PASS promises, with every check passing. On the diagnose benchmark's seed 4144 (a
10 s VLP-16 shake hardly tilted, the gyro-to-IMU rotation estimated) the accelerometer
misalignment's hidden shift is 4.4 sigmas (roll), and a misalignment of 1.5 times its prior,
below what the recording shows, left the pitch 3.3 of its sigmas off under a PASS (1.2 without
it)."""


@dataclass(frozen=True)
class UncheckedPrior:
    """An effect held fixed whose prior this recording cannot check, or (prior 0) which the
    model takes as exact.

    Attributes:
        effect: its name (``accel_scale``, ``lidar_azimuth``, ...).
        prior: the prior's sigma per coordinate, solver units (0: none, taken as exact).
        detectable: the RMS per coordinate from which the recording names the effect nine times
            in ten along the direction it determines worst, solver units; ``inf`` when some
            direction of it is not determined at all.
        hidden_shift: how far an effect of that size would move the extrinsic or time offset,
            in their reported sigmas (the largest over the coordinates; ``inf`` with
            ``detectable``).
        coordinate: the coordinate it moves most (0-6: t_x, t_y, t_z, rotation about the
            LiDAR's x, y, z, time offset).
    """

    effect: str
    prior: float
    detectable: float
    hidden_shift: float
    coordinate: int = 0

    @property
    def warns(self) -> bool:
        """A prior hidden far enough for the verdict to warn (:data:`UNCHECKED_WARN`); an
        effect taken as exact never warns (nothing says how large it may be), its note says
        what the result assumes."""
        return self.prior > 0.0 and self.hidden_shift >= UNCHECKED_WARN

    @property
    def assumed(self) -> bool:
        """Taken as exact: no prior."""
        return self.prior <= 0.0


def unchecked_priors(held: Sequence[EffectEvidence], sigma: F64) -> list[UncheckedPrior]:
    """The priors among ``held`` (effects held fixed and not covered by their shift) that the
    recording cannot check (:data:`UNCHECKED_FACTOR`) and that could hide an error beyond the
    reported ``sigma`` (:data:`HIDDEN_SHIFT`), and the effects without a prior (taken as exact;
    not those whose size is measured apart from the fit) that could hide one of
    :data:`UNCHECKED_WARN` sigmas; the one that could hide most first.

    An effect ``d`` held at zero moves the estimate by ``A d`` (its shift map) and shows in the
    score test nine times in ten once ``d^T I d`` reaches the non-centrality ``c`` of
    :func:`~licalib_cli.consistency.power.detectable_noncentrality`. Over the effects inside
    that ellipsoid, the largest move of coordinate ``i`` is ``sqrt(c a_i^T I^-1 a_i)``: the
    root of ``c`` times the spread the effect's estimate would add to that coordinate
    (``shift_std``), whatever the prior. The prior's reach (``A P A^T``) times the detectable
    RMS along the worst direction does not give it: it counts directions the recording
    determines well as if they hid as much as the worst, and leaves out that an effect of that
    RMS is ``sqrt(3)`` times as long. On the sample it named a gyro misalignment that could
    hide 2.6 sigmas (0.5 here) and on the diagnose benchmark's seed 4144 an accelerometer
    misalignment that could hide 2.6 (4.4 here: 1.5 times the prior, below what that recording
    shows, moved the pitch by about 2.1 of its sigmas).
    """
    out = []
    for e in held:
        if _sized_apart(e):
            continue
        u = _unchecked(
            e.score.name,
            e.prior_sigma,
            e.shift_std,
            e.score.information,
            int(e.score.estimate.size),
            int(e.score.rank),
            sigma,
        )
        if u is not None:
            out.append(u)
    return sorted(out, key=lambda u: -u.hidden_shift)


def combined_unchecked_priors(
    segments: Sequence[Sequence[EffectEvidence]], sigma: F64, relative_rank: float = 1e-8
) -> list[UncheckedPrior]:
    """:func:`unchecked_priors` for several segments of one recording calibrated together, with
    ``sigma`` the joint sigmas: an effect of the rig shows in their information summed (as the
    combined score test, :func:`~licalib_cli.consistency.score.combined_score`), and the spread
    its estimate would add to the joint estimate is at most the best-determined segment's (the
    smallest ``shift_std``: the summed information narrows it further). ``segments`` holds each
    segment's held effects that its sigmas do not cover by their shift; an effect missing from
    one is left out."""
    by_name: dict[str, list[EffectEvidence]] = {}
    for held in segments:
        for e in held:
            if _sized_apart(e):
                continue
            by_name.setdefault(e.score.name, []).append(e)
    out = []
    for name, effects in by_name.items():
        sizes = {e.score.profiled_information.shape for e in effects}
        if len(effects) != len(segments) or len(sizes) != 1 or 0 in next(iter(sizes)):
            continue
        info = np.sum([e.score.profiled_information for e in effects], axis=0)
        vals = np.linalg.eigvalsh(0.5 * (info + info.T))
        kept = vals[vals > relative_rank * max(float(vals.max(initial=0.0)), 1e-300)]
        u = _unchecked(
            name,
            min(e.prior_sigma for e in effects),
            np.min([e.shift_std for e in effects], axis=0),
            kept,
            int(info.shape[0]),
            int(kept.size),
            sigma,
        )
        if u is not None:
            out.append(u)
    return sorted(out, key=lambda u: -u.hidden_shift)


def _sized_apart(e: EffectEvidence) -> bool:
    """Without a prior but known to within a measurement apart from the fit (the clock drift
    from the stamps against the record times): bounded, so neither unchecked nor assumed."""
    return e.prior_sigma <= 0.0 and bool(np.any(np.asarray(e.prior_std) > 0.0))


def _unchecked(
    name: str,
    prior_sigma: float,
    shift_std: F64,
    information: npt.ArrayLike,
    coordinates: int,
    rank: int,
    sigma: F64,
) -> UncheckedPrior | None:
    finite = np.isfinite(sigma) & (sigma > 0.0)
    if not np.any(finite):
        return None
    spread = np.where(finite, np.asarray(shift_std, dtype=np.float64), 0.0)
    shares = spread / np.where(finite, sigma, 1.0)
    coordinate = int(np.argmax(shares))
    threshold = chi2_isf(EFFECT_P_VALUE, max(rank, 1))
    if rank < coordinates:
        detectable, hidden = float("inf"), float("inf")
    else:
        detectable, _ = detectable_rms(threshold, coordinates, information)
        hidden = float(np.sqrt(detectable_noncentrality(threshold, rank)) * shares[coordinate])
    logger.debug(
        "prior of %s: %.3g, named from %.3g, hidden shift %.2f sigmas of %s",
        name,
        prior_sigma,
        detectable,
        hidden,
        COORDINATES[coordinate],
    )
    if prior_sigma <= 0.0:
        listed = hidden >= UNCHECKED_WARN
    else:
        listed = detectable > UNCHECKED_FACTOR * prior_sigma and hidden >= HIDDEN_SHIFT
    if not listed:
        return None
    return UncheckedPrior(name, max(prior_sigma, 0.0), detectable, hidden, coordinate)


def unchecked_text(items: Sequence[UncheckedPrior]) -> str:
    """``, which this recording cannot check: ...`` for the sigmas' reason; empty without any
    prior among ``items``."""
    items = [u for u in items if not u.assumed]
    if not items:
        return ""
    parts = []
    for u in items:
        prior, unit = display_size(u.effect, u.prior)
        if np.isfinite(u.detectable):
            size, _ = display_size(u.effect, u.detectable)
            parts.append(f"{u.effect} only from {size:.2g} {unit} RMS (prior {prior:.2g})")
        else:
            parts.append(f"{u.effect} not in every direction (prior {prior:.2g} {unit})")
    shown = listed(parts)
    return (
        f", which this recording cannot check: it would show {shown}; the sigmas hold while "
        f"the {_sensors(items)} within those priors"
    )


def prior_owner(effects: Sequence[str]) -> tuple[str, str]:
    """What the priors of ``effects`` (check names) are of, and where they are set: ``("IMU
    intrinsics", "model.imu_prior")``, the LiDAR's, or both."""
    lidar = any(e.startswith("lidar_") for e in effects)
    imu = any(not e.startswith("lidar_") for e in effects) or not effects
    if lidar and imu:
        return "IMU and LiDAR intrinsics", "model.imu_prior and model.lidar_prior"
    if lidar:
        return "LiDAR intrinsics", "model.lidar_prior"
    return "IMU intrinsics", "model.imu_prior"


def listed(parts: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]


def _sensors(items: Sequence[UncheckedPrior]) -> str:
    owner, _ = prior_owner([u.effect for u in items])
    return {"IMU intrinsics": "IMU is", "LiDAR intrinsics": "LiDAR is"}.get(owner, "sensors are")


MODEL_NAMES = {"imu_clock_drift": "clock_drift"}
"""An effect's name in ``model.imu`` where it differs from the score test's (the LiDAR's drop
their ``lidar_`` prefix in ``model.lidar``)."""

PRIOR_KEYS = {"gyro_rotation": "gyro_rotation_deg"}
"""An IMU effect's key in ``model.imu_prior`` where it differs from its name."""

_ADVICE = {
    "gyro_scale": "turned faster about every axis",
    "gyro_misalignment": "turned faster about every axis",
    "gyro_rotation": "tilted by tens of degrees about both horizontal axes",
    "accel_scale": "tilted by tens of degrees about both horizontal axes and accelerated "
    "along every axis",
    "accel_misalignment": "tilted by tens of degrees about both horizontal axes",
    "g_sensitivity": "turned and accelerated along every axis",
}
"""How a recording shows each IMU block (what the advice of :func:`unchecked_warning` asks)."""

_NO_PRIOR = ("gyro_bias_walk", "accel_bias_walk", "imu_clock_drift")
"""Effects without a prior key: the model estimates them or takes them as absent."""


def _prior_key(effect: str) -> str:
    """``model.imu_prior.accel_scale``, ``model.lidar_prior.azimuth_deg``, ...."""
    if effect.startswith("lidar_"):
        return f"model.lidar_prior.{lidar_key(effect.removeprefix('lidar_'))}"
    return f"model.imu_prior.{PRIOR_KEYS.get(effect, effect)}"


def _reach(u: UncheckedPrior) -> str:
    """``it would show X only from D unit RMS, and an effect it cannot show would move C by
    up to H of its sigmas``."""
    where = COORDINATES[u.coordinate]
    _, unit = display_size(u.effect, 0.0)
    if np.isfinite(u.detectable):
        size, _ = display_size(u.effect, u.detectable)
        return (
            f"it would show {u.effect} only from {size:.2g} {unit} RMS, and an effect it "
            f"cannot show would move {where} by up to {u.hidden_shift:.1f} of its sigmas"
        )
    return f"it does not show {u.effect} in every direction, and that direction moves {where}"


def unchecked_warning(items: Sequence[UncheckedPrior]) -> str | None:
    """The verdict's warning when some of ``items`` (:func:`unchecked_priors`, in that order)
    could hide a shift of at least :data:`UNCHECKED_WARN` sigmas; None otherwise. One sentence
    group per sensor, the sensor of the one that could hide most first."""
    warned = [u for u in items if u.warns]
    if not warned:
        return None
    lidar = [u for u in warned if u.effect.startswith("lidar_")]
    imu = [u for u in warned if not u.effect.startswith("lidar_")]
    groups = [g for g in ((imu, lidar) if warned[0] in imu else (lidar, imu)) if g]
    return " ".join(_warning(g) for g in groups)


def _warning(warned: Sequence[UncheckedPrior]) -> str:
    u = warned[0]
    prior, unit = display_size(u.effect, u.prior)
    shown = _reach(u)
    if u.effect == "imu_clock_drift":
        return (
            f"The extrinsic rests on the IMU clock's rate, which this recording cannot check: "
            f"{shown}. Add clock_drift to model.imu, or synchronise the clocks."
        )
    names = [w.effect for w in warned]
    named = listed(names)
    them = "them" if len(names) > 1 else "it"
    lidar = u.effect.startswith("lidar_")
    whose = "the LiDAR's factory calibration" if lidar else "the IMU's own calibration"
    subject, known = f"{whose} of {named}", f"{whose} is known to keep {them} well below that"
    if names == ["lidar_point_time"]:
        subject = "the per-point times of the LiDAR's driver (lidar_point_time)"
        known = "the driver's per-point times are known to be well within that"
    _, section = prior_owner(names)
    of = f" for {u.effect}" if len(names) > 1 else ""
    how = None if lidar else _ADVICE.get(u.effect)
    record = f"Record with the rig {how}, or estimate {them}" if how else f"Estimate {them}"
    zero = " and ".join(_prior_key(n) for n in names)
    return (
        f"The extrinsic rests on {subject} ({section}{of}: {prior:.2g} {unit}), which this "
        f"recording cannot check: {shown}. {record} ({model_entries(names)}), which replaces "
        f"the prior by what the data say; if {known}, set {zero} to 0 and the result assumes "
        f"{them} exact."
    )


def assumed_note(items: Sequence[UncheckedPrior]) -> str | None:
    """The checks' note on the effects among ``items`` the result takes as exact though an
    error of them this recording cannot show could move a coordinate by
    :data:`UNCHECKED_WARN` of its sigmas; None without any. A note, not a warning: nothing
    says how large such an error is; set its prior and the sigmas and the verdict judge it."""
    assumed = [u for u in items if u.assumed]
    if not assumed:
        return None
    parts = []
    for u in assumed:
        where = COORDINATES[u.coordinate]
        if np.isfinite(u.detectable):
            size, unit = display_size(u.effect, u.detectable)
            parts.append(
                f"{u.effect} (an error below {size:.2g} {unit} RMS could move {where} by up "
                f"to {u.hidden_shift:.1f} of its sigmas)"
            )
        else:
            parts.append(f"{u.effect} (not shown in every direction; it moves {where})")
    names = [u.effect for u in assumed]
    keyed = [n for n in names if n not in _NO_PRIOR]
    give = (
        f", or give its size per coordinate in {' or '.join(_prior_key(n) for n in keyed)}, "
        "which puts it in the sigmas and lets the verdict judge it"
        if keyed
        else ""
    )
    return (
        f"The result takes as exact what the model holds fixed without a prior and this "
        f"recording cannot show: {listed(parts)}. Where one may be that large, estimate it "
        f"({model_entries(names)}){give}."
    )


def unchecked_sections(items: Sequence[UncheckedPrior]) -> tuple[UncheckedPriorCheck, ...]:
    """``items`` as the result file's ``consistency.unchecked_priors``."""
    out = []
    for u in items:
        prior, unit = display_size(u.effect, u.prior)
        size, _ = display_size(u.effect, u.detectable)
        out.append(
            UncheckedPriorCheck(
                name=u.effect,
                unit=unit,
                prior=prior,
                detectable=size,
                coordinate=COORDINATES[u.coordinate],
                hidden_shift_sigmas=u.hidden_shift,
                warns=u.warns,
            )
        )
    return tuple(out)
