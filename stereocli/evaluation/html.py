"""A self-contained HTML report: the score tables plus, per scene, left image / estimate / GT /
error map / bad pixels side by side, every image embedded as a base64 PNG (one file, no links)."""

from __future__ import annotations

import base64
import html
from pathlib import Path

import cv2
import numpy as np

from ..errors import check_outputs_free
from ..io.atomic import write_text
from .maps import scene_images
from .report import format_table, region_table
from .scoring import EvalReport

#: Previews wider than this are downscaled in the HTML (keeps the file small).
MAX_PREVIEW_WIDTH = 480


def _png_base64(rgb: np.ndarray) -> str:
    if rgb.shape[1] > MAX_PREVIEW_WIDTH:
        scale = MAX_PREVIEW_WIDTH / rgb.shape[1]
        rgb = cv2.resize(rgb, (MAX_PREVIEW_WIDTH, max(1, round(rgb.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 RGB
        raise RuntimeError("PNG encoding failed")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def _table_html(report: EvalReport, region: str) -> str:
    """The region's table with the text report's columns (:func:`~stereocli.evaluation.report.region_table`)."""
    header, rows = region_table(report, region)
    lines = ["<tr><th>scene</th>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    for i, (name, cells) in enumerate(rows):
        average = bool(report.scenes) and i == len(rows) - 1
        lines.append(("<tr class=avg>" if average else "<tr>") + f"<td>{html.escape(name)}</td>"
                     + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "<table>" + "\n".join(lines) + "</table>"


def render_html(report: EvalReport, title: str = "stereocli eval") -> str:
    """The whole report as one HTML string (needs results scored with ``keep_arrays=True``)."""
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             "<style>body{font-family:sans-serif;margin:1em}table{border-collapse:collapse;margin:.5em 0}"
             "td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}td:first-child{text-align:left}"
             "tr.avg{font-weight:bold}.row{display:flex;gap:6px;flex-wrap:wrap}figure{margin:0}"
             "figcaption{font-size:small;text-align:center}img{display:block}.rules{color:#333;max-width:60em}"
             "</style></head><body>",
             f"<h1>{html.escape(title)}</h1><p class=rules>{html.escape(report.rules)}</p>"]
    for region in report.regions:
        parts.append(f"<h2>{html.escape(region)}</h2>" + _table_html(report, region))
    for note in report.notes:
        parts.append(f"<p>note: {html.escape(note)}</p>")
    for f in report.failures:
        parts.append(f"<p><b>{'error' if f.get('partial') else 'failed'}</b> {html.escape(f['name'])}: "
                     f"{html.escape(f['message'])}</p>")
    for s in report.scenes:
        imgs = scene_images(s, report.thresholds)
        parts.append(f"<h3>{html.escape(s.name)}</h3><div class=row>")
        for key, caption in (("left", "left image"), ("estimate", "estimate"), ("gt", "ground truth"),
                             ("error", "|error|"), ("bad", "bad pixels")):
            if key in imgs:
                parts.append(f"<figure><img alt='{key}' src='data:image/png;base64,{_png_base64(imgs[key])}'>"
                             f"<figcaption>{caption}</figcaption></figure>")
        parts.append("</div>")
    parts.append("<details><summary>text table</summary><pre>" + html.escape(format_table(report, "text"))
                 + "</pre></details></body></html>")
    return "\n".join(parts)


def write_html(report: EvalReport, out_dir: str | Path, *, overwrite: bool = False,
               filename: str = "report.html") -> Path:
    """Write ``OUT/report.html`` (atomically); refuses to replace it without ``overwrite``."""
    path = Path(out_dir) / filename
    check_outputs_free([path], overwrite=overwrite)
    write_text(path, render_html(report))
    return path
