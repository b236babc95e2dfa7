"""``stereocli stages``: every registered stage with its parameters."""

from __future__ import annotations

import click


@click.command("stages")
@click.argument("pattern", required=False, default="*")
@click.option("--kind", type=click.Choice(["preprocess", "cost", "aggregation", "optimizer", "refinement"]),
              help="Only stages of this kind.")
@click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text", show_default=True)
@click.option("--long", "long_", is_flag=True, help="Print each stage's full documentation.")
def stages_cmd(pattern, kind, fmt, long_):
    """List registered stages (optionally matching an fnmatch PATTERN) and their parameters."""
    import fnmatch
    import json

    from .. import registry

    chosen = [s for s in registry.stages(kind) if fnmatch.fnmatch(s.name, pattern)]
    if fmt == "json":
        out = [{"kind": s.kind, "name": s.name, "summary": s.summary, "doc": s.doc,
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
            default = list(p.default) if isinstance(p.default, tuple) else p.default
            unit = f" {p.unit}" if p.unit else ""
            rng = f" in {p.describe_range()}" if p.describe_range() else ""
            click.echo(f"      {p.name} ({p.type_name}{rng}, default {default}{unit}): {p.help}")
