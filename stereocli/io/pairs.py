"""Finding stereo pairs in what the user passed on the command line: the one pairing rule of
``calibrate``, ``rectify``, ``match``, ``triangulate --scenes`` and ``eval`` (docs/formats.md, "Input
layouts").

On the command line: two image files (left, right), two folders of images (left, right), or
folders. A folder holds exactly one of these layouts; a folder holding two is an error naming
them, never a guess:

* **a scene**: a known pair of file stems (:data:`SCENE_PAIRS`: ``im0``/``im1``, ``im2``/``im6``,
  ``im3``/``im4``, ``view1``/``view5``, ``left``/``right``), with optional ``calib.txt`` and valid
  masks ``valid0.png``/``valid1.png``; named by the folder. When several known pairs are present
  (a full Middlebury 2001 set holds ``im0`` ... ``im8``), the one whose left view has ground
  truth (``disp2.pgm`` for ``im2``) is the scene; otherwise the folder is ambiguous;
* **side-word files**: ``left01``/``right01``, ``left_0001``/``right_0001``, ``0001_left``/
  ``0001_right``, ``img_left_7``/``img_right_7``: the side word stands as a word of its own (a
  letter next to it makes it part of another word: ``bright`` names no side); paired and named
  by the stem without the side word (``01``, ``0001``, ``img_7``);
* **two subfolders**: ``left/`` + ``right/`` or ``cam0/`` + ``cam1/``, paired and named by the stem
  without its own side word or ``l``/``r`` prefix or suffix (``left/0001_l.png`` with
  ``right/0001_r.png`` is ``0001``);
* **scene folders**: subfolders that are scenes (each named by its folder).

Two files are named like the folder they come from: a scene pair of one folder by the folder,
side-word partners by their common name, others by the left file's stem. So a pair has the same
name in every subcommand, and ``rectify -> match -> triangulate -> eval`` chain by name.

Files that cannot be paired are returned as problems (the caller reports them as failed items,
or ``calibrate`` refuses the folder), never dropped silently.

A pair's name is its output folder's name (``OUTDIR/<name>/``), made safe by :func:`output_name`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import cast

from ..errors import DataError
from .images import IMAGE_SUFFIXES

#: Names a batch keeps for itself in its output folder: the run record. (Its lock, staging folder
#: and completion markers start with a dot, which no output name does.)
RESERVED_NAMES = ("run.json",)
#: Characters an output name never holds: path separators and control characters (line breaks
#: included), which would break paths, one-line messages and text tables.
_UNSAFE = re.compile(r"[/\\\x00-\x1f\x7f-\x9f\u2028\u2029]")

#: Known (left, right) file stems of a scene folder: Middlebury 2014, 2001/2003, the Tsukuba copy
#: in the project's data, Middlebury 2005/2006, and a plain left/right pair.
SCENE_PAIRS = (("im0", "im1"), ("im2", "im6"), ("im3", "im4"), ("view1", "view5"), ("left", "right"))
#: Subfolder pairs holding the left and the right views.
SUBFOLDER_PAIRS = (("left", "right"), ("cam0", "cam1"))


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


def natural_key(key: str) -> list:
    """Sort key that orders digit runs by value (``2`` before ``10``)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key)]


def _table() -> str:
    """The layouts, for messages."""
    scenes = ", ".join(f"{a}/{b}" for a, b in SCENE_PAIRS)
    return (f"scene files {scenes}; left01/right01, left_0001 or 0001_left files; left/ + right/ or "
            "cam0/ + cam1/ subfolders; scene folders")


# --------------------------------------------------------------------------- side words

_SEPARATORS = "_-. "
#: A side word standing as a word of its own: no letter right before or after it.
_SIDE_WORD = re.compile(r"(?<![a-z])(left|right)(?![a-z])", re.IGNORECASE)
#: A one-letter side affix (``0001_l``, ``r-0001``), only inside a folder that names the side.
_SIDE_LETTER = {side: re.compile(rf"^{side[0]}[_\-. ]|[_\-. ]{side[0]}$", re.IGNORECASE) for side in ("left", "right")}


def _without(stem: str, start: int, end: int) -> str:
    """``stem`` without ``stem[start:end]`` and the separators around it, one separator kept
    between what remains on both sides (``img_left_7`` -> ``img_7``)."""
    before, after = stem[:start], stem[end:]
    head, tail = before.rstrip(_SEPARATORS), after.lstrip(_SEPARATORS)
    if not (head and tail):
        return head + tail
    removed = before[len(head):] + after[: len(after) - len(tail)]
    return head + removed[:1] + tail


