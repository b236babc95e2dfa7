"""Pairing calibration photos: ``left/`` + ``right/`` subfolders, or ``left*``/``right*`` names.

Pairs are keyed by the file stem with the side word removed (``left01.jpg`` ↔ ``right01.jpg``,
``left/cam_0003.png`` ↔ ``right/cam_0003.png``, ``img_left_7`` ↔ ``img_right_7``). A file
without a partner is an error (the counts must match), named in the message.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..errors import DataError
from ..io.images import IMAGE_SUFFIXES

_SIDE_WORD = re.compile(r"(left|right)", re.IGNORECASE)


def _side_key(stem: str) -> tuple[str | None, str]:
    m = _SIDE_WORD.search(stem)
    if not m:
        return None, stem
    key = (stem[: m.start()] + stem[m.end():]).strip("_-. ")
    return m.group(1).lower(), key


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _natural(key: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key)]


def find_calibration_pairs(folder: str | Path) -> list[tuple[str, str, str]]:
    """``(name, left_path, right_path)`` pairs in ``folder`` (sorted naturally by name)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: not a folder (calibrate expects a folder with left/ + right/ or left*/right* images)")
    left_dir, right_dir = folder / "left", folder / "right"
    lefts: dict[str, Path] = {}
    rights: dict[str, Path] = {}
    if left_dir.is_dir() and right_dir.is_dir():
        for side, d, table in (("left", left_dir, lefts), ("right", right_dir, rights)):
            for p in _images(d):
                key = _side_key(p.stem)[1] if _side_key(p.stem)[0] == side else p.stem
                table[key or p.stem] = p
    else:
        for p in _images(folder):
            side, key = _side_key(p.stem)
            if side == "left":
                lefts[key] = p
            elif side == "right":
                rights[key] = p
        if not lefts and not rights:
            raise DataError(f"{folder}: no calibration images (expected left/ + right/ subfolders or left*/right* files)")
    only_left = sorted(lefts.keys() - rights.keys(), key=_natural)
    only_right = sorted(rights.keys() - lefts.keys(), key=_natural)
    if only_left or only_right:
        first = lefts[only_left[0]] if only_left else rights[only_right[0]]
        raise DataError(
            f"{folder}: {len(lefts)} left and {len(rights)} right images do not pair up "
            f"({first.name} has no partner; {len(only_left) + len(only_right)} unpaired in all)")
    if not lefts:
        raise DataError(f"{folder}: no calibration image pairs")
    return [(k, str(lefts[k]), str(rights[k])) for k in sorted(lefts, key=_natural)]
