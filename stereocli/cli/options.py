"""Options shared by several subcommands, defined once."""

from __future__ import annotations

import math

import click

from ..errors import excerpt


class Finite(click.FloatRange):
    """A number that must be finite (NaN passes every range check, and inf is no setting),
    optionally within a range: ``Finite(min=0, min_open=True)``."""

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{excerpt(value, quote=True)} is not a finite number", param, ctx)
        return number

    def _describe_range(self) -> str:
        # --help shows the bounds; without any, nothing (click would print "x<=None").
        return "" if self.min is None and self.max is None else super()._describe_range()

class _NdispType(click.ParamType):
    """A number of disparities in [1, 100000], or ``auto`` (estimate the range from the images)."""

    name = "N|auto"

    def convert(self, value, param, ctx):
        if value is None or isinstance(value, int) or value == "auto":
            return value
        try:
            number = int(str(value))
        except ValueError:
            self.fail(f"{excerpt(value, quote=True)} is neither a whole number nor 'auto'", param, ctx)
        if not 1 <= number <= 100000:
            self.fail(f"{number} is not in the range 1<=x<=100000", param, ctx)
        return number


NDISP = _NdispType()


class _RangeType(click.ParamType):
    """``MIN:MAX``: two finite numbers, MIN below MAX (e.g. ``0:64``, ``-8.5:40``)."""

    name = "MIN:MAX"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        try:
            low, high = (float(v) for v in str(value).split(":"))
        except ValueError:
            self.fail(f"{excerpt(value, quote=True)} is not MIN:MAX (two numbers, e.g. 0:64)", param, ctx)
        if not (math.isfinite(low) and math.isfinite(high)) or low >= high:
            self.fail(f"{excerpt(value, quote=True)}: MIN and MAX must be finite numbers, MIN below MAX", param, ctx)
        return low, high


RANGE = _RangeType()

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
                    help="Override one config value (repeatable; beats --config); listed stages: "
                         "refinement+=STAGE appends, refinement.lr_check+=STAGE inserts before lr_check, "
                         "refinement-=median removes, refinement.median=STAGE replaces.")


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
