"""``stereocli match``: rectified pairs -> disparity maps."""

from __future__ import annotations

from pathlib import Path

import click

from . import options
from .common import print_json, run_batch_command, unpaired_failures


@click.command("match")
@click.argument("inputs", nargs=-1, required=True, type=click.Path())
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False),
              help="Output folder; each pair writes OUTDIR/<name>/disp0.pfm.")
@options.config_files
@options.sets
@click.option("--ndisp", type=options.NDISP, metavar="N|auto",
              help="Number of disparities searched; 'auto' estimates each pair's range from its images "
                   "(default: calib.txt ndisp, else estimated).")
@click.option("--min-disp", type=int, default=None,
              help="Smallest disparity searched, px (default 0; may be negative).")
@click.option("--require-aligned", is_flag=True,
              help="Fail a pair whose rows are not aligned (else a warning): it needs rectifying first "
                   "(rectify --calib, or rectify --uncalibrated).")
@click.option("--png16", "png16_scale", type=options.Finite(min=0, max=65535, min_open=True), default=None,
              metavar="SCALE",
              help="Also write disp0.png as uint16 round(d*SCALE), 0 = invalid (KITTI uses 256).")
@click.option("--npy", is_flag=True, help="Also write disp0.npy (float32).")
@click.option("--viz", is_flag=True, help="Also write disp0_viz.png, an 8-bit colour preview with a colour bar "
                                         "(not data).")
@click.option("--viz-range", "viz_range", type=options.RANGE, metavar="MIN:MAX", default=None,
              help="Disparities (px) at the ends of the --viz colours [default: calib.txt vmin:vmax, else each map's "
                   "1st-99th percentiles]; implies --viz.")
@click.option("--confidence", is_flag=True, help="Also write conf0.pfm, per-pixel confidence in [0, 1].")
@click.option("--right", is_flag=True, help="Also write disp1.pfm, the right-view disparity.")
@click.option("--keep-invalid", is_flag=True, help="Skip hole filling: invalid pixels stay +inf.")
@click.option("--sequence", is_flag=True,
              help="Match INPUT, a folder of frames (or two folders), as one sequence in name order; "
                   "video inputs always are one.")
@click.option("--side-by-side", is_flag=True, help="INPUT is one video holding both views, the left view on the left.")
@click.option("--top-bottom", is_flag=True, help="INPUT is one video holding both views, the left view on top.")
@click.option("--temporal", type=click.Choice(["on", "off"]), default=None,
              help="Sequences: reuse the previous frames (narrower search, steadier maps) or match each frame "
                   "on its own [default: on].")
@click.option("--video-out", "video_out", type=click.Path(dir_okay=False), default=None, metavar="FILE",
              help="Sequences: also write the disparity maps as one colour video (.mp4, .avi, ...), one colour "
                   "range for every frame (--viz-range, else calib.txt vmin:vmax, else the first map's).")
@options.batch
@click.option("--split-strips/--no-split-strips", "split_strips", default=None,
              help="Spread the row strips of each large pair over the Dask workers (default: on with --scheduler).")
