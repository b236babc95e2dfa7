"""``stereocli config``: inspect the effective matching configuration."""

from __future__ import annotations

import click

from . import options


@click.group("config")
def config_group():
    """Inspect matching configurations and presets."""


@config_group.command("show")
@options.config_files
@options.sets
def show_cmd(config_files, sets):
    """Print the effective config (defaults < --config files < --set) as YAML."""
    from ..matching.config import build_config

    cfg = build_config(config_files, sets)
    click.echo("# sources: " + ", ".join(cfg.sources))
    click.echo(cfg.to_yaml(), nl=False)


@config_group.command("presets")
def presets_cmd():
    """List the bundled presets (usable as --config NAME)."""
    from ..config import preset_dir, preset_names

    for name in preset_names():
        first = (preset_dir() / f"{name}.yaml").read_text().splitlines()[0].lstrip("# ")
        click.echo(f"{name}: {first}")
