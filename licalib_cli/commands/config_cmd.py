"""``licalib config dump``: print the resolved configuration."""

from __future__ import annotations

from pathlib import Path

import typer

from licalib_cli.commands.options import SetOption, settings_of
from licalib_cli.config import dump_config, load_config

app = typer.Typer(help="Inspect configuration files.", no_args_is_help=True)


@app.command("dump")
def dump(
    config: Path | None = typer.Option(None, "--config", "-c", help="YAML config to resolve."),
    settings: SetOption = None,
) -> None:
    """Print the resolved configuration (defaults filled in) as YAML."""
    typer.echo(dump_config(load_config(config, settings=settings_of(settings))), nl=False)
