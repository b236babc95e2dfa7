"""``stereocli triangulate``: disparity + calibration -> depth maps and point clouds."""

from __future__ import annotations

from pathlib import Path

import click

from ..errors import ConfigError as usage_error  # one-line message, exit 2
from . import options
from .common import print_json, run_batch_command, unpaired_failures


@click.command("triangulate")
@click.argument("inputs", nargs=-1, required=True, type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(),
              help="OUT.ply / OUT.npy for one disparity file, else a folder receiving <name>/cloud.ply, depth.pfm.")
@click.option("--calib", "calib_path", type=click.Path(),
              help="Calibration of the rectified pair (calib.txt, OpenCV, ROS); "
                   "default: calib.txt beside the disparity.")
@click.option("--image", type=click.Path(dir_okay=False), help="Left image for colours (default: im0.png beside it).")
@click.option("--scenes", type=click.Path(file_okay=False),
              help="The pairs (e.g. rectify's output, any layout match reads) whose calib.txt and left image "
                   "go with the disparity of the same name.")
@click.option("--confidence", type=click.Path(dir_okay=False),
              help="Confidence map (PFM/npy) stored per point (default: conf0.pfm beside the disparity).")
@click.option("--min-confidence", type=options.Finite(0, 1),
              help="Drop points whose confidence is below this (needs a confidence map; match writes 0 where it "
                   "filled or found nothing).")
@click.option("--scale", type=options.Finite(min=0, min_open=True),
              help="Disparity scale of integer PNG inputs (d = value / scale; 16-bit default 256).")
@click.option("--units", type=click.Choice(["m", "cm", "mm"]), help="Depth unit (default: the calibration's).")
@click.option("--use-q", is_flag=True, help="Take f, cx, cy, B, doffs from the Q matrix instead of P1/P2.")
@click.option("--min-depth", type=options.Finite(min=0), help="Drop points nearer than this (depth units).")
@click.option("--max-depth", type=options.Finite(min=0, min_open=True),
              help="Drop points farther than this (depth units).")
@click.option("--keep-unsupported", is_flag=True,
              help="Also keep points the match does not support: disparities outside the range it searched, "
                   "pixels no right-view pixel shows, and d + doffs < 2 px (near infinity).")
@click.option("--stride", type=click.IntRange(1, 1000), default=1, show_default=True,
              help="Keep every STRIDE-th pixel in x and y (point cloud decimation).")
@click.option("--ascii", "ascii_ply", is_flag=True, help="ASCII PLY instead of binary little endian.")
@click.option("--normals", is_flag=True, help="Add nx ny nz (from neighbouring depths) to the PLY.")
@click.option("--no-color", is_flag=True, help="Do not colour points from the image.")
@click.option("--npy", is_flag=True, help="Folder mode: write cloud.npy (N x 3 float32 XYZ) instead of cloud.ply.")
@click.option("--depth-format", type=click.Choice(["pfm", "tif", "npy"]), default=None,
              help="Depth map format (folder mode default pfm; single-file mode writes OUT_depth.EXT only if set).")
@click.option("--depth-png16", is_flag=True, help="Also write a uint16 PNG of depth in millimetres (0 = invalid).")
@click.option("--summary", is_flag=True, help="Write a JSON summary (count, depth percentiles, bounding box).")
@options.output_format
@options.batch
@options.verbose
@click.pass_context
def triangulate_cmd(ctx, inputs, output, calib_path, image, scenes, confidence, min_confidence, scale, units, use_q,
                    min_depth, max_depth, keep_unsupported, stride, ascii_ply, normals, no_color, npy, depth_format,
                    depth_png16, summary, fmt, overwrite, skip_existing, dry_run, jobs, scheduler, retries):
    """Turn disparity maps into depth maps and coloured point clouds.

    Z = f·B / (d + doffs), X = Z·(x − cx)/f, Y = Z·(y − cy)/f in the rectified left camera
    frame (x right, y down, z forward), in the calibration's unit (Middlebury calib.txt: mm).
    Only what the match supports becomes a point: invalid disparities, disparities outside the
    range the match searched (params.json beside the disparity, else calib.txt), pixels no
    right-view pixel shows (valid masks, the image's edge) and d + doffs < 2 px are dropped, and
    so are depths outside --min-depth/--max-depth; depth maps hold +inf there. --summary and
    run.json count the dropped pixels by reason.

    \b
    Examples:
      stereocli triangulate out/scene/disp0.pfm --calib rect/scene/calib.txt -o scene.ply
      stereocli triangulate out/ --scenes rect/ -o clouds/ --units m --max-depth 5 --summary
      stereocli triangulate disp.png --scale 256 --calib rig.yml --image left.png -o cloud.ply --ascii
    """
    from ..jobs.triangulate import plan_items, triangulate_item

    if min_depth is not None and max_depth is not None and min_depth >= max_depth:
        raise usage_error(f"--min-depth {min_depth} must be below --max-depth {max_depth}")
    if calib_path:
        from ..io.calib import load_calibration

        load_calibration(calib_path)  # fail fast on unreadable / unknown calibration
    verbosity = options.verbosity(ctx)
    opts = {"scale": scale, "units": units, "use_q": use_q, "min_depth": min_depth, "max_depth": max_depth,
            "stride": stride, "ascii": ascii_ply, "normals": normals, "color": not no_color,
            "min_confidence": min_confidence, "keep_unsupported": keep_unsupported}
    items, problems = plan_items(inputs, output, calib=calib_path, image=image, scenes=scenes, confidence=confidence,
                                 npy=npy, depth_format=depth_format, depth_png16=depth_png16, summary=summary,
                                 options=opts)
    if dry_run:
        print_json([i.as_dict() for i in items])
        return
    for problem in problems:
        click.echo(f"Warning: {problem}", err=True)
    out = Path(output)
    single = out.suffix.lower() in (".ply", ".npy")
    code, result = run_batch_command("triangulate", items, triangulate_item, outdir=None if single else out,
                                     config=opts, verbosity=verbosity, extra_failures=unpaired_failures(problems),
                                     jobs=jobs, overwrite=overwrite, skip_existing=skip_existing,
                                     scheduler=scheduler, retries=retries)
    if fmt == "json":
        print_json({r.name: r.details for r in result.results if r.status == "ok"})
    elif verbosity >= 0:
        for r in result.results:
            if r.status == "ok":
                p = r.details.get("depth_percentiles", {})
                dropped = ", ".join(f"{n} {reason}" for reason, n in r.details.get("dropped", {}).items() if n)
                click.echo(f"{r.name}: {r.details['points']} points, median depth {p.get('p50', float('nan')):.4g} "
                           f"{r.details['units']}{f' (pixels dropped: {dropped})' if dropped else ''} -> "
                           f"{r.outputs['cloud']}", err=True)
    ctx.exit(code)
