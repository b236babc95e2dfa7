"""``stereocli stages``: every registered stage with its parameters (and traits with -v)."""

from __future__ import annotations

import click

from . import options


@click.command("stages")
@click.argument("pattern", required=False, default="*")
@click.option("--kind", type=click.Choice(["preprocess", "cost", "aggregation", "optimizer", "refinement"]),
              help="Only stages of this kind.")
@click.option("--format", "fmt", type=click.Choice(["text", "json", "markdown"]), default="text", show_default=True,
              help="markdown: the reference page docs/methods.md is generated with this.")
@click.option("--long", "long_", is_flag=True, help="Print each stage's full documentation.")
@options.verbose
@click.pass_context
def stages_cmd(ctx, pattern, kind, fmt, long_):
    """List registered stages (optionally matching an fnmatch PATTERN) and their parameters.

    With -v, also each stage's traits: what the pipeline knows about it (reads the cost
    volume, fills holes, fuses with WTA, memory per volume cell, ...).
    """
    import fnmatch
    import json

    from .. import registry
    from ..matching import stages as _stages  # noqa: F401  (registers the built-in stages)

    chosen = [s for s in registry.stages(kind) if fnmatch.fnmatch(s.name, pattern)]
    show_traits = options.verbosity(ctx) >= 1
    if fmt == "markdown":
        click.echo(registry.markdown_reference(chosen), nl=False)
        return
    if fmt == "json":
        out = [{"kind": s.kind, "name": s.name, "summary": s.summary, "doc": s.doc,
                "traits": s.traits.describe(),
                "params": [{"name": p.name, "type": p.type_name, "default": p.default, "unit": p.unit,
                            "range": p.describe_range(), "help": p.help} for p in s.param_specs()]}
               for s in chosen]
        click.echo(json.dumps(out, indent=2, default=list))
        return
    current = None
    for s in chosen:
        if s.kind != current:
            current = s.kind
            click.echo(click.style(f"\n[{s.kind}]", bold=True))
        click.echo(f"  {s.name}: {s.summary}")
        if long_ and s.doc != s.summary:
            for line in s.doc.splitlines()[1:]:
                click.echo(f"      {line.strip()}")
        for p in s.param_specs():
            click.echo(f"      {p.name} ({_param_line(p)}): {p.help}")
        if show_traits:
            for line in s.traits.describe():
                click.echo(f"      [trait] {line}")


def _param_line(p) -> str:
    default = list(p.default) if isinstance(p.default, tuple) else p.default
    unit = f" {p.unit}" if p.unit else ""
    rng = f" in {p.describe_range()}" if p.describe_range() else ""
    return f"{p.type_name}{rng}, default {default}{unit}"