def side_key(stem: str) -> tuple[str | None, str]:
    """``(side, key)``: the side word of ``stem`` (``"left"``/``"right"``; None without one, or
    when it names both sides) and the stem without it (``"img_left_7"`` -> ``("left", "img_7")``,
    ``"0001_right"`` -> ``("right", "0001")``)."""
    found = list(_SIDE_WORD.finditer(stem))
    if not found or len({m.group(1).lower() for m in found}) > 1:
        return None, stem
    m = found[0]
    return m.group(1).lower(), _without(stem, m.start(), m.end())


def _folder_key(stem: str, side: str) -> str:
    """The pairing key of ``stem`` in a folder of ``side`` images: without its own side word,
    else without a one-letter ``l``/``r`` prefix or suffix, else the stem itself."""
    for m in _SIDE_WORD.finditer(stem):
        if m.group(1).lower() == side:
            return _without(stem, m.start(), m.end()) or stem
    letter = _SIDE_LETTER[side].search(stem)
    if letter:
        return (stem[: letter.start()] + stem[letter.end():]).strip(_SEPARATORS) or stem
    return stem


def _pair_by_key(lefts: dict[str, Path], rights: dict[str, Path], left_where: str,
                 right_where: str) -> tuple[list[StereoInput], list[str]]:
    """Pairs of the keys both sides hold (in natural order), and the unpaired files as problems."""
    pairs = [StereoInput(name=k, left=str(lefts[k]), right=str(rights[k]))
             for k in sorted(lefts.keys() & rights.keys(), key=natural_key)]
    problems = [f"{lefts[k]}: no matching right image in {right_where}"
                for k in sorted(lefts.keys() - rights.keys(), key=natural_key)]
    problems += [f"{rights[k]}: no matching left image in {left_where}"
                 for k in sorted(rights.keys() - lefts.keys(), key=natural_key)]
    return pairs, problems


def _keyed(files: list[Path], key_of) -> dict[str, Path]:
    """``files`` by key; two files with one key are an error naming both."""
    table: dict[str, Path] = {}
    for p in files:
        key = key_of(p)
        if key in table:
            raise DataError(f"ambiguous pair name {key!r}: {table[key]} and {p} are both its image; "
                            "rename or remove one")
        table[key] = p
    return table


def pair_folders(left_dir: Path, right_dir: Path) -> tuple[list[StereoInput], list[str]]:
    """Pair the images of ``left_dir`` and ``right_dir`` by key (the stem without its own side
    word or ``l``/``r`` affix); returns pairs and unpaired-file problems."""
    lefts = _keyed(image_files(left_dir), lambda p: _folder_key(p.stem, "left"))
    rights = _keyed(image_files(right_dir), lambda p: _folder_key(p.stem, "right"))
    return _pair_by_key(lefts, rights, str(left_dir), str(right_dir))


def _side_word_files(images: list[Path]) -> list[Path]:
    """The images whose stem holds one side word and more (``left01``, not ``left``)."""
    out = []
    for p in images:
        side, key = side_key(p.stem)
        if side and key:
            out.append(p)
    return out


def pair_side_word_files(folder: Path, images: list[Path]) -> tuple[list[StereoInput], list[str]]:
    """Pair ``left*``/``right*`` files of one folder by the stem without the side word."""
    by_side: dict[str, list[Path]] = {"left": [], "right": []}
    for p in _side_word_files(images):
        by_side[cast(str, side_key(p.stem)[0])].append(p)  # _side_word_files keeps stems with a side word
    lefts = _keyed(by_side["left"], lambda p: side_key(p.stem)[1])
    rights = _keyed(by_side["right"], lambda p: side_key(p.stem)[1])
    return _pair_by_key(lefts, rights, str(folder), str(folder))


# --------------------------------------------------------------------------- scene folders

def _has_ground_truth(folder: Path, left_stem: str) -> bool:
    """Whether ``folder`` holds the ground truth of view ``left_stem`` (``disp2.pgm`` for ``im2``,
    ``disp0GT.pfm`` for ``im0``, ``disp1.png`` for ``view1``)."""
    digits = re.sub(r"\D", "", left_stem)
    if not digits:
        return False
    return any(p.is_file() for p in folder.glob(f"disp{digits}*") if re.fullmatch(
        rf"disp{digits}(GT)?\.(pfm|pgm|png)", p.name, re.IGNORECASE))


