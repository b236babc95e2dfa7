"""Versions and run records (what ran, with which config, how long) for reproducibility."""

from __future__ import annotations

import json
import platform
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from . import __version__
from .io.atomic import write_text

_DEPENDENCIES = ("numpy", "opencv-python-headless", "numba", "llvmlite", "click", "tqdm", "imageio", "PyYAML")


def versions() -> dict[str, str]:
    """stereocli, Python, platform and dependency versions."""
    out = {"stereocli": __version__, "python": sys.version.split()[0], "platform": platform.platform()}
    for dist in _DEPENDENCIES:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


class RunRecord:
    """Collects per-item status and timings; written as ``run.json`` beside the outputs."""

    def __init__(self, command: str, argv: list[str], config: dict | None = None) -> None:
        started = time.strftime("%Y-%m-%dT%H:%M:%S%z")  # create the record before the batch runs
        self._t0 = time.perf_counter()
        self.data: dict[str, Any] = {
            "command": command,
            "argv": argv,
            "versions": versions(),
            "started": started,
            "config": config,
            "items": [],
            "interrupted": False,
        }

    def add_item(self, item: dict) -> None:
        self.data["items"].append(item)

    def interrupted(self, signal_name: str, total: int) -> None:
        """Mark the run as stopped by ``signal_name`` with ``total`` items planned (``items`` holds
        the ones that finished)."""
        self.data.update(interrupted=True, signal=signal_name, planned=total)

    def write(self, path: str | Path) -> None:
        """Write ``run.json``; ``seconds`` runs from the record's creation (before the batch).

        The records of earlier runs in the same folder that made outputs still there (their
        ``ok`` items no later run made again) are kept in ``previous``, oldest first, and each
        item this run skipped names the run that made it (``made_by``: that run's ``started``).
        So resuming with ``--skip-existing`` never loses the record of the run behind the outputs.
        """
        items = self.data["items"]
        self.data["seconds"] = round(time.perf_counter() - self._t0, 4)
        self.data["summary"] = {
            status: sum(1 for i in items if i.get("status") == status) for status in ("ok", "skipped", "failed")
        }
        self.data.pop("previous", None)
        self.data.pop("previous_unreadable", None)
        earlier, problem = _earlier_runs(Path(path))
        kept = _runs_behind_outputs(earlier, items)
        for item in items:
            if item.get("status") == "skipped":
                maker = next((run for run in reversed(kept) if _made(run, item.get("name"))), None)
                if maker is not None:
                    item["made_by"] = maker.get("started")
        if kept:
            self.data["previous"] = kept
        if problem:
            self.data["previous_unreadable"] = problem
        write_text(path, json.dumps(self.data, indent=2, default=_json_default) + "\n")


def _made(run: dict, name: str | None) -> bool:
    """Whether ``run`` made item ``name`` (status ok)."""
    return any(i.get("name") == name and i.get("status") == "ok" for i in run.get("items", ()))


def _earlier_runs(path: Path) -> tuple[list[dict], str]:
    """The records in an existing ``run.json`` (its ``previous`` runs, then itself), oldest first,
    and why it could not be read ("" when it could, or there is none)."""
    if not path.is_file():
        return [], ""
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return [], f"{path.name} of an earlier run could not be read ({type(exc).__name__}); its record is lost"
    if not isinstance(old, dict):
        return [], f"{path.name} of an earlier run holds no run record; its record is lost"
    previous = [run for run in old.pop("previous", []) if isinstance(run, dict)]
    old.pop("previous_unreadable", None)
    return previous + [old], ""


def _runs_behind_outputs(runs: list[dict], newest_items: list[dict]) -> list[dict]:
    """Of ``runs`` (oldest first), those that made an item no later run (nor the newest, whose
    items are ``newest_items``) made again: the runs whose outputs are still in the folder."""
    remade = {i.get("name") for i in newest_items if i.get("status") == "ok"}
    kept = []
    for run in reversed(runs):
        made = {i.get("name") for i in run.get("items", ()) if isinstance(i, dict) and i.get("status") == "ok"}
        if made - remade:
            kept.append(run)
        remade |= made
    return kept[::-1]


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)