@options.verbose
@click.pass_context
def match_cmd(ctx, inputs, outdir, config_files, sets, ndisp, min_disp, png16_scale, npy, viz, viz_range,
              confidence, right, keep_invalid, overwrite, skip_existing, dry_run, jobs, scheduler, retries,
              split_strips, require_aligned, sequence, side_by_side, top_bottom, temporal, video_out):
    """Compute disparity maps for rectified pairs.

    INPUT is a pair of image files, a scene folder (im0/im1, im2/im6, view1/view5 or left/right
    [+ calib.txt]), a folder of scene folders, a folder of left01/right01 (left_0001, 0001_left)
    files, or a folder with left/ + right/ or cam0/ + cam1/ subfolders: the layouts of every
    subcommand (docs/formats.md). A folder holding two layouts is an error naming them.
    A sequence is matched frame after frame, reusing what the rig and the scene keep: a folder
    of frames with --sequence, two videos (left, right), or one video with --side-by-side or
    --top-bottom; frame i writes OUTDIR/<i as 000000>/.
    The disparity range comes from --ndisp/--min-disp, else from each scene's calib.txt, else
    it is estimated from the images (recorded in params.json with its evidence). Every pair's
    row alignment is measured; a pair whose rows are out of line gets a warning.

    \b
    Examples:
      stereocli match samples/scenes -o out
      stereocli match left.png right.png -o out --ndisp 64 --set optimizer.p2=1.2
      stereocli match my_pairs/ -o out --ndisp auto --require-aligned
      stereocli match data/ -o out -c fast --jobs 2 --skip-existing
      stereocli match data/ -o out --scheduler tcp://127.0.0.1:8786 --retries 2
      stereocli match --sequence frames/ -o out --ndisp 64
      stereocli match left.mp4 right.mp4 -o out --video-out disparity.mp4
      stereocli match --side-by-side rig.mp4 -o out --temporal off
    """
    from ..errors import ConfigError
    from ..io.pairs import discover_pairs
    from ..jobs.match import match_item, plan_items
    from ..jobs.sequence import wants_sequence
    from ..matching.config import build_config
    from ..process import keep_freed_memory_within
    from ..runinfo import versions

    verbosity = options.verbosity(ctx)
    if side_by_side and top_bottom:
        raise ConfigError("--side-by-side and --top-bottom exclude each other: a video holds one layout")
    layout = "side-by-side" if side_by_side else "top-bottom" if top_bottom else None
    if sequence or layout or wants_sequence(inputs):
        unavailable = {"--split-strips": split_strips, "--scheduler": scheduler, "--jobs": jobs > 1,
                       "--retries": retries}
        for flag, given in unavailable.items():
            if given:
                raise ConfigError(f"{flag}: not available for a sequence, which is matched in one process, "
                                  "frame after frame")
        code = _match_sequence(ctx, inputs, outdir, layout, build_config(config_files, sets), verbosity,
                               ndisp=ndisp, min_disp=min_disp, temporal=temporal or "on", right=right,
                               png16_scale=png16_scale, npy=npy, viz=viz or viz_range is not None, viz_range=viz_range,
                               confidence=confidence, keep_invalid=keep_invalid, require_aligned=require_aligned,
                               video_out=video_out, overwrite=overwrite, skip_existing=skip_existing, dry_run=dry_run)
        ctx.exit(code)
    if temporal is not None or video_out is not None:
        raise ConfigError(f"{'--temporal' if temporal is not None else '--video-out'} applies to sequences: "
                          "--sequence FOLDER, two videos, or --side-by-side / --top-bottom VIDEO")
    if split_strips and not scheduler:
        raise ConfigError("--split-strips spreads strips over Dask workers: give --scheduler tcp://HOST:PORT or local")
    config = build_config(config_files, sets)
    keep_freed_memory_within(config.runtime.memory_gb)  # process-wide: a smaller budget keeps less freed memory
    effective = config.as_dict()
    pairs, problems = discover_pairs(inputs)
    items = plan_items(pairs, outdir, config=effective, ndisp=ndisp, min_disp=min_disp, png16_scale=png16_scale,
                       npy=npy, viz=viz or viz_range is not None, viz_range=viz_range, confidence=confidence,
                       right=right, keep_invalid=keep_invalid,
                       split_strips=bool(scheduler) and split_strips is not False, require_aligned=require_aligned,
                       record_info={"versions": versions(), "config_sources": config.sources})
    if dry_run:
        print_json({"command": "match", "config": effective, "config_sources": config.sources,
                    "unpaired": problems,
                    "items": [{"name": i.name, "inputs": i.inputs, "outputs": i.outputs,
                               "min_disp": i.options["min_disp"], "ndisp": i.options["ndisp"] or "auto",
                               "range_source": i.options["range_source"], **({"error": i.error} if i.error else {})}
                              for i in items]})
        return
    if verbosity >= 1:
        _report_memory(items, config)
    for problem in problems:
        click.echo(f"Warning: {problem}", err=True)
    code, _ = run_batch_command("match", items, match_item, outdir=Path(outdir), config=effective, verbosity=verbosity,
                                extra_failures=unpaired_failures(problems), jobs=jobs, overwrite=overwrite,
                                skip_existing=skip_existing, scheduler=scheduler, retries=retries)
    ctx.exit(code)


