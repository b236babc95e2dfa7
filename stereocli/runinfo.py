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
        """Write ``run.json``; ``seconds`` runs from the record's creation (before the batch)."""
        items = self.data["items"]
        self.data["seconds"] = round(time.perf_counter() - self._t0, 4)
        self.data["summary"] = {
            status: sum(1 for i in items if i.get("status") == status) for status in ("ok", "skipped", "failed")
        }
        write_text(path, json.dumps(self.data, indent=2, default=_json_default) + "\n")


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)