def _scene_files(folder: Path, stems: dict[str, Path] | None = None) -> list[tuple[Path, Path]]:
    """The known scene pairs of ``folder`` (:data:`SCENE_PAIRS`); of several, the one whose left
    view has ground truth when exactly one has."""
    stems = _by_stem(folder) if stems is None else stems
    found = [(stems[a], stems[b]) for a, b in SCENE_PAIRS if a in stems and b in stems]
    if len(found) > 1:
        with_gt = [pair for pair in found if _has_ground_truth(folder, pair[0].stem)]
        if len(with_gt) == 1:
            return with_gt
    return found


def _ambiguous_scene(folder: Path, found: list[tuple[Path, Path]]) -> DataError:
    names = " and ".join(f"{a.name}/{b.name}" for a, b in found)
    return DataError(f"{folder}: ambiguous scene: it holds the pairs {names}; give the two files of the "
                     f"one to use (e.g. {found[0][0]} {found[0][1]})")


def scene_pair(folder: Path) -> StereoInput | None:
    """The pair inside a scene folder, or None when the folder is not a scene.

    Raises :class:`DataError` naming the candidates when it holds several known pairs and ground
    truth singles out none of them.
    """
    found = _scene_files(folder)
    if len(found) > 1:
        raise _ambiguous_scene(folder, found)
    return _scene_input(folder, *found[0]) if found else None


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
    """Two image files given on the command line, named as their folder would name them: a scene
    pair of one folder (``im0``/``im1``, ``left``/``right``, ...) is that scene (named by the folder,
    with its calib.txt and masks); files of ``left/`` and ``right/`` (``cam0/``, ``cam1/``) and
    side-word partners (``left01``/``right01``) are named by their common key (``01``); other
    files by the left file's stem."""
    if left.parent.resolve() == right.parent.resolve() and (left.stem, right.stem) in SCENE_PAIRS:
        return _scene_input(left.parent, left, right)
    if (left.parent.name.lower(), right.parent.name.lower()) in SUBFOLDER_PAIRS:
        lkey, rkey = _folder_key(left.stem, "left"), _folder_key(right.stem, "right")
        return StereoInput(name=lkey if lkey == rkey else left.stem, left=str(left), right=str(right))
    (lside, lkey), (rside, rkey) = side_key(left.stem), side_key(right.stem)
    partners = (lside, rside) == ("left", "right") and lkey == rkey and lkey
    return StereoInput(name=lkey if partners else left.stem, left=str(left), right=str(right))


# --------------------------------------------------------------------------- one folder

def _subfolders(folder: Path) -> dict[str, Path]:
    """Subfolders by lower-case name (hidden ones, such as a batch's staging folder, left out)."""
    return {p.name.lower(): p for p in sorted(folder.iterdir()) if p.is_dir() and not p.name.startswith(".")}


def _layouts(folder: Path) -> list[tuple[str, str]]:
    """The layouts ``folder`` holds, as ``(kind, what)`` with ``what`` naming the files."""
    images = image_files(folder)
    subs = _subfolders(folder)
    found = []
    scene = _scene_files(folder, {p.stem: p for p in images})
    if scene:
        found.append(("scene", " and ".join(f"{a.name}/{b.name}" for a, b in scene)))
    side = [p for p in _side_word_files(images) if not any(p in pair for pair in scene)]
    if side:
        found.append(("side-word files", f"{len(side)} left*/right* files ({side[0].name}, ...)"))
    paired_dirs = set()
    for a, b in SUBFOLDER_PAIRS:
        if a in subs and b in subs:
            found.append(("subfolders", f"{subs[a].name}/ + {subs[b].name}/"))
            paired_dirs |= {a, b}
    scenes = [d for key, d in subs.items() if key not in paired_dirs and _scene_files(d)]
    if scenes:
        found.append(("scene folders", f"{len(scenes)} scene folder(s) ({scenes[0].name}/, ...)"))
    return found


