"""The ``stereocli`` command group.

Subcommands are imported lazily (only the one that runs is loaded), so ``stereocli --help``
does not pay for numpy, OpenCV or numba imports.
"""

from __future__ import annotations

import importlib
import sys

import click

from .. import __version__

#: command name -> (module under stereocli.cli, attribute, one-line help for --help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "calibrate": ("calibrate", "calibrate_cmd", "Checkerboard pairs -> intrinsics, distortion, R, T and a report."),
    "rectify": ("rectify", "rectify_cmd", "Calibration + pairs -> row-aligned pairs, valid masks, calib.txt."),
    "match": ("match", "match_cmd", "Rectified pairs -> disparity maps (the configurable pipeline)."),
    "triangulate": ("triangulate", "triangulate_cmd", "Disparity + calibration -> depth maps and point clouds."),
    "eval": ("eval", "eval_cmd", "Score disparity maps against ground truth (MiddEval3, v2, KITTI)."),
    "convert-calib": ("calibrate", "convert_calib_cmd", "Convert calibration files between formats."),
    "stages": ("stages", "stages_cmd", "List every registered stage and its parameters."),
    "config": ("config_cmd", "config_group", "Show the effective matching configuration."),
    "demo": ("demo", "demo_cmd", "Run the whole chain on the bundled samples and print the scores."),
    "warmup": ("warmup", "warmup_cmd",
               "Compile the matching kernels ahead of the first run (Docker images, CI caches)."),
}


class LazyGroup(click.Group):
    """A group whose subcommands are imported only when used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module_name, attr, _ = COMMANDS[name]
        module = importlib.import_module(f"stereocli.cli.{module_name}")
        return getattr(module, attr)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # Use the static help lines so --help imports no subcommand module.
        rows = [(name, help_) for name, (_, _, help_) in COMMANDS.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


def _show_versions(ctx: click.Context, _param: click.Parameter, value: bool) -> None:
    if not value or ctx.resilient_parsing:
        return
    from ..runinfo import versions
    from ..runtime.aot import describe

    for name, version in versions().items():
        click.echo(f"{name}: {version}")
    click.echo(f"kernels: {describe()}")
    ctx.exit(0)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="stereocli")
@click.option("--show-versions", is_flag=True, expose_value=False, is_eager=True, callback=_show_versions,
              help="Print Python and dependency versions (for bug reports) and exit.")
@click.option("-v", "--verbose", count=True, help="More output (-v details, -vv tracebacks).")
@click.option("-q", "--quiet", count=True, help="Less output (-q: errors only).")
@click.pass_context
def cli(ctx: click.Context, verbose: int, quiet: int) -> None:
    """Stereo vision on image folders: calibrate, rectify, match, triangulate, eval.

    Disparity is float32 pixels referenced to the left image (x_right = x_left - d);
    invalid pixels are +inf. Run `stereocli demo OUTDIR` to see the whole chain.
    """
    from ..process import keep_freed_memory, notify_compilation, prepare_kernels

    keep_freed_memory()  # process-wide: freed large buffers stay in the process between pairs
    prepare_kernels()  # before numba starts: sleeping idle threads, a faster start
    ctx.ensure_object(dict)
    ctx.obj["verbosity"] = ctx.obj.get("verbosity", 0) + verbose - quiet
    notify_compilation(_on_first_compile(ctx))
    ctx.call_on_close(lambda: notify_compilation(None))  # for this command only


#: Said on stderr when kernels compile (a cache miss: the README's "Start-up and first run").
COMPILE_NOTICE = ("stereocli: compiling the numba kernels that this preset or image type needs beyond those built "
                  "at install, once; later runs load them from the cache")


def _on_first_compile(ctx: click.Context):
    """What to do when kernels compile: say so once, and warm up the first pair's config (at a
    compile during its matching: one during a pair's survey comes before it is known)."""
    said: list[bool] = []

    def on_compile() -> bool:
        if not said:
            said.append(True)
            _compile_notice(ctx)
        return not _warm_up_first_run()  # True: call again at the next compile

    return on_compile


def _compile_notice(ctx: click.Context) -> None:
    """The first kernel of this run has to compile: say so (unless -q)."""
    if ctx.obj.get("verbosity", 0) >= 0:  # -q: errors only
        from ..runtime.aot import missing_build_advice

        advice = missing_build_advice()  # an install that lost its compiled kernels says so here
        click.echo(f"stereocli: {advice}" if advice else COMPILE_NOTICE, err=True)


def _warm_up_first_run() -> bool:
    """When a pair is being matched, compile its whole config on every core first (the run
    then loads its kernels from the cache instead of compiling them one by one); True if it did."""
    pipeline = sys.modules.get("stereocli.matching.pipeline")
    if pipeline is None or pipeline.current_config() is None:
        return False
    from ..matching.warmup import warm_up_first_run

    warm_up_first_run(pipeline.current_config())
    return True


def main(argv: list[str] | None = None) -> None:
    """Console entry point: run the group, map library errors and signals to exit codes, and
    keep third-party output apart (:func:`~stereocli.cli.errors.run_captured`)."""
    from ..process import limit_blas_threads

    limit_blas_threads()  # before any subcommand imports numpy
    from .errors import run_captured

    sys.exit(run_captured(cli, argv))
