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
    """List the bundled presets (usable as --config NAME), each with its whole first sentence."""
    import re
    import textwrap

    from ..config import preset_names, preset_summary

    for name in preset_names():
        summary = re.sub(r"^[\w ]{0,40}? preset: ", "", preset_summary(name))  # the name is printed already
        click.echo(textwrap.fill(f"{name}: {summary}", width=100, subsequent_indent="    ", break_on_hyphens=False))
