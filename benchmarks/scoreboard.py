"""The scoreboard: ``benchmarks/results/scoreboard.json``, the one source of the published scores.

``benchmarks/accuracy.py --scoreboard`` writes it; ``benchmarks/render_docs.py`` writes the score
tables of the README, ``docs/benchmarks.md`` and the presets' comments from it. Layout::

    {"about": "...",
     "runs": {"<id>": {"command", "date", "cpu", "cores", "threads", "repeat", "versions", "note"}},
     "datasets": {"mb2014" | "v2" | "validation": {"title", "scenes": {name: {"weight", "ndisp"}}}},
     "methods": {"stereocli default" | "OpenCV SGBM 3WAY" | ...: {dataset: {
         "scores_run": id, "times_run": id or null, "in_turns": bool,
         "average": {"bad1.0", "bad2.0", ["bad4.0"], "avgerr", "invalid"},
         "time": {"seconds", "mde_per_s", "x3way"} or null,
         "scenes": {name: {"bad1.0", ..., "seconds", "x3way"}}}}}}

Scores are nonocc percentages (``avgerr`` in px) by the rules of the dataset's title; ``average``
is MiddEval3's weighted average, the plain mean elsewhere. ``time.x3way`` is the method's time
over OpenCV SGBM 3WAY's on the same pairs in the same rounds (``in_turns``), summed over the
dataset's scenes. A run that measures only some methods or datasets replaces those entries and
keeps the others, each naming the run its scores and its times come from.
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
from pathlib import Path

PATH = Path(__file__).resolve().parent / "results" / "scoreboard.json"
ABOUT = ("Scores of benchmarks/accuracy.py, written by `accuracy.py --scoreboard`; the README's preset table, "
         "docs/benchmarks.md's score tables and the presets' score comments are written from this file by "
         "`python benchmarks/render_docs.py`. Each entry names the run (runs) its scores and its times come from.")
#: Digits kept in the file (the documents show two).
DIGITS = 4


def load(path: Path = PATH) -> dict:
    """The scoreboard at ``path``, or an empty one."""
    if path.is_file():
        return json.loads(path.read_text())
    return {"about": ABOUT, "runs": {}, "datasets": {}, "methods": {}}


def save(board: dict, path: Path = PATH) -> None:
    """Write ``board`` to ``path`` (a temporary file renamed over it), keeping only the runs an entry names."""
    used = {entry.get(key) for datasets in board["methods"].values() for entry in datasets.values()
            for key in ("scores_run", "times_run")}
    board["runs"] = {run_id: run for run_id, run in board["runs"].items() if run_id in used}
    path.parent.mkdir(parents=True, exist_ok=True)
    text = _dump(_rounded(board)) + "\n"
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".scoreboard-")
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(text)
    os.replace(tmp, path)


def _dump(value, depth: int = 0) -> str:
    """JSON with one line per mapping of plain values (a scene's scores), indented above that."""
    if not isinstance(value, dict) or not any(isinstance(v, (dict, list)) for v in value.values()):
        return json.dumps(value, ensure_ascii=False)
    pad = " " * (depth + 1)
    items = [f"{pad}{json.dumps(k, ensure_ascii=False)}: {_dump(v, depth + 1)}" for k, v in value.items()]
    return "{\n" + ",\n".join(items) + "\n" + " " * depth + "}"


def _rounded(value):
    if isinstance(value, float):
        return round(value, DIGITS)
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else what the platform module says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def new_run(board: dict, *, command: str, threads: int, repeat: int, versions: dict, date: str,
            note: str = "") -> str:
    """Add a run record to ``board``; returns its id."""
    number = 1 + max((int(k.split("-")[-1]) for k in board["runs"] if k.split("-")[-1].isdigit()), default=0)
    run_id = f"run-{number}"
    board["runs"][run_id] = {"command": command, "date": date, "cpu": cpu_model(), "cores": os.cpu_count(),
                             "threads": threads, "repeat": repeat, "versions": versions, "note": note}
    return run_id


def record(board: dict, method: str, dataset: str, *, run_id: str, average: dict, scenes: dict,
           time: dict | None, in_turns: bool, keep_times: bool) -> None:
    """Put one method's scores on one dataset into ``board``.

    ``scenes`` maps a scene to its scores, ``seconds`` and ``x3way``; ``time`` is the dataset's
    ``seconds``, ``mde_per_s`` and ``x3way``. With ``keep_times`` the times of the entry being
    replaced stay (with the run they came from), and an entry without any has none.
    """
    old = board["methods"].get(method, {}).get(dataset)
    entry = {"scores_run": run_id, "times_run": run_id, "in_turns": in_turns, "average": average,
             "time": time, "scenes": scenes}
    if keep_times:
        old_scenes = (old or {}).get("scenes", {})
        entry.update(times_run=(old or {}).get("times_run"), time=(old or {}).get("time"),
                     in_turns=(old or {}).get("in_turns", in_turns))
        for name, values in scenes.items():
            kept = old_scenes.get(name, {})
            values.update(seconds=kept.get("seconds"), x3way=kept.get("x3way"))
    board["methods"].setdefault(method, {})[dataset] = entry
