"""Options shared by several subcommands, defined once."""

from __future__ import annotations

import click

overwrite = click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
skip_existing = click.option("--skip-existing", is_flag=True, help="Skip items whose outputs already exist (resume).")
dry_run = click.option("--dry-run", is_flag=True, help="Print the plan as JSON and write nothing.")
jobs = click.option("-j", "--jobs", type=click.IntRange(1, 256), default=1, show_default=True,
                    help="Items processed in parallel (process pool); outputs do not depend on it.")
scheduler = click.option(
    "--scheduler", metavar="tcp://HOST:PORT|local", default=None,
    help="Run items on a Dask cluster (needs pip install \"stereocli[dask]\"); 'local' starts a LocalCluster "
         "of --jobs worker processes (default 2). Workers must see the same input and output paths.")
retries = click.option("--retries", type=click.IntRange(0, 100), default=0, show_default=True,
                       help="Run a failed item again up to N more times (any executor).")
output_format = click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text",
                             show_default=True, help="Report format on stdout.")
config_files = click.option("-c", "--config", "config_files", multiple=True, metavar="FILE|PRESET",
                            help="YAML config file or bundled preset name (repeatable; later wins).")
sets = click.option("-s", "--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE",
                    help="Override one config value (repeatable; beats --config).")


def batch(func):
    """The options of every batch subcommand: --overwrite, --skip-existing, --dry-run, --jobs,
    --scheduler, --retries (in that order in --help)."""
    for option in reversed((overwrite, skip_existing, dry_run, jobs, scheduler, retries)):
        func = option(func)
    return func


def _add_verbosity(delta: int):
    def callback(ctx: click.Context, _param: click.Parameter, value: int) -> None:
        root = ctx.find_root()
        root.ensure_object(dict)
        root.obj["verbosity"] = root.obj.get("verbosity", 0) + delta * value

    return callback


def verbose(func):
    """Counted -v/-q accepted after the subcommand too (``stereocli match ... -v``)."""
    func = click.option("-v", "--verbose", count=True, expose_value=False, callback=_add_verbosity(1),
                        help="More output (-v details, -vv tracebacks).")(func)
    return click.option("-q", "--quiet", count=True, expose_value=False, callback=_add_verbosity(-1),
                        help="Less output.")(func)


def verbosity(ctx: click.Context) -> int:
    """The counted -v minus -q of the root group (0 = normal)."""
    root = ctx.find_root()
    return (root.obj or {}).get("verbosity", 0)
