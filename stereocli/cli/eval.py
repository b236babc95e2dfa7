"""``stereocli eval``: score disparity maps against ground truth (thin layer over stereocli.evaluate)."""

from __future__ import annotations

import os

import click

from . import options


def _parse_thresholds(_ctx: click.Context, _param: click.Parameter, value: str | None):
    if value is None:
        return None
    try:
        values = tuple(float(v) for v in value.replace(" ", "").split(",") if v)
    except ValueError:
        raise click.BadParameter(f"{value!r} is not a comma-separated list of numbers, e.g. 0.5,1,2,4") from None
    if not values or any(v < 0 for v in values):
        raise click.BadParameter(f"{value!r}: give one or more non-negative thresholds, e.g. 0.5,1,2,4")
    return values


@click.command("eval")
@click.argument("results", type=click.Path(path_type=str))
@click.argument("ground_truth", type=click.Path(path_type=str))
@click.option("--format", "fmt", type=click.Choice(["text", "json", "csv", "markdown"]), default="text",
              show_default=True, help="Report format on stdout.")
@click.option("--dataset", type=click.Choice(["middlebury2014", "middlebury2003", "middlebury2001", "middlebury2005",
                                              "kitti"]),
              default=None, help="Score with this benchmark's rules (default: detected from the ground truth); "
                                 "kitti also reads a lone GT file or a folder of <name>.png GT files.")
@click.option("--thresholds", callback=_parse_thresholds, default=None, metavar="LIST",
              help="Bad-pixel thresholds in px, comma-separated.  [default: 0.5,1,2,4]")
@click.option("--resolution", type=click.Choice(["auto", "F", "H", "Q"]), default="auto", show_default=True,
              help="MiddEval3 resolution of the GT; auto reads trainingQ/H/F from the path, else F.")
@click.option("--threshold-units", type=click.Choice(["full", "native"]), default="full", show_default=True,
              help="full: thresholds and errors in full-resolution px (a Q GT's errors x4, so bad2.0 = "
                   "0.5 px at Q); native: px of the scored grid (unofficial for H/Q GT).")
@click.option("--same-resolution", is_flag=True,
              help="UNOFFICIAL: score at the estimate's size (GT subsampled) instead of upsampling the estimate.")
@click.option("--ndisp", type=options.Finite(min=0, min_open=True), default=None,
              help="Disparity range at the estimate's resolution for clipping [default: calib.txt ndisp; "
                   "none for v2].")
@click.option("--gt-scale", type=options.Finite(min=0, min_open=True), default=None,
              help="v2 8-bit GT scale [default per scene: Tsukuba 16, Venus 8, Teddy/Cones 4; Middlebury "
                   "2005/2006 1, 2 or 3 from the image width].")
@click.option("--error-maps", "error_maps", type=click.Path(file_okay=False, path_type=str), default=None,
              metavar="DIR", help="Write DIR/<scene>/{disparity,gt,error,bad}.png (shared colour scale, legend).")
@click.option("--html", "html_dir", type=click.Path(file_okay=False, path_type=str), default=None, metavar="DIR",
              help="Write DIR/report.html: tables + images, self-contained (base64 PNGs).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=str), default=None,
              help="Also write the report to this file (same format).")
@options.overwrite
@options.jobs
@options.scheduler
@options.retries
@options.verbose
@click.pass_context
def eval_cmd(ctx: click.Context, results: str, ground_truth: str, fmt: str, dataset: str | None,
             thresholds: tuple[float, ...] | None, resolution: str, threshold_units: str, same_resolution: bool,
             ndisp: float | None, gt_scale: float | None, error_maps: str | None, html_dir: str | None,
             output: str | None, overwrite: bool, jobs: int, scheduler: str | None, retries: int) -> None:
    """Score disparity maps against ground truth with the official benchmark rules.

    RESULTS is a disparity file (PFM, 16-bit PNG, npy) or a folder of <scene>/disp0*.pfm
    (+ time.txt), <scene>.pfm or KITTI <name>.png files. GROUND_TRUTH is a GT file, a scene
    folder or a folder of scene folders (Middlebury 2014 / MiddEval3, 2001/2003, 2005/2006) or a
    KITTI 2015 root (disp_noc_0/ and/or disp_occ_0/). Scenes are matched by name, as match names
    its outputs; missing results are failures.

    Scenes are scored in-process, or in parallel with --jobs N (process pool) or --scheduler
    (Dask); the report is the same. --retries re-runs scenes whose scoring crashed.

    Exit codes: 0 all scored, 3 some scenes (or regions) failed, 1 nothing could be scored or a
    single pair failed, 2 bad options.

    \b
    Examples:
      stereocli eval out samples/scenes
      stereocli eval out ../data/trainingQ --format json --jobs 2
      stereocli eval out gt/ --scheduler tcp://127.0.0.1:8786 --retries 1
    """
    from ..errors import DataError, check_outputs_free
    from ..evaluation import EvalOptions, format_table
    from ..io.atomic import write_text
    from ..jobs.evaluate import evaluate

    verbosity = options.verbosity(ctx)
    opts = EvalOptions(
        thresholds=thresholds or EvalOptions.thresholds,
        resolution=resolution,
        threshold_units=threshold_units,
        same_resolution=same_resolution,
        ndisp=ndisp,
        dataset=dataset,
        gt_scale=gt_scale,
        keep_arrays=bool(error_maps or html_dir),
    )
    if output:
        _check_report_path(output, results, ground_truth)
        check_outputs_free([output], overwrite=overwrite)
    report = evaluate(results, ground_truth, options=opts, jobs=jobs, scheduler=scheduler, retries=retries,
                      verbose_errors=verbosity >= 2)
    text = format_table(report, fmt)
    click.echo(text, nl=False)
    if output:
        write_text(output, text)
    if error_maps and report.scenes:
        from ..evaluation.maps import write_error_maps

        written = write_error_maps(report, error_maps, overwrite=overwrite)
        if verbosity > 0:
            click.echo(f"wrote {len(written)} error-map images under {error_maps}", err=True)
    if html_dir and report.scenes:
        from ..evaluation.html import write_html

        path = write_html(report, html_dir, overwrite=overwrite)
        if verbosity >= 0:
            click.echo(f"wrote {path}", err=True)
    if fmt != "text" and verbosity >= 0:
        for f in report.failures:
            click.echo(f"{'Error' if f.get('partial') else 'Failed'}: {f['name']}: {f['message']}", err=True)
    if not report.scenes:
        raise DataError(f"no scene could be scored ({len(report.failures)} failed)")
    ctx.exit(report.exit_code)


#: Files of the inputs that a report written with ``-o`` must never replace.
_DATA_SUFFIXES = (".pfm", ".png", ".npy", ".pgm", ".ppm", ".txt")


def _check_report_path(output: str, results: str, ground_truth: str) -> None:
    """Refuse ``-o`` on a results or ground-truth file (even with ``--overwrite``): the report
    would replace what it scores."""
    from pathlib import Path

    from ..errors import ConfigError

    real = Path(os.path.realpath(output))
    for given in (results, ground_truth):
        root = Path(os.path.realpath(given))
        inside = root.is_dir() and root in real.parents and real.is_file() and real.suffix.lower() in _DATA_SUFFIXES
        if real == root or inside:
            raise ConfigError(f"--output {output} would replace the input {given if real == root else real}; "
                              "write the report elsewhere")
