"""``--set KEY=VALUE`` config overrides shared by the benchmarks (e.g. a denser final round:
``--set surfels.final_points_per_scan=15000 --set surfels.max_points=1500000``)."""

from __future__ import annotations

import argparse
from typing import Any

import yaml


def _override(item: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--set``: the dotted config key and its YAML value."""
    key, sep, value = item.partition("=")
    if not sep or not key.strip():
        msg = f"expected KEY=VALUE (e.g. surfels.final_points_per_scan=8000), got {item!r}"
        raise argparse.ArgumentTypeError(msg)
    return key.strip(), yaml.safe_load(value)


def add_set_option(p: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` (repeatable): ``args.set`` is a list of (dotted key, value)."""
    p.add_argument(
        "--set",
        action="append",
        default=[],
        type=_override,
        metavar="KEY=VALUE",
        help="config override, e.g. surfels.final_points_per_scan=15000 (repeatable; null "
        "unsets an optional key)",
    )


def load_with(overrides: dict[str, Any]) -> Any:
    """The default config with ``overrides`` (dotted keys; None sets a key to null), as
    ``licalib calibrate --set`` gives them."""
    from licalib_cli.config import load_config

    return load_config(None, settings=overrides)
