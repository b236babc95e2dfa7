"""``stereocli rectify``: calibration (or the pairs' own matches) + pairs -> row-aligned pairs,
valid masks, calib.txt."""

from __future__ import annotations

from pathlib import Path

import click

from ..errors import ConfigError as usage_error  # one-line message, exit 2
from ..errors import excerpt
from . import options
from .common import print_json, run_batch_command, unpaired_failures


def _size(text: str | None) -> tuple[int, int] | None:
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise usage_error(f"--size {excerpt(text, quote=True)}: expected WIDTHxHEIGHT, e.g. 1280x960") from None
    if w <= 0 or h <= 0:
        raise usage_error(f"--size {excerpt(text, quote=True)}: width and height must be positive")
    from ..rectification.maps import MAX_SIDE

    if max(w, h) > MAX_SIDE:
        raise usage_error(f"--size {w}x{h}: rectification handles at most {MAX_SIDE} px a side")
    return w, h


@click.command("rectify")
@click.argument("inputs", nargs=-1, required=True, type=click.Path())
@click.option("--calib", "calib_path", type=click.Path(),
              help="Calibration file (OpenCV .yml/.xml/.json, ROS pair, Kalibr camchain).")
@click.option("--uncalibrated", is_flag=True,
              help="No calibration: estimate homographies from the pairs' matches (one for all pairs of the rig).")
@click.option("--per-pair", is_flag=True, help="With --uncalibrated: estimate each pair's homographies alone "
                                                "(pairs from different rigs).")
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False),
              help="Output folder; each pair writes OUTDIR/<name>/{im0,im1,valid0,valid1}.png + calib.txt.")
@click.option("--alpha", type=options.Finite(0, 1), default=0.0, show_default=True,
              help="0 = crop to valid pixels, 1 = keep every source pixel (black borders, masked).")
@click.option("--size", "size_text", metavar="WxH", help="Rectified image size (default: the calibration's).")
@click.option("--interp", type=click.Choice(["nearest", "linear", "cubic", "lanczos"]), default="linear",
              show_default=True, help="Resampling of the images.")
@click.option("--ndisp", type=click.IntRange(1, 100000), help="ndisp written to calib.txt (default: estimated).")
@click.option("--min-depth", type=options.Finite(min=0, min_open=True),
              help="Nearest scene depth (calibration units) for the ndisp estimate = f·B/min_depth.")
@click.option("--check", is_flag=True, help="Also write check.png: side by side, horizontal lines, ROI boxes.")
@options.output_format
@options.batch
@options.verbose
@click.pass_context
def rectify_cmd(ctx, inputs, calib_path, uncalibrated, per_pair, outdir, alpha, size_text, interp, ndisp, min_depth,
                check, fmt, overwrite, skip_existing, dry_run, jobs, scheduler, retries):
    """Rectify stereo pairs so that epipolar lines are image rows.

    INPUT is a pair of image files, a folder of left01/right01 (left_0001, 0001_left) photos, a
    folder with left/ + right/ or cam0/ + cam1/ subfolders, or scene folders: the layouts of
    every subcommand (docs/formats.md). Each pair writes OUTDIR/<name>/, named as match names it.
    Without --ndisp, calib.txt gets the range estimated from the rectified pair, rounded up to
    a multiple of 16 (at least f·B / --min-depth).

    With --uncalibrated, homographies that make the pairs' epipolar lines rows with the least
    distortion are estimated from their feature matches; each pair also gets
    rectification.json (H0, H1: original pixel -> rectified pixel). calib.txt then has no
    baseline, so triangulate refuses it.

    \b
    Examples:
      stereocli rectify photos/ --calib rig.yml -o rectified --check
      stereocli rectify left.png right.png --calib rig.yml -o out --alpha 1 --size 1280x960
      stereocli rectify photos/ --uncalibrated -o rectified
    """
    from ..io.pairs import discover_pairs

    verbosity = options.verbosity(ctx)
    if uncalibrated:
        given = [flag for flag, name in (("--calib", "calib_path"), ("--alpha", "alpha"), ("--size", "size_text"),
                                         ("--min-depth", "min_depth"))
                 if ctx.get_parameter_source(name) == click.core.ParameterSource.COMMANDLINE]
        if given:
            raise usage_error(f"--uncalibrated estimates the rectification; {', '.join(given)} does not apply")
        pairs, problems = discover_pairs(inputs)
        _rectify_uncalibrated(ctx, pairs, problems, outdir, interp=interp, check=check, ndisp=ndisp,
                              per_pair=per_pair, fmt=fmt, verbosity=verbosity, overwrite=overwrite,
                              skip_existing=skip_existing, dry_run=dry_run, jobs=jobs, scheduler=scheduler,
                              retries=retries)
        return
    if not calib_path:
        raise usage_error("rectify needs --calib FILE, or --uncalibrated to estimate the rectification from the pairs")
    if per_pair:
        raise usage_error("--per-pair applies to --uncalibrated only")
    from ..io.calib import load_calibration
    from ..jobs.rectify import plan_items, rectify_item

    size = _size(size_text)
    load_calibration(calib_path)  # fail fast (exit 1/2) before any work
    pairs, problems = discover_pairs(inputs)
    items = plan_items(pairs, outdir, calib_path=calib_path, alpha=alpha, size=size, interpolation=interp,
                       check=check, ndisp=ndisp, min_depth=min_depth)
    if dry_run:
        print_json([i.as_dict() for i in items])
        return
    for problem in problems:
        click.echo(f"Warning: {problem}", err=True)
    settings = {"calibration": str(calib_path), "alpha": alpha, "size": list(size) if size else None,
                "interp": interp}
    code, result = run_batch_command("rectify", items, rectify_item, outdir=Path(outdir), config=settings,
                                     verbosity=verbosity, extra_failures=unpaired_failures(problems), jobs=jobs,
                                     overwrite=overwrite, skip_existing=skip_existing, scheduler=scheduler,
                                     retries=retries)
    if verbosity >= 1 or fmt == "json":
        print_json([r.as_dict() for r in result.results])
    ctx.exit(code)


