#!/usr/bin/env python3
"""Write the score tables of the documents from ``benchmarks/results/scoreboard.json``.

Every published score comes from one file, as ``docs/methods.md`` comes from the stage registry.
The generated parts sit between markers, and only they are rewritten:

* Markdown (``README.md``, ``docs/benchmarks.md``): ``<!-- scoreboard: NAME -->`` ...
  ``<!-- /scoreboard -->``;
* the presets (``configs/*.yaml``): ``# scoreboard: NAME`` ... ``# /scoreboard``.

    python benchmarks/render_docs.py            # rewrite the blocks
    python benchmarks/render_docs.py --check    # list the blocks that differ (exit 1), write nothing

``tests/test_docs.py`` fails when a block is not what this script writes.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import textwrap
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
SCOREBOARD = REPO / "benchmarks" / "results" / "scoreboard.json"

#: Presets in the order of the tables; ``LADDER`` from the fastest to the most accurate.
PRESETS = ("default", "accurate", "fast", "quality", "adcensus", "realtime")
LADDER = ("realtime", "fast", "default", "accurate", "quality")
OPENCV = {"OpenCV BM": "OpenCV BM", "OpenCV SGBM": "SGBM", "OpenCV SGBM 3WAY": "SGBM 3WAY", "OpenCV SGBM HH": "SGBM HH"}
PANDORA = "Pandora census+SGM"
V2_SCENES = ("tsukuba", "venus", "teddy", "cones")
#: Hirschmüller's SGM paper (2008, official v2 masks): Tsukuba, Venus, Teddy, Cones bad > 1 %.
SGM_PAPER = (3.26, 1.00, 6.02, 3.06)

#: The README's preset table: what each preset runs and what it is for.
PRESET_ROWS = {
    "realtime": ("mean removal, SAD 9×9 + WTA, single matching phase, sub-pixel, texture threshold; holes stay "
                 "invalid", "video rates, sparse output"),
    "fast": ("census 5×5, coarse-to-fine 4-path SGM, sub-pixel, LR check, fill, 3×3 median, `plane_smooth`",
             "previews; pairs whose rows meet"),
    "default": ("`row_align` (tracking 4× reduced), census 5×5, coarse-to-fine 4-path SGM, sub-pixel, LR check, "
                "fill, 5×5 median, `plane_smooth`", "almost everything: near SGBM's speed, half its errors"),
    "accurate": ("`row_align` (2×), census 5×5, SGM with wider windows, sub-pixel, LR check, fill, median, "
                 "geodesic vote, `plane_smooth`", "the best accuracy per second"),
    "quality": ("`accurate` with colour-weighted census + `plane_fit` of LR rejects + `mirror_fusion` + "
                "`photo_consistency` + locally consistent vote + `slanted_patchmatch`", "the most accurate maps"),
    "adcensus": ("AD-census, two-threshold cross aggregation, 8-path SGM, region voting, interpolation, median; "
                 "**integer** output", "integer-GT benchmarks (v2), not photographs"),
}


# --- reading the scoreboard ----------------------------------------------------------------------


class Board:
    """The scoreboard with the look-ups the tables need."""

    def __init__(self, data: dict) -> None:
        self.data = data
        self.methods: dict = data["methods"]
        self.datasets: dict = data["datasets"]

    def entry(self, method: str, dataset: str) -> dict | None:
        return self.methods.get(method, {}).get(dataset)

    def average(self, method: str, dataset: str, key: str) -> float | None:
        entry = self.entry(method, dataset)
        return None if entry is None else entry["average"].get(key)

    def scene(self, method: str, dataset: str, scene: str, key: str) -> float | None:
        entry = self.entry(method, dataset)
        return None if entry is None else entry["scenes"].get(scene, {}).get(key)

    def time(self, method: str, dataset: str, key: str) -> float | None:
        entry = self.entry(method, dataset)
        return None if entry is None or not entry.get("time") else entry["time"].get(key)

    def scenes(self, dataset: str) -> list[str]:
        return list(self.datasets.get(dataset, {}).get("scenes", {}))

    def presets(self) -> list[str]:
        """Presets on the board, in table order (other configs after the bundled ones)."""
        names = [m.removeprefix("stereocli ") for m in self.methods if m.startswith("stereocli ")]
        return [p for p in PRESETS if p in names] + sorted(n for n in names if n not in PRESETS)

    def opencv(self) -> list[str]:
        return [m for m in OPENCV if m in self.methods]


def num(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def ratio(board: Board, method: str, dataset: str) -> str:
    """A method's time over SGBM 3WAY's; ``≈`` when it was not measured in turns with it."""
    value = board.time(method, dataset, "x3way")
    if value is None:
        return "–"
    entry = board.entry(method, dataset)
    return f"≈ {value:.0f}" if not entry.get("in_turns", True) else f"{value:.2f}"


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def times_note(board: Board, dataset: str) -> str:
    """Where a table's times come from: the run that measured the default's."""
    entry = board.entry("stereocli default", dataset) or {}
    run = board.data["runs"].get(entry.get("times_run") or "", {})
    if not run:
        return "no times measured yet"
    return f"times: {run['threads']} threads, best of {run['repeat']} (run `{entry['times_run']}`)"


# --- docs/benchmarks.md ---------------------------------------------------------------------------


def summary(board: Board, dataset: str) -> str:
    keys = ["bad1.0", "bad2.0", "bad4.0"] if dataset == "mb2014" else ["bad1.0", "bad2.0"]
    header = ["method"] + [f"{k} %" for k in keys] + ["avgerr px", "invalid %", "time s (sum)", "MDE/s", "time ×3WAY"]
    rows = []
    methods = [f"stereocli {p}" for p in board.presets()] + board.opencv() + [PANDORA]
    for method in methods:
        if board.entry(method, dataset) is None:
            continue
        label = f"{PANDORA} (`--pandora PATH`)" if method == PANDORA else method
        rows.append([label] + [num(board.average(method, dataset, k)) for k in keys]
                    + [num(board.average(method, dataset, "avgerr")), num(board.average(method, dataset, "invalid")),
                       num(board.time(method, dataset, "seconds"), 3), num(board.time(method, dataset, "mde_per_s"), 1),
                       ratio(board, method, dataset)])
    return table(header, rows)


def per_scene(board: Board, dataset: str, key: str, *, weight: bool = False, ndisp: bool = False,
              default_time: bool = False) -> str:
    presets = board.presets()
    opencv = board.opencv()
    header = ["scene"] + (["weight"] if weight else []) + (["ndisp"] if ndisp else []) + presets + \
        [OPENCV[m] for m in opencv] + (["default ×3WAY"] if default_time else [])
    rows = []
    for scene in board.scenes(dataset):
        info = board.datasets[dataset]["scenes"][scene]
        row = [scene] + ([f"{info['weight']:g}"] if weight else []) + ([str(info["ndisp"])] if ndisp else [])
        row += [num(board.scene(f"stereocli {p}", dataset, scene, key)) for p in presets]
        row += [num(board.scene(m, dataset, scene, key)) for m in opencv]
        if default_time:
            row.append(num(board.scene("stereocli default", dataset, scene, "x3way")))
        rows.append(row)
    return table(header, rows)


def below_opencv(board: Board, preset: str) -> tuple[list[str], tuple[str, float, str, float] | None]:
    """MiddEval3 scenes where ``preset``'s bad-2.0 or bad-4.0 is not below every SGBM mode's, and
    the scene where its bad-2.0 comes closest to an SGBM mode's: (scene, its, mode, mode's)."""
    modes = [m for m in board.opencv() if "SGBM" in m]
    method = f"stereocli {preset}"
    losing, closest = [], None
    for scene in board.scenes("mb2014"):
        for key in ("bad2.0", "bad4.0"):
            own = board.scene(method, "mb2014", scene, key)
            if any(board.scene(m, "mb2014", scene, key) <= own for m in modes):
                losing.append(scene)
                break
        own = board.scene(method, "mb2014", scene, "bad2.0")
        best = min(modes, key=lambda m: board.scene(m, "mb2014", scene, "bad2.0"))
        other = board.scene(best, "mb2014", scene, "bad2.0")
        if closest is None or other - own < closest[3] - closest[1]:
            closest = (scene, own, OPENCV[best], other)
    return losing, closest


def mb2014_notes(board: Board) -> str:
    if not board.opencv():
        return ""
    losing, closest = below_opencv(board, "default")
    if not losing:
        scene, own, mode, other = closest
        return (f"Every scene's bad-2.0 and bad-4.0 of the default is below every OpenCV SGBM mode's; the closest "
                f"is {scene} ({own:.2f} against {mode}'s {other:.2f}).")
    return (f"The default's bad-2.0 and bad-4.0 are below every OpenCV SGBM mode's on "
            f"{len(board.scenes('mb2014')) - len(losing)} of the {len(board.scenes('mb2014'))} scenes "
            f"(not on {', '.join(losing)}).")


def pandora_note(board: Board) -> str:
    if board.entry(PANDORA, "mb2014") is None:
        return ""
    lower = [100 * (1 - board.average("stereocli default", "mb2014", k) / board.average(PANDORA, "mb2014", k))
             for k in ("bad2.0", "bad4.0")]
    return (f"The default's error rates are {lower[0]:.0f} % (bad-2.0) and {lower[1]:.0f} % (bad-4.0) lower than "
            f"Pandora's.")


def runs(board: Board) -> str:
    """The runs the tables come from."""
    used: dict[str, set[str]] = {}
    for datasets in board.methods.values():
        for entry in datasets.values():
            used.setdefault(entry["scores_run"], set()).add("scores")
            if entry.get("times_run"):
                used.setdefault(entry["times_run"], set()).add("times")
    lines = []
    for run_id, run in board.data["runs"].items():
        what = " and ".join(sorted(used.get(run_id, ())))
        threads = f"{run['threads']} thread{'s' if run['threads'] != 1 else ''}"
        machine = f"{run['cpu']}, {run['cores']} cores, {threads}, best of {run['repeat']}"
        date = f", {run['date']}" if run.get("date") else ""
        note = f" {run['note'][0].upper()}{run['note'][1:]}." if run.get("note") else ""
        lines.append(f"- `{run_id}` ({what}): `{run['command']}` on {machine}{date}.{note}")
    return "\n".join(lines)


def validation_summary(board: Board) -> str:
    return summary(board, "validation")


# --- README.md -------------------------------------------------------------------------------------


def pair_text(values: list[float | None], best: list[bool]) -> str:
    return " / ".join(f"**{num(v)}**" if b else num(v) for v, b in zip(values, best))


def readme_presets(board: Board) -> str:
    presets = [p for p in LADDER if p in board.presets()] + [p for p in board.presets() if p not in LADDER]
    columns = {p: ([board.average(f"stereocli {p}", "mb2014", k) for k in ("bad2.0", "bad4.0")],
                   [board.scene(f"stereocli {p}", "v2", s, "bad1.0") for s in V2_SCENES],
                   [board.average(f"stereocli {p}", "validation", "bad1.0")]) for p in presets}

    def best(i: int, j: int, value: float | None) -> bool:
        values = [columns[p][i][j] for p in presets if columns[p][i][j] is not None]
        return value is not None and value == min(values)

    rows = []
    for p in presets:
        pipeline, use = PRESET_ROWS.get(p, ("", ""))
        name = f"`{p}`" + (" (outside the ladder)" if p not in LADDER else "")
        cells = [pair_text(col, [best(i, j, v) for j, v in enumerate(col)]) for i, col in enumerate(columns[p])]
        rows.append([name, pipeline, *cells, ratio(board, f"stereocli {p}", "mb2014"), use])
    ref = "OpenCV SGBM 3WAY"
    if board.entry(ref, "mb2014"):
        rows.append([f"{ref} (reference)", "",
                     " / ".join(num(board.average(ref, "mb2014", k)) for k in ("bad2.0", "bad4.0")),
                     " / ".join(num(board.scene(ref, "v2", s, "bad1.0")) for s in V2_SCENES),
                     num(board.average(ref, "validation", "bad1.0")), ratio(board, ref, "mb2014"), ""])
    header = ["preset", "pipeline", "MiddEval3 bad-2.0 / bad-4.0", "v2 Tsukuba / Venus / Teddy / Cones",
              f"validation ({len(board.scenes('validation'))} scenes)", "× SGBM 3WAY", "use it for"]
    return "\n\n".join([table(header, rows), readme_ladder(board), readme_against_opencv(board)])


def _ladder_claim(values: list[float | None], *, falling: bool) -> bool:
    if any(v is None for v in values):
        return False
    return all((b < a) if falling else (b > a) for a, b in zip(values, values[1:]))


def readme_ladder(board: Board) -> str:
    ladder = [p for p in LADDER if p in board.presets()]
    m = [f"stereocli {p}" for p in ladder]
    bad2 = [board.average(x, "mb2014", "bad2.0") for x in m]
    v2 = [board.average(x, "v2", "bad1.0") for x in m]
    validation = [board.average(x, "validation", "bad1.0") for x in m]
    times = [board.time(x, "mb2014", "x3way") for x in m]
    order = ", ".join(f"`{p}`" for p in ladder)
    slower = _ladder_claim(times, falling=False)
    more_accurate = all(_ladder_claim(v, falling=True) for v in (bad2, v2, validation))
    claim = (" each preset is slower than the one before it and more accurate on MiddEval3, on the v2 average and "
             "on the validation mean" if slower and more_accurate else "")
    text = (f"Along the ladder ({order}){claim}: MiddEval3 bad-2.0 {' / '.join(num(v) for v in bad2)}; "
            f"v2 average {' / '.join(num(v) for v in v2)}; validation mean {' / '.join(num(v) for v in validation)} %.")
    d, q, a = "stereocli default", "stereocli quality", "stereocli accurate"
    if all(board.entry(x, "mb2014") for x in (d, q, a)):
        scenes = board.scenes("mb2014")
        q_wins = sum(all(board.scene(q, "mb2014", s, k) < board.scene(d, "mb2014", s, k) for k in ("bad2.0", "bad4.0"))
                     for s in scenes)
        a_wins = sum(board.scene(a, "mb2014", s, "bad2.0") < board.scene(d, "mb2014", s, "bad2.0") for s in scenes)
        q_time = board.time(q, "mb2014", "x3way") / board.time(d, "mb2014", "x3way")
        a_time = board.time(a, "mb2014", "x3way") / board.time(d, "mb2014", "x3way")
        q_where = ("every MiddEval3 scene" if q_wins == len(scenes)
                   else f"{q_wins} of the {len(scenes)} MiddEval3 scenes")
        text += (f" `quality` beats the default's bad-2.0 and bad-4.0 on {q_where} in {q_time:.1f}× its time; "
                 f"`accurate` ({a_time:.1f}×) its bad-2.0 on {a_wins} of the {len(scenes)}.")
    return text


def readme_against_opencv(board: Board) -> str:
    parts = []
    if board.opencv():
        losing, _ = below_opencv(board, "default")
        where = "every MiddEval3 scene" if not losing else \
            f"{len(board.scenes('mb2014')) - len(losing)} of the {len(board.scenes('mb2014'))} MiddEval3 scenes"
        parts.append(f"The default's bad-2.0 and bad-4.0 are below every OpenCV SGBM mode's on {where}")
    accurate = [board.scene("stereocli accurate", "v2", s, "bad1.0") for s in V2_SCENES]
    if all(v is not None for v in accurate) and all(v < p for v, p in zip(accurate, SGM_PAPER)):
        parts.append("`accurate`'s v2 scores are below Hirschmüller's SGM paper's "
                     f"({' / '.join(f'{p:.2f}' for p in SGM_PAPER)})")
    text = ", and ".join(parts) + "." if parts else ""
    per_pair = [board.scene("stereocli default", "mb2014", s, "x3way") for s in board.scenes("mb2014")]
    per_pair = [v for v in per_pair if v is not None]
    if per_pair:
        text += f" Per MiddEval3 pair the default takes {min(per_pair):.2f}–{max(per_pair):.2f}× SGBM 3WAY's time."
    entry = board.entry("stereocli default", "mb2014")
    run = board.data["runs"].get(entry.get("times_run") or entry["scores_run"]) if entry else None
    if run:
        threads = f"{run['threads']} thread{'s' if run['threads'] != 1 else ''}"
        text += (f" Times (× SGBM 3WAY) measured on {run['cpu']}, {run['cores']} cores, {threads}: the ratio "
                 "depends on the CPU, so measure yours with the harness.")
    return text.strip()


# --- configs/*.yaml --------------------------------------------------------------------------------


def preset_comment(board: Board, preset: str) -> str:
    method = f"stereocli {preset}"
    if board.entry(method, "mb2014") is None:
        return f"Not on the scoreboard yet ({SCOREBOARD.relative_to(REPO)})."
    bad = [num(board.average(method, "mb2014", k)) for k in ("bad2.0", "bad4.0")]
    v2 = "/".join(num(board.scene(method, "v2", s, "bad1.0")) for s in V2_SCENES)  # one word: wrapped whole
    text = (f"Scores: MiddEval3-Q {bad[0]} % bad-2.0 / {bad[1]} % bad-4.0 (weighted); Middlebury v2 {v2} % bad > 1 "
            f"(Tsukuba/Venus/Teddy/Cones); validation {num(board.average(method, 'validation', 'bad1.0'))} % "
            f"bad > 1 (mean of {len(board.scenes('validation'))} scenes not tuned on); time "
            f"{ratio(board, method, 'mb2014')}x OpenCV SGBM 3WAY's (MiddEval3-Q).")
    if preset != "default" and board.entry("stereocli default", "mb2014"):
        scenes = board.scenes("mb2014")
        better = [s for s in scenes if board.scene(method, "mb2014", s, "bad2.0")
                  < board.scene("stereocli default", "mb2014", s, "bad2.0")]
        if 0 < len(better) < len(scenes):
            others = [s for s in scenes if s not in better]
            text += (f" bad-2.0 below the default's on {len(better)} of the {len(scenes)} MiddEval3 scenes"
                     + (f" (not on {', '.join(others)})." if len(others) <= 4 else "."))
        elif len(better) == len(scenes):
            text += " bad-2.0 below the default's on every MiddEval3 scene."
    text += f" From {SCOREBOARD.relative_to(REPO)}."
    return text


# --- blocks ----------------------------------------------------------------------------------------


def renderers() -> dict[str, Callable[[Board], str]]:
    out: dict[str, Callable[[Board], str]] = {
        "runs": runs,
        "mb2014-summary": lambda b: "\n\n".join(filter(None, [summary(b, "mb2014"), pandora_note(b)])),
        "mb2014-bad2": lambda b: per_scene(b, "mb2014", "bad2.0", weight=True, default_time=True),
        "mb2014-bad4": lambda b: "\n\n".join(filter(None, [per_scene(b, "mb2014", "bad4.0", weight=True),
                                                          mb2014_notes(b)])),
        "v2-summary": lambda b: summary(b, "v2"),
        "v2-bad1": lambda b: per_scene(b, "v2", "bad1.0", default_time=True),
        "v2-bad2": lambda b: per_scene(b, "v2", "bad2.0"),
        "validation-summary": validation_summary,
        "validation-bad1": lambda b: per_scene(b, "validation", "bad1.0", ndisp=True),
        "presets": readme_presets,
    }
    for preset in PRESETS:
        out[f"preset {preset}"] = lambda b, preset=preset: preset_comment(b, preset)
    return out


MARKDOWN_BLOCK = re.compile(r"(<!-- scoreboard: (?P<name>[^>]+?) -->\n)(?P<body>.*?)(<!-- /scoreboard -->)", re.S)
YAML_BLOCK = re.compile(r"(# scoreboard: (?P<name>.+?)\n)(?P<body>(?:#.*\n)*?)(# /scoreboard\n)")
#: Documents and the blocks each must hold.
DOCUMENTS = {
    "README.md": ("presets",),
    "docs/benchmarks.md": ("runs", "mb2014-summary", "mb2014-bad2", "mb2014-bad4", "v2-summary", "v2-bad1", "v2-bad2",
                           "validation-summary", "validation-bad1"),
    **{f"configs/{p}.yaml": (f"preset {p}",) for p in PRESETS},
}


def render_text(text: str, board: Board, *, yaml: bool, where: str) -> str:
    """``text`` with each of its blocks rewritten; unknown block names are errors."""
    known = renderers()

    def replace(match: re.Match) -> str:
        name = match.group("name").strip()
        if name not in known:
            raise SystemExit(f"{where}: unknown scoreboard block {name!r}; known: {', '.join(known)}")
        body = known[name](board)
        if yaml:
            lines = textwrap.wrap(body, width=98, break_on_hyphens=False)
            return match.group(1) + "".join(f"# {line}\n" for line in lines) + match.group(4)
        chunks = [chunk if chunk.startswith(("|", "- ")) else textwrap.fill(chunk, width=96, break_on_hyphens=False)
                  for chunk in body.split("\n\n")]
        return match.group(1) + "\n\n".join(chunks) + "\n" + match.group(4)

    return (YAML_BLOCK if yaml else MARKDOWN_BLOCK).sub(replace, text)


def block_names(text: str, *, yaml: bool) -> list[str]:
    return [m.group("name").strip() for m in (YAML_BLOCK if yaml else MARKDOWN_BLOCK).finditer(text)]


def render_all(repo: Path = REPO, scoreboard: Path | None = None) -> dict[str, tuple[str, str]]:
    """``{document: (text now, text as generated)}``; raises ``SystemExit`` when a document lacks a block."""
    board = Board(json.loads((scoreboard or repo / "benchmarks" / "results" / "scoreboard.json").read_text()))
    out = {}
    for name, required in DOCUMENTS.items():
        path = repo / name
        text = path.read_text(encoding="utf-8")
        yaml = path.suffix == ".yaml"
        missing = [b for b in required if b not in block_names(text, yaml=yaml)]
        if missing:
            raise SystemExit(f"{name}: no scoreboard block {', '.join(missing)}")
        out[name] = (text, render_text(text, board, yaml=yaml, where=name))
    return out


def stale(repo: Path = REPO) -> list[str]:
    """Documents whose blocks are not what :func:`render_all` writes."""
    return [name for name, (now, generated) in render_all(repo).items() if now != generated]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="list the documents that differ (exit 1); write nothing")
    args = ap.parse_args(argv)
    documents = render_all()
    changed = [name for name, (now, generated) in documents.items() if now != generated]
    if args.check:
        for name in changed:
            print(f"{name}: scoreboard blocks differ (run python benchmarks/render_docs.py)")
        return 1 if changed else 0
    for name in changed:
        (REPO / name).write_text(documents[name][1], encoding="utf-8")
        print(f"rewrote {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
