"""``stereocli warmup``: compile the matching kernels ahead of the first run."""

from __future__ import annotations

import os

import click

from . import options


@click.command("warmup")
@options.config_files
@options.sets
@click.option("--all-presets", is_flag=True, help="Every bundled preset (with --set applied to each).")
@click.option("-j", "--jobs", type=click.IntRange(1, 64), default=None,
              help="Processes compiling at once (default: the number of cores, at most two per config).")
@options.verbose
@click.pass_context
def warmup_cmd(ctx, config_files, sets, all_presets, jobs):
    """Compile the kernels a matching config uses, so the first `match` starts at once.

    Numba compiles each kernel the first time it runs and caches it on disk beside the
    installed package (or in NUMBA_CACHE_DIR); this runs the config on small synthetic pairs,
    on several processes at once. Use it when building a Docker image or a CI cache. Without
    -c, the default preset; each -c PRESET|FILE is a config of its own (with --set applied).

    \b
    Examples:
      stereocli warmup
      stereocli warmup -c fast -c accurate
      stereocli warmup --all-presets --jobs 2
    """
    import time

    from ..config import preset_names
    from ..matching.config import build_config
    from ..matching.warmup import warm_up
    from ..process import notify_compilation

    if all_presets:
        configs = {name: build_config([name], sets) for name in preset_names()}
    elif config_files:
        configs = {name: build_config([name], sets) for name in config_files}
    else:
        configs = {"default": build_config([], sets)}
    jobs = jobs or min(os.cpu_count() or 1, 2 * len(configs))
    quiet = options.verbosity(ctx) < 0

    def report(label: str, task: str, seconds: float) -> None:
        if not quiet:
            click.echo(f"{label}: {task} ready ({seconds:.1f} s)", err=True)

    notify_compilation(None)  # compiling is what this command is for
    t0 = time.perf_counter()
    warm_up(configs, jobs=jobs, report=report)
    if not quiet:
        click.echo(f"compiled kernels for {', '.join(configs)} in {time.perf_counter() - t0:.1f} s "
                   f"({jobs} process{'es' if jobs > 1 else ''})", err=True)
