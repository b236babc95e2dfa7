"""``stereocli demo OUTDIR``: the whole chain on the bundled samples, as a user would type it.

Each step is the real subcommand invoked with the arguments printed above it, so the demo
doubles as a worked example of the command line.
"""

from __future__ import annotations

import shlex
from pathlib import Path

import click

from . import options


def find_samples(explicit: str | None) -> Path | None:
    """The samples folder: --samples, ./samples, or the one beside the source checkout."""
    candidates = [Path(explicit)] if explicit else [Path("samples"), Path(__file__).resolve().parents[2] / "samples"]
    for c in candidates:
        if (c / "scenes").is_dir() and (c / "rig").is_dir():
            return c
    if explicit:
        from ..errors import DataError

        raise DataError(f"{explicit}: not a samples folder (expected scenes/ and rig/; see samples/generate.py)")
    return None


@click.command("demo")
@click.argument("outdir", type=click.Path(file_okay=False))
@click.option("--samples", "samples_dir", type=click.Path(file_okay=False),
              help="Samples folder (default: ./samples, else generated into OUTDIR/samples).")
@click.option("-c", "--config", "config_files", multiple=True, metavar="FILE|PRESET",
              help="Matching config for the match step.")
@options.verbose
@click.pass_context
def demo_cmd(ctx, outdir, samples_dir, config_files):
    """Run calibrate -> rectify -> match -> triangulate -> eval on the samples and print the scores.

    Outputs go to OUTDIR (replaced if it exists from an earlier demo).
    """
    from .main import cli

    out = Path(outdir)
    samples = find_samples(samples_dir)
    if samples is None:
        samples = out / "samples"
        click.echo(f"# no samples folder found: generating them into {samples}", err=True)
        from ..synth.samples import generate_samples

        generate_samples(samples, log=lambda m: click.echo(m, err=True))
    truth = samples / "rig" / "truth.yml"
    square = _square_size(truth)
    config_args = [a for c in config_files for a in ("-c", c)]
    steps = [
        # the rendered rig is in metres
        ["calibrate", samples / "rig", "-o", out / "calib.yml", "--pattern", "9x6", "--square", f"{square:g}m",
         "--overwrite"],
        ["rectify", samples / "raw" / "scene1", "--calib", out / "calib.yml", "-o", out / "rectified", "--overwrite"],
        ["match", samples / "scenes", out / "rectified", "-o", out / "disparity", "--overwrite", "--viz", *config_args],
        ["triangulate", out / "disparity", "-o", out / "clouds", "--overwrite"],
        ["eval", out / "disparity", samples / "scenes"],
    ]
    for step in steps:
        args = [str(a) for a in step]
        click.echo(click.style("$ stereocli " + " ".join(shlex.quote(a) for a in args), bold=True), err=True)
        code = cli.main(args=args, prog_name="stereocli", standalone_mode=False)
        if isinstance(code, int) and code != 0:
            ctx.exit(code)
    click.echo(f"# demo outputs in {out}", err=True)


def _square_size(truth: Path) -> float:
    import cv2

    fs = cv2.FileStorage(str(truth), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode("square_size")
        return float(node.real()) if not node.empty() else 1.0
    finally:
        fs.release()
