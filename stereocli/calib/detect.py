"""Detect the target in many images in parallel, with a cache keyed by file identity.

Detection is the slow part of calibration and does not depend on the calibration flags, so
results are cached in a JSON file keyed by ``absolute path | mtime_ns | size | pattern key |
detector``; re-running ``calibrate`` with other flags re-uses them. A changed image (new
mtime or size) is detected again.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io.atomic import write_text
from ..io.images import read_image
from .pattern import Pattern, detect

CACHE_VERSION = 1


@dataclass
class Detection:
    """The target in one image: corners (N, 2) float32 px and optional ids, or a failure reason."""

    path: str
    size: tuple[int, int]  # (width, height)
    corners: np.ndarray | None = None
    ids: np.ndarray | None = None
    reason: str = ""
    cached: bool = False

    @property
    def found(self) -> bool:
        return self.corners is not None

    def to_json(self) -> dict:
        return {"size": list(self.size), "reason": self.reason,
                "corners": None if self.corners is None else self.corners.round(5).tolist(),
                "ids": None if self.ids is None else self.ids.tolist()}

    @classmethod
    def from_json(cls, path: str, d: dict) -> Detection:
        return cls(path=path, size=tuple(d["size"]), reason=d.get("reason", ""),
                   corners=None if d.get("corners") is None else np.asarray(d["corners"], dtype=np.float32),
                   ids=None if d.get("ids") is None else np.asarray(d["ids"], dtype=np.int32), cached=True)


def cache_key(path: str | os.PathLike, pattern: Pattern, detector: str) -> str:
    p = Path(path).resolve()
    st = p.stat()
    return f"{p}|{st.st_mtime_ns}|{st.st_size}|{pattern.key}|{detector}"


def _load_cache(cache: Path | None) -> dict:
    try:
        if cache is None or not cache.is_file():
            return {}
        data = json.loads(cache.read_text())
    except (OSError, ValueError):
        return {}  # a damaged or unreadable cache is only a lost speed-up
    if not isinstance(data, dict) or data.get("version") != CACHE_VERSION or not isinstance(data.get("entries"), dict):
        return {}
    return data["entries"]


def _cached(path: str, entry) -> Detection | None:
    """The cached detection of ``path``, or None when absent or damaged (detected again)."""
    if not isinstance(entry, dict):
        return None
    try:
        det = Detection.from_json(path, entry)
        w, h = det.size
        ok = det.corners is None or (det.corners.ndim == 2 and det.corners.shape[1] == 2
                                     and np.isfinite(det.corners).all())
        ok = ok and (det.ids is None or det.corners is not None and det.ids.shape == (det.corners.shape[0],))
        return det if ok and int(w) > 0 and int(h) > 0 and isinstance(det.reason, str) else None
    except (KeyError, TypeError, ValueError):
        return None


def _detect_one(path: str, pattern: Pattern, detector: str) -> Detection:
    image = read_image(path, gray=True)
    h, w = image.shape[:2]
    smallest = 3 * (min(pattern.cols, pattern.rows) + 1)  # a few pixels a square at least
    if min(w, h) < smallest:
        return Detection(path=path, size=(w, h), reason=f"{w}x{h} px is too small for a {pattern.cols}x{pattern.rows} "
                                                        f"target (at least {smallest} px a side)")
    try:
        corners, ids, reason = detect(image, pattern, detector=detector)
    except Exception as exc:  # noqa: BLE001 - an OpenCV failure on one image is that image's reason
        corners, ids, reason = None, None, f"detector failed ({type(exc).__name__}: {str(exc).strip()[:80]})"
    return Detection(path=path, size=(w, h), corners=corners, ids=ids, reason=reason)


def detect_all(paths: list[str], pattern: Pattern, *, detector: str = "auto", jobs: int | None = None,
               cache: str | os.PathLike | None = None, progress: bool | None = None,
               warnings: list[str] | None = None) -> dict[str, Detection]:
    """Detect ``pattern`` in every image (threads: OpenCV releases the GIL); returns path → Detection.

    Unreadable images raise :class:`DataError` naming the file. A cache that cannot be written
    is only a lost speed-up: detection goes on, and a line saying so is added to ``warnings``.
    """
    from tqdm import tqdm

    cache_path = Path(cache) if cache else None
    entries = _load_cache(cache_path)
    out: dict[str, Detection] = {}
    keys = {}
    todo = []
    for p in paths:
        if not Path(p).is_file():
            raise DataError(f"{p}: no such file")
        keys[p] = cache_key(p, pattern, detector)
        cached = _cached(p, entries.get(keys[p]))
        if cached is not None:
            out[p] = cached
        else:
            todo.append(p)
    if todo:
        jobs = jobs or os.cpu_count() or 1
        enabled = sys.stderr.isatty() if progress is None else progress
        bar = tqdm(total=len(todo), desc="detect", unit="img", file=sys.stderr, disable=not enabled)
        try:
            with cf.ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
                futures = {pool.submit(_detect_one, p, pattern, detector): p for p in todo}
                try:
                    for fut in cf.as_completed(futures):
                        det = fut.result()
                        out[det.path] = det
                        bar.update(1)
                except BaseException:  # Ctrl-C or a bad image: do not wait for the queued images
                    pool.shutdown(wait=False, cancel_futures=True)
                    raise
        finally:
            bar.close()
        if cache_path is not None:
            for p in todo:
                entries[keys[p]] = out[p].to_json()
            try:
                write_text(cache_path, json.dumps({"version": CACHE_VERSION, "entries": entries}) + "\n")
            except (OSError, DataError) as exc:
                reason = exc.strerror if isinstance(exc, OSError) else str(exc).removeprefix(f"{cache_path}: ")
                if warnings is not None:
                    warnings.append(f"{cache_path}: detection cache not written ({reason}); the next run detects "
                                    "again (--cache FILE puts it elsewhere)")
    return {p: out[p] for p in paths}