def _discover_folder(folder: Path) -> tuple[list[StereoInput], list[str]]:
    """The pairs of one folder given on the command line (see the module's docstring)."""
    layouts = _layouts(folder)
    if len(layouts) > 1:
        raise DataError(f"{folder}: ambiguous: it holds {' and '.join(what for _, what in layouts)}; "
                        "keep one layout per folder, or give the folders or files to pair")
    images = image_files(folder)
    subs = _subfolders(folder)
    kind = layouts[0][0] if layouts else None
    if kind == "scene":
        return [cast(StereoInput, scene_pair(folder))], []  # a "scene" layout is a scene_pair
    if kind == "side-word files":
        pairs, problems = pair_side_word_files(folder, images)
        side = set(_side_word_files(images))
        problems += [f"{p}: no left/right word in its name (the folder pairs left*/right* files); not paired"
                     for p in images if p not in side]
        return pairs, problems
    if kind == "subfolders":
        a, b = next((a, b) for a, b in SUBFOLDER_PAIRS if a in subs and b in subs)
        pairs, problems = pair_folders(subs[a], subs[b])
        problems += [f"{p}: beside {subs[a].name}/ + {subs[b].name}/ (which hold the pairs); not paired"
                     for p in images]
        return pairs, problems
    pairs, problems = [], []
    for sub in subs.values():
        try:
            scene = scene_pair(sub)
        except DataError as exc:  # this scene's failure, not the batch's
            problems.append(str(exc))
            continue
        if scene:
            pairs.append(scene)
            continue
        inner = _layouts(sub)
        if inner:  # pairs of their own, named by their files: give the folder itself
            problems.append(f"{sub}: holds {inner[0][1]}, not one scene; give {sub} itself to pair them")
        elif image_files(sub):
            problems.append(f"{sub}: holds images but no recognised left/right pair ({_table()})")
    if kind == "scene folders":
        problems += [f"{p}: beside scene folders; not paired" for p in images]
    elif images:
        problems.append(f"{folder}: holds images but no recognised left/right pair ({_table()})")
    elif not subs:
        raise DataError(f"{folder}: empty folder (no images or scene folders)")
    return pairs, problems


def _pairs_by_itself(folder: Path) -> bool:
    """Whether ``folder`` holds pairs of its own (any layout but loose one-side images)."""
    layouts = _layouts(folder)
    if not layouts:
        return bool(_subfolders(folder))
    if [kind for kind, _ in layouts] != ["side-word files"]:
        return True
    sides = {side_key(p.stem)[0] for p in _side_word_files(image_files(folder))}
    return len(sides) > 1


# --------------------------------------------------------------------------- calibration photos

def find_calibration_pairs(folder: str | os.PathLike) -> list[tuple[str, str, str]]:
    """``(name, left_path, right_path)`` of the photo pairs in ``folder`` (the same layouts and
    names as :func:`discover_pairs`), sorted naturally by name.

    Raises :class:`DataError` when the folder is ambiguous, a photo has no partner, or nothing
    pairs.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: not a folder (calibrate expects a folder with left/ + right/ or left*/right* "
                        "images)")
    try:
        pairs, problems = _discover_folder(folder)
    except DataError as exc:
        if "empty folder" not in str(exc):
            raise
        pairs, problems = [], []
    if problems:
        raise DataError(f"{folder}: the photos do not pair up ({problems[0]}; {len(problems)} unpaired in all)")
    if not pairs:
        raise DataError(f"{folder}: no calibration image pairs (expected {_table()})")
    for pair in pairs:
        pair.name = output_name(pair.name)
    unique_names([(pair.name, pair.left) for pair in pairs])
    return [(p.name, p.left, p.right) for p in sorted(pairs, key=lambda p: natural_key(p.name))]


# --------------------------------------------------------------------------- command-line inputs

def discover_pairs(inputs: list[str] | tuple[str, ...], *,
                   side_words: bool = True) -> tuple[list[StereoInput], list[str]]:
    """Resolve command-line inputs into stereo pairs (every layout of the module's docstring).

    Returns ``(pairs, problems)``; raises :class:`DataError` when an input does not exist, a
    folder is ambiguous, or nothing at all can be paired. Pair names are made safe
    (:func:`output_name`) and unique (a clash is an error, since outputs are written to
    ``OUTDIR/<name>/``). ``side_words`` is accepted for older callers: every command pairs
    side-word files.
    """
    del side_words
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
        pairs += [file_pair(left, right) for left, right in zip(files[0::2], files[1::2])]
    if len(folders) == 2 and not any(_pairs_by_itself(f) for f in folders):
        # Two folders of images: the left views and the right views.
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
            + (f" ({problems[0]})" if problems else f" (expected {_table()})")
        )
    for pair in pairs:
        pair.name = output_name(pair.name)
    unique_names([(pair.name, pair.left) for pair in pairs])
    return pairs, problems
