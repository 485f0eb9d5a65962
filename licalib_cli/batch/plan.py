"""Which bags a batch must calibrate and which it can take from an earlier run.

Results are laid out as ``OUT/<rig>/<bag-stem>.yaml`` (schema v1, as ``calibrate`` writes) with
the resolved config beside each as ``<bag-stem>.config.yaml``. A result is up to date, and its
bag is not calibrated again, when its ``provenance`` holds the fingerprint of the same bag
content and of the same resolved configuration and segments choice (:func:`job_fingerprint`).
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from licalib_cli.batch.inputs import BatchJob
from licalib_cli.config import CalibConfig, config_fingerprint, load_config
from licalib_cli.errors import ConfigError, LicalibError, ManifestError
from licalib_cli.results import CalibrationResult, check_not_an_input

__all__ = ["SUMMARY_FILES", "PlannedBag", "job_fingerprint", "plan"]

logger = logging.getLogger(__name__)

SUMMARY_FILES = ("summary.csv", "rigs.csv")
"""The files a batch writes at the top of its output folder."""


@dataclass(frozen=True)
class PlannedBag:
    """A job with its resolved settings and what to do with it.

    Attributes:
        job: the job.
        cfg: its resolved configuration.
        result_path: ``OUT/<rig>/<stem>.yaml``.
        bag_fingerprint: the bag's content fingerprint.
        config_fingerprint: the fingerprint of the resolved configuration and the segments
            choice (:func:`job_fingerprint`).
        existing: the earlier result, when it is up to date (the bag is not calibrated).
        reason: why it is calibrated: ``new``, ``bag changed``, ``config changed``,
            ``result unreadable``; ``up to date`` when it is not.
    """

    job: BatchJob
    cfg: CalibConfig
    result_path: Path
    bag_fingerprint: str
    config_fingerprint: str
    existing: CalibrationResult | None
    reason: str

    @property
    def config_path(self) -> Path:
        """The resolved config written beside the result."""
        return self.result_path.with_name(self.result_path.stem + ".config.yaml")

    @property
    def label(self) -> str:
        return self.job.label


def plan(
    jobs: Sequence[BatchJob], out_dir: Path, settings: Mapping[str, Any] | None = None
) -> list[PlannedBag]:
    """Resolve every job's configuration and result path, and find the up-to-date results.

    Args:
        jobs: the bags (see :func:`licalib_cli.batch.read_inputs`).
        out_dir: the output folder.
        settings: ``--set`` settings by dotted key, applied over every job's config file (its
            manifest row's options over them).

    Returns:
        One entry per job, in order.

    Raises:
        ConfigError: a config that cannot be used (its own sentence).
        ManifestError: two jobs would write the same result, or a result would overwrite an
            input.
    """
    from licalib_cli.pipeline.assemble import bag_fingerprint

    out_dir = Path(out_dir).absolute()
    configs: dict[tuple[Any, ...], CalibConfig] = {}
    owners: dict[Path, BatchJob] = {}
    inputs = _inputs(jobs)
    planned = []
    for job in jobs:
        key = (job.config, *job.overrides().values())
        if key not in configs:
            configs[key] = _load(job, settings)
        cfg = configs[key]
        result = out_dir / job.rig / f"{job.stem}.yaml"
        other = owners.setdefault(result, job)
        if other is not job:
            msg = (
                f"The bags {other.bag} ({other.source}) and {job.bag} ({job.source}) would both "
                f"write {result}; give them different rig ids in a manifest (column 'rig')."
            )
            raise ManifestError(msg)
        for path in (result, result.with_name(f"{job.stem}.config.yaml")):
            check_not_an_input(path, inputs, f"The batch result {path}")
        entry = PlannedBag(
            job=job,
            cfg=cfg,
            result_path=result,
            bag_fingerprint=bag_fingerprint(job.bag),
            config_fingerprint=job_fingerprint(cfg, job.segments),
            existing=None,
            reason="new",
        )
        planned.append(_against_earlier(entry))
    for name in SUMMARY_FILES:
        check_not_an_input(out_dir / name, inputs, f"The batch summary {out_dir / name}")
    return planned


def job_fingerprint(cfg: CalibConfig, segments: str | None) -> str:
    """What a result's ``provenance.config_fingerprint`` holds in a batch: the resolved
    configuration's fingerprint (as ``calibrate`` writes it) for one segment; with a segments
    choice (normalised, see :func:`~licalib_cli.batch.inputs.normalise_segments`), the first 16
    hex digits of the sha256 of that fingerprint and the choice, so that a changed choice
    calibrates the bag again."""
    base = config_fingerprint(cfg)
    if segments is None:
        return base
    return hashlib.sha256(f"{base}\nsegments: {segments}\n".encode()).hexdigest()[:16]


def _inputs(jobs: Sequence[BatchJob]) -> list[tuple[str, Path | None]]:
    out: list[tuple[str, Path | None]] = []
    for job in jobs:
        out += [("the input bag", job.bag), ("the config file", job.config)]
    return out


def _load(job: BatchJob, settings: Mapping[str, Any] | None) -> CalibConfig:
    try:
        return load_config(job.config, job.overrides(), dict(settings or {}))
    except ConfigError as err:
        # a fault of the config file or of --set is the same for every bag that uses them
        if "--set" in str(err) or (job.config is not None and str(job.config) in str(err)):
            raise
        msg = f"{str(err).rstrip('.')} (for {job.bag}, {job.source})."
        raise ConfigError(msg) from err


def _against_earlier(entry: PlannedBag) -> PlannedBag:
    """The entry with the earlier result when it is up to date, else with the reason."""
    path = entry.result_path
    if not path.exists():
        return entry
    try:
        earlier = CalibrationResult.load(path)
    except LicalibError as err:
        logger.debug("%s: the earlier result is not readable (%s)", entry.label, err)
        return replace(entry, reason="result unreadable")
    prov = earlier.provenance
    if prov is None or prov.bag_fingerprint != entry.bag_fingerprint:
        return replace(entry, reason="bag changed")
    if prov.config_fingerprint != entry.config_fingerprint:
        return replace(entry, reason="config changed")
    return replace(entry, existing=earlier, reason="up to date")