def _match_sequence(ctx, inputs, outdir, layout, config, verbosity, *, video_out, overwrite, skip_existing, dry_run,
                    **match_options) -> int:
    """Plan, run and report one sequence (``match_options`` as :func:`~stereocli.jobs.sequence.plan_sequence`
    takes them); writes ``--video-out`` once the frames are done. Returns the exit code."""
    from ..jobs.sequence import SequenceRun, check_video_out, find_sequence, plan_sequence, write_sequence_video
    from ..process import keep_freed_memory_within
    from ..runinfo import versions

    keep_freed_memory_within(config.runtime.memory_gb)
    effective = config.as_dict()
    source = find_sequence(inputs, layout=layout)
    items = plan_sequence(source, outdir, config=effective,
                          record_info={"versions": versions(), "config_sources": config.sources}, **match_options)
    if video_out is not None:
        check_video_out(video_out, items, overwrite=overwrite or skip_existing)
    if dry_run:
        print_json({"command": "match", "config": effective, "config_sources": config.sources,
                    "sequence": source.as_record(), "unpaired": source.problems, "video_out": video_out,
                    "items": [{"name": i.name, "inputs": i.inputs, "outputs": i.outputs, "frame": i.options["frame"],
                               "min_disp": i.options["min_disp"], "ndisp": i.options["ndisp"] or "auto",
                               "range_source": i.options["range_source"]} for i in items]})
        return 0
    for warning in source.warnings:
        click.echo(f"Warning: {warning}", err=True)
    for problem in source.problems:
        click.echo(f"Warning: {problem}", err=True)
    run = SequenceRun(source, items)
    try:
        code, result = run_batch_command("match", items, run, outdir=Path(outdir), config=effective,
                                         verbosity=verbosity, extra_failures=unpaired_failures(source.problems),
                                         record_extra=lambda: {"sequence": run.record()}, executor="inline", jobs=1,
                                         overwrite=overwrite, skip_existing=skip_existing)
    finally:
        run.close()
    if video_out is not None and not result.interrupted:
        written = write_sequence_video(video_out, items, fps=source.fps, viz_range=match_options["viz_range"])
        if verbosity >= 0:
            lo, hi = written["range"]
            click.echo(f"{video_out}: {written['frames']} frames at {written['fps']:g} fps, colours {lo:g} to {hi:g} px"
                       + (f", {written['missing']} black (no map)" if written["missing"] else ""), err=True)
    return code


def _report_memory(items, config) -> None:
    from ..jobs.items import label_message
    from ..jobs.match import memory_plan
    from ..matching.pipeline import GIB

    for item in items:
        if item.error:
            continue  # reported as the item's failure
        try:
            plan = memory_plan(item, config)  # from the images' headers: nothing is decoded
        except Exception as exc:  # noqa: BLE001 - the item fails with it when it runs
            click.echo(label_message(item.name, str(exc)), err=True)
            continue
        if plan is None:
            continue  # a header it cannot read: the item reports its images when it runs
        size = f"{item.name}: {plan.width}x{plan.height}"
        if plan.estimate is None:
            click.echo(f"{size}, disparity range estimated when the pair runs; at least {plan.least / GIB:.2f} GiB "
                       f"(budget {config.runtime.memory_gb:g} GiB)", err=True)
            continue
        click.echo(f"{size}, ndisp {item.options['ndisp']}: {plan.strips} strip(s), estimated peak "
                   f"{plan.estimate / GIB:.2f} GiB (budget {config.runtime.memory_gb:g} GiB)", err=True)
