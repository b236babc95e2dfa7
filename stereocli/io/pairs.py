"""Finding stereo pairs in what the user passed on the command line.

Accepted forms (mixed freely):

* two image files: ``left.png right.png`` (named by the left file's stem);
* a scene folder holding a known left/right pair (``im0/im1`` Middlebury 2014, ``im2/im6``
  2001/2003, ``im3/im4`` Tsukuba copy, ``left/right``), with optional ``calib.txt`` and valid
  masks ``valid0.png``/``valid1.png`` written by ``rectify`` (named by the folder);
* a folder of scene folders;
* a folder with ``left/`` and ``right/`` subfolders, or the two folders themselves, paired by
  file stem (``left/0001.png`` with ``right/0001.png``; a ``left_``/``right_`` or
  ``_left``/``_right`` prefix or suffix on the stem is ignored for pairing).

Files that cannot be paired are returned as problems (the caller reports them as failed
items), never dropped silently.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import DataError
from .images import IMAGE_SUFFIXES

#: Known (left, right) file stems inside a scene folder, in priority order.
SCENE_PAIRS = (("im0", "im1"), ("im2", "im6"), ("im3", "im4"), ("left", "right"), ("view1", "view5"))


@dataclass
class StereoInput:
    """One pair to process. Paths are strings so items pickle cheaply."""

    name: str
    left: str
    right: str
    calib: str | None = None  # Middlebury calib.txt, when present
    left_valid: str | None = None  # valid-pixel mask (255 = valid) from rectify
    right_valid: str | None = None
    folder: str | None = None  # the scene folder, when the pair came from one
    extra: dict = field(default_factory=dict)


def _images(folder: Path) -> dict[str, Path]:
    return {p.stem: p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES}


def scene_pair(folder: Path) -> StereoInput | None:
    """The pair inside a scene folder, or None when the folder is not a scene."""
    images = _images(folder)
    for left, right in SCENE_PAIRS:
        if left in images and right in images:
            calib = folder / "calib.txt"
            v0, v1 = folder / "valid0.png", folder / "valid1.png"
            return StereoInput(
                name=folder.name,
                left=str(images[left]),
                right=str(images[right]),
                calib=str(calib) if calib.is_file() else None,
                left_valid=str(v0) if v0.is_file() else None,
                right_valid=str(v1) if v1.is_file() else None,
                folder=str(folder),
            )
    return None


_SIDE = re.compile(r"(^(left|right|l|r)[_-]?)|([_-]?(left|right|l|r)$)", re.IGNORECASE)


def _pair_key(stem: str) -> str:
    return _SIDE.sub("", stem) or stem


def pair_folders(left_dir: Path, right_dir: Path) -> tuple[list[StereoInput], list[str]]:
    """Pair ``left_dir`` and ``right_dir`` images by stem; returns pairs and unpaired-file problems."""
    lefts = {_pair_key(s): p for s, p in _images(left_dir).items()}
    rights = {_pair_key(s): p for s, p in _images(right_dir).items()}
    pairs = [StereoInput(name=k, left=str(lefts[k]), right=str(rights[k])) for k in sorted(lefts.keys() & rights.keys())]
    problems = [f"{lefts[k]}: no matching right image in {right_dir}" for k in sorted(lefts.keys() - rights.keys())]
    problems += [f"{rights[k]}: no matching left image in {left_dir}" for k in sorted(rights.keys() - lefts.keys())]
    return pairs, problems


def discover_pairs(inputs: list[str] | tuple[str, ...]) -> tuple[list[StereoInput], list[str]]:
    """Resolve command-line inputs into stereo pairs.

    Returns ``(pairs, problems)``; raises :class:`DataError` when an input does not exist or
    nothing at all can be paired. Pair names are unique (a clash is an error, since outputs
    are written to ``OUTDIR/<name>/``).
    """
    paths = [Path(p) for p in inputs]
    for p in paths:
        if not p.exists():
            raise DataError(f"{p}: no such file or folder")
    pairs: list[StereoInput] = []
    problems: list[str] = []
    files = [p for p in paths if p.is_file()]
    folders = [p for p in paths if p.is_dir()]
    if files:
        if len(files) % 2:
            raise DataError(f"{files[-1]}: image files must be given in left/right pairs")
        for left, right in zip(files[0::2], files[1::2]):
            pairs.append(StereoInput(name=left.stem, left=str(left), right=str(right)))
    if len(folders) == 2 and not any(scene_pair(f) or _has_subfolders(f) for f in folders):
        # Two plain folders of images: left/ and right/.
        found, bad = pair_folders(folders[0], folders[1])
        pairs += found
        problems += bad
        folders = []
    for folder in folders:
        found, bad = _discover_folder(folder)
        pairs += found
        problems += bad
    if not pairs:
        raise DataError(
            f"{', '.join(map(str, inputs))}: no stereo pairs found"
            + (f" ({problems[0]})" if problems else " (expected im0/im1 scene folders, left/ + right/ folders or image pairs)")
        )
    seen: dict[str, str] = {}
    for pair in pairs:
        if pair.name in seen:
            raise DataError(f"two pairs are both named {pair.name!r} ({seen[pair.name]} and {pair.left}); outputs would clash")
        seen[pair.name] = pair.left
    return pairs, problems


def _has_subfolders(folder: Path) -> bool:
    return any(p.is_dir() for p in folder.iterdir())


def _discover_folder(folder: Path) -> tuple[list[StereoInput], list[str]]:
    scene = scene_pair(folder)
    if scene:
        return [scene], []
    left, right = folder / "left", folder / "right"
    if left.is_dir() and right.is_dir():
        return pair_folders(left, right)
    pairs, problems = [], []
    subdirs = sorted(p for p in folder.iterdir() if p.is_dir())
    for sub in subdirs:
        scene = scene_pair(sub)
        if scene:
            pairs.append(scene)
        elif _images(sub):
            problems.append(f"{sub}: holds images but no recognised left/right pair ({_pair_names()})")
    if not subdirs and _images(folder):
        problems.append(f"{folder}: holds images but no recognised left/right pair ({_pair_names()})")
    if not subdirs and not _images(folder):
        raise DataError(f"{folder}: empty folder (no images or scene folders)")
    return pairs, problems


def _pair_names() -> str:
    return ", ".join(f"{a}/{b}" for a, b in SCENE_PAIRS)


def common_root(paths: list[str]) -> str:
    return os.path.commonpath(paths) if paths else ""
