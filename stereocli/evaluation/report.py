"""Report formatting: text (default, greppable header row), JSON, CSV and Markdown tables.

Text and Markdown show the control characters of scene names and messages escaped (a newline
as ``\\n``), so every scene stays one row; Markdown also escapes ``|``. CSV quotes such fields and
JSON keeps them as they are.
"""

from __future__ import annotations

import csv
import io
import json
import math
import textwrap
import unicodedata
from typing import Any

from .metrics import quantile_key, threshold_key
from .scoring import EvalReport, SceneResult, json_ready

FORMATS = ("text", "json", "csv", "markdown")

_TIME_COLS = [("time", "time"), ("time_per_mp", "s/MP"), ("time_per_gd", "s/GD")]


def metric_columns(report: EvalReport) -> list[str]:
    """Metric keys in display order (KITTI D1 columns first when present)."""
    present: set[str] = set()
    for s in report.scenes:
        for values in s.metrics.values():
            if values:
                present.update(values)
    cols: list[str] = [k for k in ("D1", "D1-bg", "D1-fg", "density") if k in present]
    cols += [threshold_key(t) for t in report.thresholds]
    cols += ["invalid", "avgerr", "rms"] + [quantile_key(q) for q in report.quantiles]
    return [c for c in cols if c in present]


def _printable(text: str) -> str:
    """``text`` with control characters and line separators escaped (``\\n``, ``\\x1b``): one line."""
    return "".join(c.encode("unicode_escape").decode("ascii") if unicodedata.category(c) in ("Cc", "Zl", "Zp") else c
                   for c in text)


def _markdown_cell(text: str) -> str:
    return _printable(text).replace("|", "\\|")


def _has_time(report: EvalReport) -> bool:
    return any(s.time is not None for s in report.scenes)


def _fmt(value: Any, key: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if key in ("time", "time_per_mp", "time_per_gd"):
        return f"{value:.3g}"
    return f"{value:.2f}"


def _rows(report: EvalReport, region: str, cols: list[str], with_time: bool) -> list[tuple[str, list[str]]]:
    rows = []
    for s in report.scenes:
        m = s.metrics.get(region)
        cells = [f"{s.weight:g}"] + [_fmt(None if m is None else m.get(c), c) for c in cols]
        if with_time:
            cells += [_fmt(getattr(s, k), k) for k, _ in _TIME_COLS]
        rows.append((_printable(s.name), cells))
    if report.scenes:
        avg = report.average
        m = avg.get(region)
        label = "average" if len({s.weight for s in report.scenes}) == 1 else "average (weighted)"
        cells = [f"{avg['weight']:g}"] + [_fmt(None if m is None else m.get(c), c) for c in cols]
        if with_time:
            cells += [_fmt(avg.get(k), k) for k, _ in _TIME_COLS]
        rows.append((label, cells))
    return rows


def region_table(report: EvalReport, region: str) -> tuple[list[str], list[tuple[str, list[str]]]]:
    """One region's table as every format shows it: the header after ``scene`` (weight, the metric
    columns, and time, s/MP, s/GD when a scene has a time) and the rows ``(scene, cells)``, the
    (weighted) average last."""
    cols = metric_columns(report)
    with_time = _has_time(report)
    header = ["weight"] + cols + ([label for _, label in _TIME_COLS] if with_time else [])
    return header, _rows(report, region, cols, with_time)


def format_text(report: EvalReport) -> str:
    cols = metric_columns(report)
    with_time = _has_time(report)
    header = ["weight"] + cols + ([label for _, label in _TIME_COLS] if with_time else [])
    lines = []
    for chunk in textwrap.wrap(report.rules, width=100):
        lines.append(f"# {chunk}")
    for region in report.regions:
        rows = _rows(report, region, cols, with_time)
        name_w = max([len("scene")] + [len(n) for n, _ in rows])
        widths = [max(len(h), *(len(r[1][i]) for r in rows)) for i, h in enumerate(header)]
        lines.append("")
        lines.append(f"## region: {region}" + _region_note(report, region))
        lines.append("  ".join(["scene".ljust(name_w)] + [h.rjust(w) for h, w in zip(header, widths)]))
        for name, cells in rows:
            lines.append("  ".join([name.ljust(name_w)] + [c.rjust(w) for c, w in zip(cells, widths)]))
    for note in report.notes:
        lines.append(f"# note: {_printable(note)}")
    for f in report.failures:
        tag = "ERROR" if f.get("partial") else "FAILED"
        lines.append(f"# {tag} {_printable(f['name'])}: {_printable(f['message'])}")
    return "\n".join(lines) + "\n"


def _region_note(report: EvalReport, region: str) -> str:
    notes = {note for s in report.scenes if (note := s.mask_notes.get(region))}
    if not notes:
        return ""
    return "  [" + "; ".join(sorted(notes)) + "]"


def format_json(report: EvalReport) -> str:
    return json.dumps(json_ready(report.as_dict()), indent=2) + "\n"


def format_csv(report: EvalReport) -> str:
    cols = metric_columns(report)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["scene", "region", "weight"] + cols + [k for k, _ in _TIME_COLS])
    avg = report.average
    for region in report.regions:
        for s in report.scenes:
            m = s.metrics.get(region) or {}
            writer.writerow([s.name, region, s.weight] + [_csv(m.get(c)) for c in cols]
                            + [_csv(getattr(s, k)) for k, _ in _TIME_COLS])
        if report.scenes:
            m = avg.get(region) or {}
            writer.writerow(["average", region, avg["weight"]] + [_csv(m.get(c)) for c in cols]
                            + [_csv(avg.get(k)) for k, _ in _TIME_COLS])
    return buf.getvalue()


def _csv(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def format_markdown(report: EvalReport) -> str:
    cols = metric_columns(report)
    with_time = _has_time(report)
    header = ["scene", "weight"] + cols + ([label for _, label in _TIME_COLS] if with_time else [])
    lines = [f"> {report.rules}"]
    for region in report.regions:
        lines += ["", f"**{region}**" + _region_note(report, region), ""]
        lines.append("| " + " | ".join(header) + " |")
        lines.append("|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|")
        for name, cells in _rows(report, region, cols, with_time):
            lines.append("| " + " | ".join([name.replace("|", "\\|")] + cells) + " |")
    if report.notes or report.failures:
        lines.append("")
    for note in report.notes:
        lines.append(f"- note: {_printable(note)}")
    for f in report.failures:
        lines.append(f"- **{'error' if f.get('partial') else 'failed'}** {_markdown_cell(f['name'])}: "
                     f"{_printable(f['message'])}")
    return "\n".join(lines) + "\n"


def format_table(report: EvalReport | SceneResult, fmt: str = "text") -> str:
    """Render ``report`` as ``text``, ``json``, ``csv`` or ``markdown``; a single scene's
    result (:func:`~stereocli.evaluation.scoring.evaluate_pair`) renders as its pair report."""
    if isinstance(report, SceneResult):
        report = report.as_report()
    if fmt == "text":
        return format_text(report)
    if fmt == "json":
        return format_json(report)
    if fmt == "csv":
        return format_csv(report)
    if fmt == "markdown":
        return format_markdown(report)
    raise ValueError(f"unknown report format {fmt!r}; choose from {', '.join(FORMATS)}")
