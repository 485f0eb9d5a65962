"""Spinning or non-repetitive: what a LiDAR's beam field means, and the beams the model uses.

A spinning LiDAR's ``ring`` numbers beams of fixed elevation: the LiDAR model
(:mod:`licalib_cli.models.lidar`) places a point from its range, its azimuth and its beam's
nominal elevation, and per-beam intrinsics correct each beam. A non-repetitive scanner (a
Livox: Mid-360, Avia, ...) numbers its lasers in a ``line`` field, and each line traces a curve
over much of the field of view: a line has no elevation, and the nominal point of a line's median
elevation lies metres from the point. Taken as rings, the lines made the range noise measured
along each beam 46 cm instead of 1 cm (second differences across elevations), the association
thresholds metres wide and a sinusoid that passes 0.7 mm off in a spinning layout end 6 mm and
0.8 ms off, WARN.

So the beam field is classified first (:func:`scan_pattern`: the spread of the elevations
within each beam, :mod:`licalib_cli.io.beam_spread`), and a non-repetitive scanner's points are
grouped into elevation bins of :data:`BIN_DEG` that serve as the model's beams
(:func:`elevation_beams`): a point's nominal elevation is then its bin's, within half a bin of
its own, so the model's ray is the point's within 0.05 deg and the driver's residual (the model
gap) is at most 9 mm at 10 m, fixed with the point. Such beams have no intrinsics of their own:
the model's per-beam blocks are refused (:func:`check_model`) and the checks do not test them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError
from licalib_cli.geometry.vectors import elevations
from licalib_cli.io.beam_spread import SPREAD_DEG
from licalib_cli.measurements import LidarScan
from licalib_cli.pipeline.settings import LIDAR_COLUMNS

__all__ = [
    "BIN_DEG",
    "SPINNING",
    "ScanPattern",
    "check_model",
    "elevation_beams",
    "scan_pattern",
    "with_scan_pattern",
]

F64 = npt.NDArray[np.float64]

BIN_DEG = 0.1
"""Width of a non-repetitive scanner's elevation bins, deg: the model's ray lies within half of
it of the point's (9 mm across the ray at 10 m, which the model gap keeps)."""

Kind = Literal["spinning", "non_repetitive"]


@dataclass(frozen=True)
class ScanPattern:
    """What the beam field means.

    Attributes:
        kind: ``spinning`` (rings of fixed elevation) or ``non_repetitive`` (lines).
        spread_deg: the beams' elevation spread (:data:`SPREAD_DEG`); NaN when not measured.
        source: ``data`` or ``config`` (``lidar.scan_pattern``).
    """

    kind: Kind
    spread_deg: float
    source: Literal["data", "config"]

    @property
    def non_repetitive(self) -> bool:
        """Whether the beams are a non-repetitive scanner's lines."""
        return self.kind == "non_repetitive"

    def evidence(self) -> str:
        """What it rests on, for messages: ``elevations spread 14.2 deg within a line`` or
        ``lidar.scan_pattern``."""
        if not np.isfinite(self.spread_deg):
            return "lidar.scan_pattern"
        unit = "line" if self.non_repetitive else "ring"
        return f"elevations spread {self.spread_deg:.1f} deg within a {unit}"


SPINNING = ScanPattern("spinning", float("nan"), "data")
"""A spinning LiDAR's pattern, as assumed where no data were read."""


def scan_pattern(spread_deg: float, cfg: CalibConfig) -> ScanPattern:
    """The configured ``lidar.scan_pattern``, or the data's: lines when the beams' elevations
    spread more than :data:`~licalib_cli.io.beam_spread.SPREAD_DEG` (``spread_deg``, the
    layout's :attr:`~licalib_cli.io.cloud_layout.CloudLayout.elevation_spread_deg`)."""
    configured = cfg.lidar.scan_pattern
    if configured != "auto":
        return ScanPattern(configured, float("nan"), "config")
    kind: Kind = "non_repetitive" if spread_deg > SPREAD_DEG else "spinning"
    return ScanPattern(kind, spread_deg, "data")


def check_model(cfg: CalibConfig, pattern: ScanPattern) -> None:
    """Refuse per-beam intrinsics in the model of a non-repetitive scanner.

    Raises:
        ConfigError: ``model.lidar`` lists a per-beam block (``--intrinsics lidar`` or
            ``all`` set them) and the scanner is non-repetitive.
    """
    if not pattern.non_repetitive:
        return
    per_beam = [name for name in cfg.model.lidar if name in LIDAR_COLUMNS]
    if not per_beam:
        return
    field = cfg.lidar.ring_field or "line"
    msg = (
        f"The LiDAR is a non-repetitive scanner ({pattern.evidence()}): its '{field}' field "
        f"numbers lasers that sweep many elevations, not beams with intrinsics of their own, so "
        f"model.lidar's {', '.join(per_beam)} cannot be estimated; calibrate without LiDAR "
        "intrinsics (--intrinsics imu or none, or remove them from model.lidar)."
    )
    raise ConfigError(msg)


def elevation_beams(scans: tuple[LidarScan, ...]) -> tuple[tuple[LidarScan, ...], F64]:
    """A non-repetitive scanner's points grouped into elevation bins of :data:`BIN_DEG`, the
    bins numbered from the lowest as beams, and each bin's nominal elevation (its points'
    median), rad.

    Returns:
        The scans with every ``ring`` replaced by its points' bins, and the (B,) nominal
        elevations (bins without points get their centre).
    """
    elev = [np.degrees(elevations(s.xyz)) for s in scans]
    lowest = min((float(e.min()) for e in elev if e.size), default=0.0)
    edge = np.floor(lowest / BIN_DEG) * BIN_DEG
    bins = [np.floor((e - edge) / BIN_DEG).astype(np.int64) for e in elev]
    num = max((int(b.max()) + 1 for b in bins if b.size), default=1)
    if num > np.iinfo(np.int16).max:
        msg = "elevation bins overflow the beam index"
        raise ValueError(msg)
    all_bins = np.concatenate(bins) if bins else np.zeros(0, dtype=np.int64)
    all_elev = np.concatenate(elev) if elev else np.zeros(0)
    order = np.argsort(all_bins, kind="stable")
    sorted_bins, sorted_elev = all_bins[order], all_elev[order]
    bounds = np.searchsorted(sorted_bins, np.arange(num + 1))
    centre = edge + (np.arange(num) + 0.5) * BIN_DEG
    phi = np.array(
        [
            float(np.median(sorted_elev[bounds[i] : bounds[i + 1]]))
            if bounds[i + 1] > bounds[i]
            else centre[i]
            for i in range(num)  # one median per bin (a few hundred), not per point
        ]
    )
    binned = tuple(replace(s, ring=b.astype(np.int16)) for s, b in zip(scans, bins, strict=True))
    return binned, np.radians(phi)


def with_scan_pattern(cfg: CalibConfig, pattern: ScanPattern) -> CalibConfig:
    """``cfg`` with ``lidar.scan_pattern`` ``non_repetitive`` when the data (or the config) say
    so (what the fits build their free parameters from); ``cfg`` itself otherwise."""
    if not pattern.non_repetitive or cfg.lidar.scan_pattern == pattern.kind:
        return cfg
    lidar = cfg.lidar.model_copy(update={"scan_pattern": pattern.kind})
    return cfg.model_copy(update={"lidar": lidar})