def _rectify_uncalibrated(ctx, pairs, problems, outdir, *, interp, check, ndisp, per_pair, fmt, verbosity,
                          overwrite, skip_existing, dry_run, jobs, scheduler, retries) -> None:
    """``rectify --uncalibrated``: estimate the homographies (one rig, or each pair alone), then
    warp every pair as a batch and report the estimate."""
    from ..jobs.items import check_outputs, is_done
    from ..jobs.rectify import estimate_uncalibrated, plan_uncalibrated, rectify_uncalibrated_item

    items = plan_uncalibrated(pairs, outdir, interpolation=interp, check=check, ndisp=ndisp, per_pair=per_pair)
    if dry_run:
        print_json([i.as_dict() for i in items])
        return
    for problem in problems:
        click.echo(f"Warning: {problem}", err=True)
    check_outputs(items, overwrite=overwrite, skip_existing=skip_existing)  # before the estimate's work
    report = None
    if not (skip_existing and all(is_done(i) for i in items)):
        report = estimate_uncalibrated(items, per_pair=per_pair)
    settings = {"uncalibrated": True, "per_pair": per_pair, "interp": interp, "estimate": report}
    code, result = run_batch_command("rectify", items, rectify_uncalibrated_item, outdir=Path(outdir),
                                     config=settings, verbosity=verbosity,
                                     extra_failures=unpaired_failures(problems), jobs=jobs, overwrite=overwrite,
                                     skip_existing=skip_existing, scheduler=scheduler, retries=retries)
    if fmt == "json":
        print_json({"estimate": report, "pairs": {r.name: r.details for r in result.results if r.status == "ok"}})
    elif verbosity >= 0 and report is not None:
        click.echo(_uncalibrated_report(report, result.results))
    ctx.exit(code)


def _uncalibrated_report(report: dict, results) -> str:
    """The estimate as text: per rig the pairs it serves and the warp's distortion, then per pair
    the matches, inliers, residual vertical disparity and disparity range."""
    lines = []
    rigs = [rig for rig in report["rigs"] if "error" not in rig]
    if len(report["rigs"]) > 1:
        lines.append(f"homographies estimated per pair ({len(rigs)} of {len(report['rigs'])}; "
                     "their distortion: --format json)")
    for rig in rigs if len(report["rigs"]) == 1 else ():
        left, right = rig["distortion"]["left"], rig["distortion"]["right"]
        lines.append(f"one pair of homographies for the {len(rig['pairs'])} pair(s), estimated from the matches of "
                     f"{len(rig['estimated_from'])}; distortion: left {left['orthogonality_deg']:.2f} deg / "
                     f"aspect {left['aspect']:.4f}, right {right['orthogonality_deg']:.2f} deg / "
                     f"aspect {right['aspect']:.4f}")
    done = [r for r in results if r.status == "ok"]
    if done:
        width = max(4, *(len(r.name) for r in done))
        lines.append(f"{'pair':{width}}  matches  inliers  |dy| median  |dy| p90  disparities")
        for r in done:
            d = r.details
            lines.append(f"{r.name:{width}}  {d['matches']:7d}  {d['inliers']:7d}  {d['dy_median']:11.2f}  "
                         f"{d['dy_p90']:8.2f}  [{d['range']['min_disp']}, {d['range']['max_disp']}] px")
    return "\n".join(lines)
