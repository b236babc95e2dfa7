"""``stereocli rectify``: calibration + pairs -> row-aligned pairs, valid masks, calib.txt."""

from __future__ import annotations

from pathlib import Path

import click

from . import options
from .common import argv, finish_batch, print_json, unpaired_failures
from ..errors import ConfigError as usage_error  # one-line message, exit 2


def _size(text: str | None) -> tuple[int, int] | None:
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise usage_error(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 1280x960") from None
    if w <= 0 or h <= 0:
        raise usage_error(f"--size {text!r}: width and height must be positive")
    return w, h


@click.command("rectify")
@click.argument("inputs", nargs=-1, required=True, type=click.Path())
@click.option("--calib", "calib_path", required=True, type=click.Path(),
              help="Calibration file (OpenCV .yml/.xml/.json, ROS pair, Kalibr camchain).")
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False),
              help="Output folder; each pair writes OUTDIR/<name>/{im0,im1,valid0,valid1}.png + calib.txt.")
@click.option("--alpha", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="0 = crop to valid pixels, 1 = keep every source pixel (black borders, masked).")
@click.option("--size", "size_text", metavar="WxH", help="Rectified image size (default: the calibration's).")
@click.option("--interp", type=click.Choice(["nearest", "linear", "cubic", "lanczos"]), default="linear",
              show_default=True, help="Resampling of the images.")
@click.option("--ndisp", type=click.IntRange(1, 100000), help="ndisp written to calib.txt (default: estimated).")
@click.option("--min-depth", type=click.FloatRange(min=0, min_open=True),
              help="Nearest scene depth (calibration units) for the ndisp estimate = f·B/min_depth.")
@click.option("--check", is_flag=True, help="Also write check.png: side by side, horizontal lines, ROI boxes.")
@options.batch
@options.verbose
@click.pass_context
def rectify_cmd(ctx, inputs, calib_path, outdir, alpha, size_text, interp, ndisp, min_depth, check, overwrite,
                skip_existing, dry_run, jobs, scheduler, retries):
    """Rectify stereo pairs so that epipolar lines are image rows.

    INPUT is a pair of image files, a folder with left/ + right/ subfolders, a folder of
    left*/right* photos (paired by the text after the side word), or scene folders.
    Without --ndisp, calib.txt gets ndisp = f·B / nearest depth (from --min-depth, else the
    nearest calibration board), rounded up to a multiple of 16.

    \b
    Examples:
      stereocli rectify photos/ --calib rig.yml -o rectified --check
      stereocli rectify left.png right.png --calib rig.yml -o out --alpha 1 --size 1280x960
    """
    from ..io.calib import load_calibration
    from ..io.pairs import discover_pairs
    from ..jobs.executors import run_batch
    from ..jobs.rectify import plan_items, rectify_item
    from ..runinfo import RunRecord

    verbosity = options.verbosity(ctx)
    size = _size(size_text)
    load_calibration(calib_path)  # fail fast (exit 1/2) before any work
    pairs, problems = discover_pairs(inputs, side_words=True)
    items = plan_items(pairs, outdir, calib_path=calib_path, alpha=alpha, size=size, interpolation=interp,
                       check=check, ndisp=ndisp, min_depth=min_depth)
    if dry_run:
        print_json([i.as_dict() for i in items])
        return
    for problem in problems:
        click.echo(f"Warning: {problem}", err=True)
    result = run_batch(items, rectify_item, jobs=jobs, overwrite=overwrite, skip_existing=skip_existing,
                       desc="rectify", verbose_errors=verbosity >= 2,
                       scheduler=scheduler, retries=retries)
    record = RunRecord("rectify", argv(), {"calibration": str(calib_path), "alpha": alpha,
                                           "size": list(size) if size else None, "interp": interp})
    code = finish_batch(result, record, Path(outdir) / "run.json", verbosity, unpaired_failures(problems))
    if verbosity >= 1:
        print_json([r.as_dict() for r in result.results])
    ctx.exit(code)
