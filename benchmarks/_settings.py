"""``--set KEY=VALUE`` config overrides shared by the benchmarks (e.g. a denser final round:
``--set surfels.final_points_per_scan=15000 --set surfels.max_points=1500000``)."""

from __future__ import annotations

import argparse
from pathlib import Path
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


def load_with(overrides: dict[str, Any], workdir: Path) -> Any:
    """The default config with ``overrides`` (dotted keys). ``load_config`` reads an override
    of None as "not given", so the keys set to null go through a config file in ``workdir``."""
    from licalib_cli.config import load_config

    nulls = [k for k, v in overrides.items() if v is None]
    if not nulls:
        return load_config(None, overrides)
    tree: dict = {}
    for key in nulls:
        *sections, leaf = key.split(".")
        node = tree
        for name in sections:
            node = node.setdefault(name, {})
        node[leaf] = None
    path = workdir / "null_settings.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(tree))
    return load_config(path, overrides)
