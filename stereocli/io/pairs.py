"""Finding stereo pairs in what the user passed on the command line: every pairing rule.

Accepted forms (mixed freely):

* two image files: ``left.png right.png`` (named by the left file's stem); two files of a scene
  folder named as a scene pair (``DIR/im0.png DIR/im1.png``) are that scene: named by the folder,
  with its ``calib.txt`` and valid masks;
* a scene folder holding a known left/right pair (``im0/im1`` Middlebury 2014, ``im2/im6``
  2001/2003, ``im3/im4`` Tsukuba copy, ``left/right``), with optional ``calib.txt`` and valid
  masks ``valid0.png``/``valid1.png`` written by ``rectify`` (named by the folder);
* a folder of scene folders;
* a folder with ``left/`` and ``right/`` subfolders, or the two folders themselves, paired by
  file stem (``left/0001.png`` with ``right/0001.png``; a ``left_``/``right_`` or
  ``_left``/``_right`` prefix or suffix on the stem is ignored for pairing);
* calibration photos (:func:`find_calibration_pairs`; ``rectify`` with ``side_words``): a
  folder of ``left*``/``right*`` files keyed by the stem with the side word removed
  (``left01.jpg`` ↔ ``right01.jpg``, ``img_left_7`` ↔ ``img_right_7``), or ``left/`` +
  ``right/`` subfolders keyed the same way, in natural order (``2`` before ``10``).

Files that cannot be paired are returned as problems (the caller reports them as failed
items), never dropped silently; calibration photos without a partner are an error.

A pair's name is its output folder's name (``OUTDIR/<name>/``), made safe by :func:`output_name`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import DataError
from .images import IMAGE_SUFFIXES

#: Names a batch keeps for itself in its output folder: the run record. (Its lock, staging folder
#: and completion markers start with a dot, which no output name does.)
RESERVED_NAMES = ("run.json",)
#: Characters an output name never holds: path separators and control characters (line breaks
#: included), which would break paths, one-line messages and text tables.
_UNSAFE = re.compile(r"[/\\\x00-\x1f\x7f-\x9f\u2028\u2029]")

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


def output_name(name: str) -> str:
    """``name`` made safe as one folder name inside an output folder: path separators and
    control characters become ``_``, and so do leading dots (no ``.``, ``..`` or hidden name,
    which could land outside OUTDIR, in its root, or on the batch's own dot-files); an empty
    name becomes ``_`` and a reserved one (:data:`RESERVED_NAMES`) gets a leading ``_``.
    Other names are kept as they are (``...`` -> ``___``, ``run.json`` -> ``_run.json``)."""
    safe = _UNSAFE.sub("_", name)
    stripped = safe.lstrip(".")
    safe = "_" * (len(safe) - len(stripped)) + stripped
    if not safe:
        return "_"
    return f"_{safe}" if safe.casefold() in RESERVED_NAMES else safe


def unique_names(named: list[tuple[str, str]]) -> None:
    """Raise :class:`DataError` when two of ``(name, source)`` share a name (their outputs
    would clash in ``OUTDIR/<name>/``), naming both sources."""
    seen: dict[str, str] = {}
    for name, source in named:
        if name in seen:
            raise DataError(f"two inputs are both named {name!r} ({seen[name]} and {source}); "
                            "their outputs would clash")
        seen[name] = source


def image_files(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _by_stem(folder: Path) -> dict[str, Path]:
    return {p.stem: p for p in image_files(folder)}


# --------------------------------------------------------------------------- scene folders

def scene_pair(folder: Path) -> StereoInput | None:
    """The pair inside a scene folder, or None when the folder is not a scene."""
    images = _by_stem(folder)
    for left, right in SCENE_PAIRS:
        if left in images and right in images:
            return _scene_input(folder, images[left], images[right])
    return None


def _scene_input(folder: Path, left: Path, right: Path) -> StereoInput:
    """The pair ``left``/``right`` of scene folder ``folder``, with its calib.txt and valid masks."""
    calib = folder / "calib.txt"
    v0, v1 = folder / "valid0.png", folder / "valid1.png"
    return StereoInput(
        name=folder.resolve().name,
        left=str(left),
        right=str(right),
        calib=str(calib) if calib.is_file() else None,
        left_valid=str(v0) if v0.is_file() else None,
        right_valid=str(v1) if v1.is_file() else None,
        folder=str(folder),
    )


def file_pair(left: Path, right: Path) -> StereoInput:
    """Two image files given on the command line: the scene they belong to when they sit in one
    folder under a scene pair's names (``im0``/``im1``, ``left``/``right``, ...), else a pair
    named by the left file's stem."""
    if left.parent.resolve() == right.parent.resolve() and (left.stem, right.stem) in SCENE_PAIRS:
        return _scene_input(left.parent, left, right)
    return StereoInput(name=left.stem, left=str(left), right=str(right))


def _pair_names() -> str:
    return ", ".join(f"{a}/{b}" for a, b in SCENE_PAIRS)


# --------------------------------------------------------------------------- left/ + right/ folders by stem

_SIDE_AFFIX = re.compile(r"(^(left|right|l|r)[_-]?)|([_-]?(left|right|l|r)$)", re.IGNORECASE)


def _stem_key(stem: str) -> str:
    return _SIDE_AFFIX.sub("", stem) or stem


def pair_folders(left_dir: Path, right_dir: Path) -> tuple[list[StereoInput], list[str]]:
    """Pair ``left_dir`` and ``right_dir`` images by stem; returns pairs and unpaired-file problems."""
    lefts = {_stem_key(s): p for s, p in _by_stem(left_dir).items()}
    rights = {_stem_key(s): p for s, p in _by_stem(right_dir).items()}
    pairs = [StereoInput(name=k, left=str(lefts[k]), right=str(rights[k])) for k in sorted(lefts.keys() & rights.keys())]
    problems = [f"{lefts[k]}: no matching right image in {right_dir}" for k in sorted(lefts.keys() - rights.keys())]
    problems += [f"{rights[k]}: no matching left image in {left_dir}" for k in sorted(rights.keys() - lefts.keys())]
    return pairs, problems


# --------------------------------------------------------------------------- side words (calibration photos)

_SIDE_WORD = re.compile(r"(left|right)", re.IGNORECASE)


def side_key(stem: str) -> tuple[str | None, str]:
    """``(side, key)``: the first side word of ``stem`` (``"left"``/``"right"``, None without
    one) and the stem without it (``"img_left_7"`` -> ``("left", "img_7")``)."""
    m = _SIDE_WORD.search(stem)
    if not m:
        return None, stem
    key = (stem[: m.start()] + stem[m.end():]).strip("_-. ")
    return m.group(1).lower(), key


def natural_key(key: str) -> list:
    """Sort key that orders digit runs by value (``2`` before ``10``)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key)]


def find_calibration_pairs(folder: str | Path) -> list[tuple[str, str, str]]:
    """``(name, left_path, right_path)`` pairs in ``folder`` (sorted naturally by name).

    Raises :class:`DataError` when a photo has no partner or nothing pairs.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: not a folder (calibrate expects a folder with left/ + right/ or left*/right* images)")
    left_dir, right_dir = folder / "left", folder / "right"
    lefts: dict[str, Path] = {}
    rights: dict[str, Path] = {}
    if left_dir.is_dir() and right_dir.is_dir():
        for side, d, table in (("left", left_dir, lefts), ("right", right_dir, rights)):
            for p in image_files(d):
                found, key = side_key(p.stem)
                table[(key if found == side else p.stem) or p.stem] = p
    else:
        for p in image_files(folder):
            side, key = side_key(p.stem)
            if side == "left":
                lefts[key] = p
            elif side == "right":
                rights[key] = p
        if not lefts and not rights:
            raise DataError(f"{folder}: no calibration images (expected left/ + right/ subfolders or left*/right* files)")
    only_left = sorted(lefts.keys() - rights.keys(), key=natural_key)
    only_right = sorted(rights.keys() - lefts.keys(), key=natural_key)
    if only_left or only_right:
        first = lefts[only_left[0]] if only_left else rights[only_right[0]]
        raise DataError(
            f"{folder}: {len(lefts)} left and {len(rights)} right images do not pair up "
            f"({first.name} has no partner; {len(only_left) + len(only_right)} unpaired in all)")
    if not lefts:
        raise DataError(f"{folder}: no calibration image pairs")
    return [(k, str(lefts[k]), str(rights[k])) for k in sorted(lefts, key=natural_key)]


def _is_side_word_folder(folder: Path) -> bool:
    """A folder of ``left*``/``right*`` photos only (no scene pair, no ``left/`` subfolder)."""
    if not folder.is_dir() or scene_pair(folder) or (folder / "left").is_dir():
        return False
    images = image_files(folder)
    return bool(images) and all(side_key(f.stem)[0] for f in images)


# --------------------------------------------------------------------------- command-line inputs

def discover_pairs(inputs: list[str] | tuple[str, ...], *,
                   side_words: bool = False) -> tuple[list[StereoInput], list[str]]:
    """Resolve command-line inputs into stereo pairs.

    Returns ``(pairs, problems)``; raises :class:`DataError` when an input does not exist or
    nothing at all can be paired. Pair names are made safe (:func:`output_name`) and unique (a
    clash is an error, since outputs are written to ``OUTDIR/<name>/``). With ``side_words``,
    folders holding only ``left*``/``right*`` photos are paired as calibration photos (listed
    first).
    """
    if side_words:
        pairs: list[StereoInput] = []
        rest = []
        for raw in inputs:
            if _is_side_word_folder(Path(raw)):
                pairs += [StereoInput(name=output_name(name), left=left, right=right)
                          for name, left, right in find_calibration_pairs(raw)]
            else:
                rest.append(raw)
        found, problems = discover_pairs(rest) if rest else ([], [])
        unique_names([(pair.name, pair.left) for pair in pairs + found])
        return pairs + found, problems
    paths = [Path(p) for p in inputs]
    for p in paths:
        if not p.exists():
            raise DataError(f"{p}: no such file or folder")
    pairs = []
    problems: list[str] = []
    files = [p for p in paths if p.is_file()]
    folders = [p for p in paths if p.is_dir()]
    if files:
        if len(files) % 2:
            raise DataError(f"{files[-1]}: image files must be given in left/right pairs")
        pairs += [file_pair(left, right) for left, right in zip(files[0::2], files[1::2])]
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
    for pair in pairs:
        pair.name = output_name(pair.name)
    unique_names([(pair.name, pair.left) for pair in pairs])
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
    subdirs = sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))  # not staging folders
    for sub in subdirs:
        scene = scene_pair(sub)
        if scene:
            pairs.append(scene)
        elif image_files(sub):
            problems.append(f"{sub}: holds images but no recognised left/right pair ({_pair_names()})")
    if not subdirs and image_files(folder):
        problems.append(f"{folder}: holds images but no recognised left/right pair ({_pair_names()})")
    if not subdirs and not image_files(folder):
        raise DataError(f"{folder}: empty folder (no images or scene folders)")
    return pairs, problems
