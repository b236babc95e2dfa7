"""``stereocli calibrate`` and ``stereocli convert-calib``."""

from __future__ import annotations

import json
import re
from pathlib import Path

import click

from ..errors import ConfigError as usage_error  # one-line message, exit 2
from ..errors import check_outputs_free, excerpt
from . import options

_SQUARE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?\d+)?)\s*([a-zA-Zµ]*)\s*$")


def _square(text: str, units: str | None) -> tuple[float, str]:
    m = _SQUARE.match(text)
    if not m:
        raise usage_error(f"--square {excerpt(text, quote=True)}: expected a length like 25mm, 0.025m or 1")
    value, unit = float(m.group(1)), m.group(2) or units or "unit"
    if units and m.group(2) and units != m.group(2):
        raise usage_error(f"--square {excerpt(text, quote=True)} and --units {excerpt(units, quote=True)} disagree")
    if value <= 0:
        raise usage_error("--square must be positive")
    return value, unit


def _output_paths(output: Path, fmt: str | None) -> list[Path]:
    from ..io.calib import ros_pair_paths

    return list(ros_pair_paths(output)) if fmt == "ros" else [output]


FORMAT_CHOICE = click.Choice(["opencv", "ros", "middlebury"])


@click.command("calibrate")
@click.argument("input_dir", metavar="INPUT", type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Calibration file: .yml/.yaml/.xml/.json (OpenCV), or with --to ros OUT_left/right.yaml.")
@click.option("--pattern", "pattern_text", required=True, metavar="COLSxROWS",
              help="Inner corners (chessboard, ChArUco) or circles per row x column, e.g. 9x6.")
@click.option("--square", "square_text", default="1", show_default=True, metavar="SIZE[UNIT]",
              help="Square side (circle spacing), e.g. 25mm or 0.025m; sets the unit of T and depth.")
@click.option("--units", default=None, help="Unit name when --square has none (e.g. mm).")
@click.option("--pattern-type", type=click.Choice(["chessboard", "circles", "acircles", "charuco"]),
              default="chessboard", show_default=True, help="Calibration target.")
@click.option("--dictionary", default="DICT_5X5_100", show_default=True, help="ChArUco ArUco dictionary.")
@click.option("--marker-size", type=options.Finite(0, 1, min_open=True, max_open=True), default=0.75,
              show_default=True, help="ChArUco marker side as a fraction of the square side.")
@click.option("--detector", type=click.Choice(["auto", "classic", "sb"]), default="auto", show_default=True,
              help="Chessboard detector: classic + cornerSubPix, the SB (sector-based) one, or classic then SB.")
@click.option("--fix-principal-point", is_flag=True, help="Keep cx, cy at the image centre.")
@click.option("--zero-tangent", is_flag=True, help="Tangential distortion p1 = p2 = 0.")
@click.option("--fix-aspect", is_flag=True, help="Keep fx / fy = 1.")
@click.option("--fix-k3", is_flag=True, help="k3 = 0 (recommended for narrow lenses and few views).")
@click.option("--rational", is_flag=True, help="Rational distortion model k4..k6 (wide-angle lenses).")
@click.option("--fisheye", is_flag=True, help="Fisheye (equidistant) model, k1..k4.")
@click.option("--same-focal", is_flag=True, help="With --joint: both cameras share fx, fy.")
@click.option("--joint", is_flag=True,
              help="Refine intrinsics in the stereo solve (default: fixed after per-camera calibration).")
@click.option("--max-view-error", type=options.Finite(min=0, min_open=True), metavar="PX",
              help="Drop views whose RMS exceeds PX and recalibrate.")
@click.option("--alpha", type=options.Finite(0, 1), default=0.0, show_default=True,
              help="Rectification alpha stored in the file (P1, P2, Q).")
@click.option("--swap", is_flag=True, help="Exchange left and right (rig wired the other way round).")
@click.option("--to", "out_format", type=FORMAT_CHOICE, default=None,
              help="Output format (default: from the extension).")
@click.option("--report", "report_path", type=click.Path(dir_okay=False),
              help="JSON report path (default: OUTPUT stem + .report.json).")
@click.option("--cache", "cache_path", type=click.Path(dir_okay=False),
              help="Detection cache (default: .stereocli-detections.json beside OUTPUT).")
@click.option("--no-cache", is_flag=True, help="Detect again and do not write a cache.")
@click.option("-j", "--jobs", type=click.IntRange(1, 256), default=None,
              help="Detection threads (default: all cores).")
@options.output_format
@options.overwrite
@options.verbose
@click.pass_context
def calibrate_cmd(ctx, input_dir, output, pattern_text, square_text, units, pattern_type, dictionary, marker_size,
                  detector, fix_principal_point, zero_tangent, fix_aspect, fix_k3, rational, fisheye, same_focal,
                  joint, max_view_error, alpha, swap, out_format, report_path, cache_path, no_cache, jobs, fmt,
                  overwrite):
    """Calibrate a stereo rig from checkerboard (or circle grid / ChArUco) photo pairs.

    INPUT is a folder of left01/right01 (left_0001, 0001_left) photos, a folder with left/ +
    right/ or cam0/ + cam1/ subfolders, or a folder of scene folders: the layouts of every
    subcommand, with the same pair names (docs/formats.md). Each camera is calibrated alone, then
    R, T with the intrinsics fixed (unless --joint). The report goes to stdout (text, or JSON with
    --format json) and to OUTPUT stem + .report.json; it lists per-view RMS, outliers, images
    without the target, the baseline, the rectified epipolar error and warnings (also on stderr).

    \b
    Examples:
      stereocli calibrate photos/ -o rig.yml --pattern 9x6 --square 25mm
      stereocli calibrate photos/ -o rig.yml --pattern 9x6 --square 25mm --fix-k3 --max-view-error 1
      stereocli calibrate photos/ -o rig --to ros --pattern 9x6 --square 0.025m
    """
    from dataclasses import asdict

    from ..api import calibrate
    from ..calib import CalibOptions, Pattern, format_report, parse_pattern_size
    from ..io.atomic import write_text
    from ..io.calib import save_calibration

    fmt_report, fmt = fmt, out_format
    verbosity = options.verbosity(ctx)
    output = Path(output)
    if fmt is None:
        if output.suffix.lower() not in (".yml", ".yaml", ".xml", ".json"):
            raise usage_error(f"{output}: cannot tell the calibration format from "
                              f"{output.suffix or 'no extension'!r}; use .yml/.yaml/.xml/.json or --to ros")
        fmt = "opencv"
    if fmt == "middlebury":
        raise usage_error("calibrate writes opencv or ros; a Middlebury calib.txt describes a rectified pair "
                          "(rectify writes it, or use convert-calib)")
    if fmt == "ros" and output.suffix.lower() not in (".yaml", ".yml"):
        output = output.with_name(output.name + ".yaml")
    cols, rows = parse_pattern_size(pattern_text)
    square, unit = _square(square_text, units)
    if fmt == "ros":
        from ..io.calib import UNIT_SCALE

        if unit not in UNIT_SCALE:  # refused now, not after detecting every image
            raise usage_error(f"--to ros: ROS camera_info is in metres; give --square a length unit, e.g. 25mm "
                              f"or 0.025m (known: {', '.join(UNIT_SCALE)})")
    pattern = Pattern(cols, rows, square, pattern_type, unit, marker_size, dictionary)
    opts = CalibOptions(fix_principal_point=fix_principal_point, zero_tangent=zero_tangent, fix_aspect=fix_aspect,
                        fix_k3=fix_k3, rational=rational, fisheye=fisheye, same_focal=same_focal, joint=joint,
                        max_view_error=max_view_error, alpha=alpha)
    if fisheye and (rational or zero_tangent or fix_k3):
        raise usage_error("--fisheye cannot be combined with --rational, --zero-tangent or --fix-k3")
    if same_focal and not joint:
        raise usage_error("--same-focal needs --joint (intrinsics are fixed in the stereo solve otherwise)")
    report_path = Path(report_path) if report_path else output.with_name(output.stem + ".report.json")
    check_outputs_free(_output_paths(output, fmt) + [report_path], overwrite=overwrite)
    cache = None if no_cache else (Path(cache_path) if cache_path else output.parent / ".stereocli-detections.json")
    result = calibrate(input_dir, pattern, detector=detector, jobs=jobs, cache=cache,
                       progress=None if verbosity >= 0 else False, swap=swap, **asdict(opts))
    written = save_calibration(output, result.calibration, fmt, ndisp=0)
    report = dict(result.report)
    report["outputs"] = [str(p) for p in written]
    write_text(report_path, json.dumps(report, indent=2) + "\n")
    # The report is the command's result (stdout, like eval's); stderr has what was written and the warnings.
    click.echo(json.dumps(report, indent=2) if fmt_report == "json" else format_report(report))
    if verbosity >= 0:
        for warning in report["warnings"]:
            click.echo(f"Warning: {warning}", err=True)
        click.echo(f"wrote {', '.join(map(str, written))} and {report_path}", err=True)


@click.command("convert-calib")
@click.argument("src", metavar="IN", type=click.Path())
@click.argument("dst", metavar="OUT", type=click.Path(dir_okay=False))
@click.option("--to", "fmt", type=FORMAT_CHOICE, default=None,
              help="Output format (default: .txt → middlebury, else opencv by extension).")
@click.option("--alpha", type=options.Finite(0, 1), default=None,
              help="Rectify with this alpha when the output needs P1/P2 and the input has none (default 0).")
@click.option("--ndisp", type=click.IntRange(0, 100000), default=0, help="ndisp for a Middlebury calib.txt.")
@options.overwrite
@options.verbose
@click.pass_context
def convert_calib_cmd(ctx, src, dst, fmt, alpha, ndisp, overwrite):
    """Convert a calibration between formats.

    Reads OpenCV FileStorage (.yml/.yaml/.xml/.json), ROS camera_info pairs (OUT_left.yaml +
    OUT_right.yaml), Kalibr camchains and Middlebury calib.txt; writes the first three
    except Kalibr. --to ros writes OUT_left.yaml and OUT_right.yaml.

    \b
    Examples:
      stereocli convert-calib rig.yml rig.json
      stereocli convert-calib rig.yml rig --to ros
      stereocli convert-calib camchain.yaml calib.txt --to middlebury
    """
    from ..io.calib import load_calibration, save_calibration
    from ..rectification.maps import rectified_calibration

    dst = Path(dst)
    if fmt is None:
        fmt = "middlebury" if dst.suffix.lower() == ".txt" else "opencv"
        if fmt == "opencv" and dst.suffix.lower() not in (".yml", ".yaml", ".xml", ".json"):
            raise usage_error(f"{dst}: cannot tell the output format from {dst.suffix or 'no extension'!r}; "
                              "use .yml/.yaml/.xml/.json, .txt or --to")
    if fmt == "ros" and dst.suffix.lower() not in (".yaml", ".yml"):
        dst = dst.with_name(dst.name + ".yaml")
    check_outputs_free(_output_paths(dst, fmt), overwrite=overwrite)
    calib = load_calibration(src)
    if alpha is not None or (fmt in ("ros", "middlebury") and not calib.is_rectified):
        calib = rectified_calibration(calib, alpha=alpha or 0.0)
    if fmt == "middlebury" and not ndisp:
        ndisp = int(calib.extra.get("ndisp", 0) or 0)
    written = save_calibration(dst, calib, fmt, ndisp=ndisp)
    if options.verbosity(ctx) >= 0:
        click.echo(f"wrote {', '.join(map(str, written))}", err=True)
