"""Ground-truth layouts: detection, loading, masks, and pairing results with scenes by name.

Layouts (auto-detected per folder, overridable with ``dataset=``):

* ``middlebury2014`` (MiddEval3 and the bundled ``samples/``): a scene folder holding
  ``disp0GT.pfm`` (+inf unknown), ``mask0nocc.png`` (255 = non-occluded), ``calib.txt``
  (``ndisp``) and ``im0.png``.
* ``middlebury2003`` / ``middlebury2001`` (v2): ``disp<k>.pgm|png`` 8-bit ``d * scale`` with 0
  unknown; the smallest ``k`` is the left GT (``disp2`` for im2, ``disp3`` for Tsukuba's im3)
  and a larger one (``disp6``) the right-view GT. Official region masks (``nonocc*``, ``all*``,
  ``disc*``, 255 = scored) are used when present, otherwise the non-occluded mask is derived
  (:func:`stereocli.evaluation.metrics.derive_nonocc_mask`) and labelled as derived.
* ``middlebury2005`` (2005/2006 sets): ``view1``/``view5`` images with the 8-bit GT ``disp1.png``
  (``disp5.png`` the right view's) stored in full-size units at every size, so divided by 1, 2 or
  3 at Full, Half or Third size, told from the image width (:data:`MB2005_SIZES`); 0 unknown.
* ``kitti`` (2015): a root holding ``disp_noc_0/<name>.png`` and/or ``disp_occ_0/<name>.png``
  (uint16, d * 256, 0 invalid), optional ``obj_map/<name>.png`` and ``image_2/<name>.png``; either
  folder alone is scored (noc with ``disp_noc_0``, occ with ``disp_occ_0``). With ``dataset="kitti"``
  also a single GT file, or a folder of ``<name>.png`` GT files (occ, or noc when the folder or
  file is named ``disp_noc*``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence, cast

import numpy as np

from ..errors import ConfigError, DataError
from ..io.images import IMAGE_SUFFIXES, read_disparity, read_image
from ..io.middlebury import read_calib_txt
from ..io.text import read_text_limited
from .metrics import derive_nonocc_mask

DATASETS = ("middlebury2014", "middlebury2003", "middlebury2001", "middlebury2005", "kitti")

#: MiddEval3 training-set weights (official table): 0.5 for these, 1.0 for the rest.
MIDDEVAL3_HALF_WEIGHT = frozenset({"PianoL", "Playroom", "Playtable", "Shelves", "Vintage"})

#: v2 GT scale factors (OpenCV testdata datasets.xml; see data/MANIFEST.md).
V2_SCALES = {"tsukuba": 16.0, "venus": 8.0, "teddy": 4.0, "cones": 4.0, "barn1": 8.0, "barn2": 8.0,
             "bull": 8.0, "poster": 8.0, "sawtooth": 8.0, "map": 8.0}
#: v2 disparity ranges (data/MANIFEST.md), used only for the s/GD time column.
V2_NDISP = {"tsukuba": 16, "venus": 20, "teddy": 60, "cones": 60}

#: Middlebury 2005/2006 sizes: (name, divisor of the 8-bit GT, smallest and largest image width in
#: px). The GT holds full-size disparities at every size; the sets' full widths are 1240-1396 px.
MB2005_SIZES = (("Full", 1, 1200, 1460), ("Half", 2, 600, 730), ("Third", 3, 400, 490))

#: MiddEval3 resolution letter -> size factor relative to full resolution.
RESOLUTION_FACTORS = {"F": 1, "H": 2, "Q": 4}
_RES_DIR = re.compile(r"^(training|test|additional)([FHQ])$")
_V2_GT = re.compile(r"^disp(\d+)\.(pgm|png|pfm)$", re.IGNORECASE)

DERIVED_NOTE = ("derived from the GT by a z-buffer visibility test (not the official v2 mask)")


@dataclass
class Scene:
    """One ground-truth scene, loaded and ready for scoring.

    ``masks`` maps a region name (``nonocc``, ``all``, optionally ``disc``) to a (H, W) bool
    array, or ``None`` when the region cannot be scored (reason in ``errors``). For KITTI,
    ``mask_gt`` holds one GT map per region (``disp_noc_0`` / ``disp_occ_0``).
    """

    name: str
    kind: str  # middlebury2014 | middlebury-v2 | middlebury2005 | kitti | generic
    gt: np.ndarray  # (H, W) float32 px at the GT resolution, +inf unknown
    masks: dict[str, np.ndarray | None]
    gt_path: Path
    ndisp: float | None = None  # at the GT resolution (calib.txt ndisp)
    weight: float = 1.0
    resolution: str = "F"  # MiddEval3 resolution letter of the GT
    gt_scale: float | None = None  # v2 8-bit scale
    left_image: Path | None = None
    mask_notes: dict[str, str] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    mask_gt: dict[str, np.ndarray] = field(default_factory=dict)
    obj_map: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return cast("tuple[int, int]", self.gt.shape)


def middeval3_weight(name: str) -> float:
    """Official MiddEval3 training weight of a scene (0.5 or 1.0)."""
    return 0.5 if name in MIDDEVAL3_HALF_WEIGHT else 1.0


def resolution_from_path(path: Path) -> str:
    """``Q``/``H``/``F`` from a MiddEval3 folder name (``trainingQ`` ...) in ``path``; else ``F``."""
    for part in reversed(Path(path).resolve().parts):
        m = _RES_DIR.match(part)
        if m:
            return m.group(2)
    return "F"


def _first_image(folder: Path, stem: str) -> Path | None:
    for suffix in IMAGE_SUFFIXES:
        p = folder / f"{stem}{suffix}"
        if p.is_file():
            return p
    return None


def _v2_gt_files(folder: Path) -> dict[int, Path]:
    found: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        m = _V2_GT.match(p.name)
        if m and p.is_file():
            found.setdefault(int(m.group(1)), p)
    return found


def is_kitti_root(path: Path) -> bool:
    return path.is_dir() and ((path / "disp_noc_0").is_dir() or (path / "disp_occ_0").is_dir())


def _is_mb2005_scene(path: Path) -> bool:
    """A Middlebury 2005/2006 scene: ``view1`` and ``disp1`` side by side."""
    return _first_image(path, "view1") is not None and any(
        (path / f"disp1{suffix}").is_file() for suffix in (".png", ".pgm"))


def detect_layout(path: Path) -> str | None:
    """Layout of a GT *scene folder* or KITTI root: a name from :data:`DATASETS` or ``None``."""
    path = Path(path)
    if not path.is_dir():
        return None
    if is_kitti_root(path):
        return "kitti"
    if (path / "disp0GT.pfm").is_file():
        return "middlebury2014"
    if _is_mb2005_scene(path):
        return "middlebury2005"
    if _v2_gt_files(path):
        return "middlebury2003"
    return None


def _read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    mask = read_image(path, gray=True)
    if mask.shape != shape:
        raise DataError(f"{path}: mask size {mask.shape[1]}x{mask.shape[0]} differs from the GT size "
                        f"{shape[1]}x{shape[0]}")
    return mask == 255


def load_middlebury2014(folder: Path, *, resolution: str | None = None) -> Scene:
    """A MiddEval3-layout scene (also the bundled synthetic samples)."""
    gt_path = folder / "disp0GT.pfm"
    gt = read_disparity(gt_path)
    scene = Scene(name=folder.name, kind="middlebury2014", gt=gt, masks={}, gt_path=gt_path,
                  weight=middeval3_weight(folder.name),
                  resolution=resolution or resolution_from_path(folder),
                  left_image=_first_image(folder, "im0"))
    mask_path = folder / "mask0nocc.png"
    if mask_path.is_file():
        scene.masks["nonocc"] = _read_mask(mask_path, gt.shape)
    else:
        scene.masks["nonocc"] = None
        scene.errors.append(f"{mask_path}: missing, nonocc not scored")
    scene.masks["all"] = np.isfinite(gt)
    calib = folder / "calib.txt"
    if calib.is_file():
        c = read_calib_txt(calib)
        if c.ndisp > 0:
            scene.ndisp = float(c.ndisp)
        if c.width and c.height and (c.height, c.width) != gt.shape:
            raise DataError(f"{calib}: width/height {c.width}x{c.height} differ from {gt_path} "
                            f"{gt.shape[1]}x{gt.shape[0]}")
    if scene.ndisp is None:
        scene.notes.append("no ndisp (calib.txt): estimates not clipped")
    return scene


def mb2005_divisor(path: Path, width: int) -> tuple[str, int]:
    """``(size name, divisor)`` of a Middlebury 2005/2006 GT ``width`` px wide (:data:`MB2005_SIZES`).

    Raises :class:`ConfigError` for a width of none of the sizes."""
    for name, divisor, low, high in MB2005_SIZES:
        if low <= width <= high:
            return name, divisor
    sizes = ", ".join(f"{name} {low}-{high}" for name, _, low, high in MB2005_SIZES)
    raise ConfigError(f"{path}: {width} px wide, none of the Middlebury 2005/2006 sizes ({sizes} px); "
                      "give the GT's divisor with --gt-scale")


def load_middlebury_v2(folder: Path, *, gt_scale: float | None = None, mb2005: bool = False) -> Scene:
    """A Middlebury 2001/2003 scene (8-bit GT decoded with the per-scene scale), or with ``mb2005``
    a 2005/2006 scene (``view1``/``disp1``: the divisor from the image width, :func:`mb2005_divisor`)."""
    files = _v2_gt_files(folder)
    if not files:
        raise DataError(f"{folder}: no disp<k>.pgm/png ground truth found")
    left_k = min(files)
    key = folder.name.lower()
    notes = []
    if mb2005 and gt_scale is None:
        width = read_image(files[left_k]).shape[1]
        size, divisor = mb2005_divisor(files[left_k], width)
        gt_scale = float(divisor)
        notes.append(f"{size} size ({width} px wide): GT values / {divisor}")
    if gt_scale is None:
        if key not in V2_SCALES:
            raise ConfigError(f"{folder}: unknown v2 scene {folder.name!r}; give its GT scale with --gt-scale")
        gt_scale = V2_SCALES[key]
    scale = None if files[left_k].suffix.lower() == ".pfm" else gt_scale
    gt = read_disparity(files[left_k], scale=scale)
    left_image = _first_image(folder, f"view{left_k}") if mb2005 else _first_image(folder, f"im{left_k}")
    scene = Scene(name=folder.name, kind="middlebury2005" if mb2005 else "middlebury-v2", gt=gt, masks={},
                  gt_path=files[left_k], gt_scale=gt_scale, ndisp=None if mb2005 else V2_NDISP.get(key),
                  resolution="F", left_image=left_image, notes=notes)
    official = {}
    for region in ("nonocc", "all", "disc"):
        for p in sorted(folder.iterdir()):
            if p.is_file() and p.stem.lower().startswith(region) and p.suffix.lower() in (".png", ".pgm"):
                official[region] = p
                break
    if "nonocc" in official:
        scene.masks["nonocc"] = _read_mask(official["nonocc"], gt.shape)
    else:
        right = None
        right_ks = [k for k in files if k > left_k]
        if right_ks:
            rp = files[max(right_ks)]
            right = read_disparity(rp, scale=None if rp.suffix.lower() == ".pfm" else gt_scale)
        scene.masks["nonocc"] = derive_nonocc_mask(gt, right)
        note = DERIVED_NOTE + (f", cross-checked with {files[max(right_ks)].name}" if right is not None else "")
        scene.mask_notes["nonocc"] = note
    if "all" in official:
        scene.masks["all"] = _read_mask(official["all"], gt.shape)
    else:
        scene.masks["all"] = np.isfinite(gt)
        scene.mask_notes["all"] = "every known-GT pixel (no official all mask)"
    if "disc" in official:
        scene.masks["disc"] = _read_mask(official["disc"], gt.shape)
    return scene


def kitti_names(root: Path) -> list[str]:
    names: set[str] = set()
    for sub in ("disp_occ_0", "disp_noc_0"):
        if (root / sub).is_dir():
            names.update(p.stem for p in (root / sub).glob("*.png"))
    return sorted(names)


def _read_kitti_gt(path: Path) -> np.ndarray:
    raw = read_image(path)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DataError(f"{path}: KITTI GT must be a 16-bit single-channel PNG")
    return read_disparity(path, scale=256.0)


#: KITTI region -> (GT folder of a root, file-name prefix of a frame folder).
_KITTI_REGIONS = {"nonocc": ("disp_noc_0", "disp_noc"), "all": ("disp_occ_0", "disp_occ")}


def kitti_region(path: Path) -> str:
    """The region a lone KITTI GT file scores: ``nonocc`` when it or its folder is named
    ``disp_noc*``, else ``all`` (KITTI's occ)."""
    named = [path.stem.lower(), path.parent.name.lower()]
    return "nonocc" if any(n.startswith("disp_noc") for n in named) else "all"


def load_kitti_file(path: Path, *, name: str | None = None) -> Scene:
    """One KITTI GT file on its own (``eval RESULT gt.png --dataset kitti``): its region from
    :func:`kitti_region`, the other region not scored (a note, not a failure)."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise DataError(f"{path}: KITTI GT is a 16-bit PNG")
    region = kitti_region(path)
    other = "all" if region == "nonocc" else "nonocc"
    return _kitti_scene(name or path.stem, {region: path},
                        notes=[f"{other} not scored: only {_KITTI_REGIONS[region][1]} GT given"])


def kitti_frame_files(folder: Path) -> dict[str, Path]:
    """The GT files of a folder holding one KITTI frame: ``disp_noc*.png`` and/or ``disp_occ*.png``
    by region; {} when it holds neither. Two files of one region are an error naming both."""
    found: dict[str, Path] = {}
    for p in sorted(folder.glob("*.png")):
        for region, (_, prefix) in _KITTI_REGIONS.items():
            if p.is_file() and p.stem.lower().startswith(prefix):
                if region in found:
                    raise DataError(f"{folder}: two {prefix} GT files ({found[region].name} and {p.name}); keep one")
                found[region] = p
    return found


def kitti_flat_names(folder: Path) -> list[str]:
    """Frames of a GT folder without disp_noc_0/ or disp_occ_0/: the folder itself when it holds
    one frame's ``disp_noc*``/``disp_occ*`` files, else one frame per ``<name>.png``."""
    if kitti_frame_files(folder):
        return [folder.name]
    return sorted(p.stem for p in folder.glob("*.png") if p.is_file())


def load_kitti(root: Path, name: str) -> Scene:
    """A KITTI 2015 frame ``name`` (e.g. ``000000_10``).

    ``root`` is a KITTI root with ``disp_noc_0/`` and/or ``disp_occ_0/`` (a region whose folder is
    absent is noted and not scored; a frame missing from a folder that exists is an error), or
    a folder of GT files: ``<name>.png`` (:func:`load_kitti_file`), one frame's ``disp_noc*.png``
    and/or ``disp_occ*.png``, or a single PNG.
    """
    if not is_kitti_root(root):
        if (root / f"{name}.png").is_file():
            return load_kitti_file(root / f"{name}.png", name=name)
        frame = kitti_frame_files(root)
        if frame:
            missing = [r for r in _KITTI_REGIONS if r not in frame]
            return _kitti_scene(name, frame, notes=[f"{r} not scored: no {_KITTI_REGIONS[r][1]}*.png in {root}"
                                                    for r in missing])
        pngs = sorted(p for p in root.glob("*.png") if p.is_file())
        if len(pngs) == 1:
            return load_kitti_file(pngs[0], name=name)
        raise DataError(f"{root}: no KITTI GT for {name!r} ({name}.png, disp_noc*.png or disp_occ*.png; or a "
                        "root with disp_noc_0/ or disp_occ_0/)")
    paths, errors, notes = {}, [], []
    for region, (sub, _) in _KITTI_REGIONS.items():
        p = root / sub / f"{name}.png"
        if p.is_file():
            paths[region] = p
        elif (root / sub).is_dir():
            errors.append((region, f"{p}: missing, {region} not scored"))
        else:
            notes.append(f"{region} not scored: no {sub}/ in the GT")
    if not paths:
        raise DataError(f"{root}: no KITTI GT for {name!r} in disp_noc_0/ or disp_occ_0/")
    image = root / "image_2" / f"{name}.png"
    obj = root / "obj_map" / f"{name}.png"
    return _kitti_scene(name, paths, errors=errors, notes=notes, left_image=image if image.is_file() else None,
                        obj_map=obj if obj.is_file() else None)


def _kitti_scene(name: str, paths: dict[str, Path], *, errors: Sequence[tuple[str, str]] = (),
                 notes: Sequence[str] = (), left_image: Path | None = None, obj_map: Path | None = None) -> Scene:
    """A KITTI scene from its GT files by region (``errors``: regions whose GT is missing)."""
    maps = {region: _read_kitti_gt(p) for region, p in paths.items()}
    main = "all" if "all" in maps else "nonocc"
    gt = maps[main]
    scene = Scene(name=name, kind="kitti", gt=gt, masks={}, gt_path=paths[main], left_image=left_image,
                  notes=list(notes))
    for region in _KITTI_REGIONS:
        if region in maps:
            if maps[region].shape != gt.shape:
                raise DataError(f"{paths[region]}: size differs from the other KITTI GT map")
            scene.mask_gt[region] = maps[region]
            scene.masks[region] = np.isfinite(maps[region])
    for region, message in errors:
        scene.masks[region] = None
        scene.errors.append(message)
    if obj_map is not None:
        scene.obj_map = read_image(obj_map, gray=True)
        if scene.obj_map.shape != gt.shape:
            raise DataError(f"{obj_map}: {scene.obj_map.shape[1]}x{scene.obj_map.shape[0]} but the GT is "
                            f"{gt.shape[1]}x{gt.shape[0]}")
    return scene


def load_scene(path: Path, *, dataset: str | None = None, gt_scale: float | None = None,
               resolution: str | None = None) -> Scene:
    """Load a GT scene folder (Middlebury 2014 or v2) with optional layout override."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: not a folder")
    kind = dataset or detect_layout(path)
    if kind == "middlebury2005":
        return load_middlebury_v2(path, gt_scale=gt_scale, mb2005=True)
    if kind == "middlebury2014":
        if not (path / "disp0GT.pfm").is_file():
            raise DataError(f"{path}: no disp0GT.pfm (Middlebury 2014 layout)")
        return load_middlebury2014(path, resolution=resolution)
    if kind in ("middlebury2003", "middlebury2001"):
        return load_middlebury_v2(path, gt_scale=gt_scale)
    if kind == "kitti":
        raise ConfigError(f"{path}: a KITTI GT is a root with disp_noc_0/ and disp_occ_0/, not a scene folder")
    raise DataError(f"{path}: no ground truth found (expected disp0GT.pfm, disp<k>.pgm, view1 + disp1.png "
                    "or disp_noc_0/; KITTI GT files: --dataset kitti)")


def load_gt_file(path: Path, *, dataset: str | None = None, gt_scale: float | None = None,
                 resolution: str | None = None) -> Scene:
    """A GT given as a single file: resolved to its scene when it sits in a known layout."""
    path = Path(path)
    parent = path.parent
    if parent.name in ("disp_noc_0", "disp_occ_0") and path.suffix.lower() == ".png" and dataset in (None, "kitti"):
        return load_kitti(parent.parent, path.stem)
    if dataset == "kitti":
        return load_kitti_file(path)
    if path.name == "disp0GT.pfm" or _V2_GT.match(path.name) and detect_layout(parent):
        return load_scene(parent, dataset=dataset, gt_scale=gt_scale, resolution=resolution)
    if dataset == "middlebury2005":
        if gt_scale is None:
            gt_scale = float(mb2005_divisor(path, read_image(path).shape[1])[1])
        dataset = "middlebury2003"  # decoded with that divisor, scored by the v2 rules below
    if dataset in ("middlebury2003", "middlebury2001"):
        if gt_scale is None and path.suffix.lower() != ".pfm":
            raise ConfigError(f"{path}: give the 8-bit GT's scale with --gt-scale (d = value / scale)")
        gt = read_disparity(path, scale=None if path.suffix.lower() == ".pfm" else gt_scale)
        nonocc = derive_nonocc_mask(gt, None)
        scene = Scene(name=path.stem, kind="middlebury-v2", gt=gt, masks={"nonocc": nonocc, "all": np.isfinite(gt)},
                      gt_path=path, gt_scale=gt_scale, resolution="F")
        scene.mask_notes["nonocc"] = DERIVED_NOTE
        return scene
    # Generic GT file: only "all" can be scored.
    scale = gt_scale
    if path.suffix.lower() == ".png" and scale is None:
        scale = 256.0 if read_image(path).dtype == np.uint16 else None
    gt = read_disparity(path, scale=scale)
    scene = Scene(name=path.stem, kind="generic", gt=gt, masks={"nonocc": None, "all": np.isfinite(gt)},
                  gt_path=path, resolution=resolution or "F")
    hint = " (a KITTI GT: --dataset kitti scores it by KITTI's rules)" if scale == 256.0 and gt_scale is None else ""
    scene.errors.append(f"{path}: a bare GT file has no non-occlusion mask, nonocc not scored{hint}")
    return scene


@dataclass
class GTEntry:
    """A scene known by name before loading (loading happens per scene so failures stay local)."""

    name: str
    kind: str
    path: Path  # scene folder, or KITTI root


def find_gt_scenes(gt_dir: Path, *, dataset: str | None = None, max_depth: int = 3) -> list[GTEntry]:
    """All GT scenes under ``gt_dir`` (itself a scene, a KITTI root, or folders of scenes)."""
    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise DataError(f"{gt_dir}: ground-truth folder not found")
    if dataset == "kitti" or (dataset is None and is_kitti_root(gt_dir)):
        names = kitti_names(gt_dir) if is_kitti_root(gt_dir) else kitti_flat_names(gt_dir)
        if not names:
            raise DataError(f"{gt_dir}: no KITTI GT (disp_noc_0/ or disp_occ_0/ folders, or <name>.png files)")
        return [GTEntry(n, "kitti", gt_dir) for n in names]
    own = detect_layout(gt_dir)
    if own is not None and own != "kitti":
        return [GTEntry(gt_dir.name, dataset or own, gt_dir)]
    found: list[GTEntry] = []
    seen: dict[str, Path] = {}

    def walk(folder: Path, depth: int) -> None:
        for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
            kind = detect_layout(sub)
            if kind == "kitti":
                continue
            if kind is not None:
                if sub.name in seen:
                    raise ConfigError(f"scene name {sub.name!r} appears twice: {seen[sub.name]} and {sub}; "
                                      f"give a narrower GROUND_TRUTH folder")
                seen[sub.name] = sub
                found.append(GTEntry(sub.name, dataset or kind, sub))
            elif depth < max_depth:
                walk(sub, depth + 1)

    walk(gt_dir, 1)
    if not found:
        raise DataError(f"{gt_dir}: no ground-truth scenes found (disp0GT.pfm, disp<k>.pgm, view1 + disp1.png, "
                        "disp_noc_0/; KITTI GT files: --dataset kitti)")
    return found


def load_entry(entry: GTEntry, *, gt_scale: float | None = None, resolution: str | None = None) -> Scene:
    if entry.kind == "kitti":
        return load_kitti(entry.path, entry.name)
    return load_scene(entry.path, dataset=entry.kind, gt_scale=gt_scale, resolution=resolution)


# --------------------------------------------------------------------------------------------
# Results side

_RESULT_SUFFIXES = (".pfm", ".png", ".npy", ".pgm")


@dataclass
class ResultEntry:
    name: str
    path: Path | None  # None when the folder exists but holds no usable disparity
    time_path: Path | None = None
    problem: str | None = None


def _time_file(folder: Path) -> Path | None:
    if (folder / "time.txt").is_file():
        return folder / "time.txt"
    cands = sorted(folder.glob("time*.txt"))
    return cands[0] if len(cands) == 1 else None


def result_in_folder(folder: Path) -> ResultEntry:
    """The disparity in a per-scene results folder: ``disp0.pfm``, else a single ``disp0*.pfm``."""
    name = folder.name
    if (folder / "disp0.pfm").is_file():
        return ResultEntry(name, folder / "disp0.pfm", _time_file(folder))
    cands = sorted(folder.glob("disp0*.pfm"))
    if len(cands) == 1:
        return ResultEntry(name, cands[0], _time_file(folder))
    if len(cands) > 1:
        return ResultEntry(name, None, None, f"{folder}: several disp0*.pfm files "
                                             f"({', '.join(c.name for c in cands)}); keep one")
    return ResultEntry(name, None, None, f"{folder}: no disp0*.pfm result")


def find_results(results_dir: Path) -> dict[str, ResultEntry]:
    """Results by scene name: ``<name>/disp0*.pfm`` (+ ``time.txt``), ``<name>.pfm|png|npy``,
    or KITTI's ``disp_0/<name>.png``."""
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise DataError(f"{results_dir}: results folder not found")
    out: dict[str, ResultEntry] = {}
    roots = [results_dir]
    if (results_dir / "disp_0").is_dir():
        roots.append(results_dir / "disp_0")
    for root in roots:
        for p in sorted(root.iterdir()):
            if p.name.startswith("."):
                continue
            if p.is_dir():
                if p.name == "disp_0":
                    continue
                entry = result_in_folder(p)
                if entry.path is None and not any(p.iterdir()):
                    continue
                if entry.path is None and entry.problem and "no disp0" in entry.problem:
                    continue  # an unrelated folder (e.g. error maps); reported only if GT wants it
                out.setdefault(p.name, entry)
            elif p.suffix.lower() in _RESULT_SUFFIXES and p.is_file():
                out.setdefault(p.stem, ResultEntry(p.stem, p, None))
    return out


def match_name(name: str, results: dict[str, ResultEntry]) -> ResultEntry | None:
    """The result of GT scene ``name``: exact name first (or the name ``match`` gives its
    outputs, :func:`~stereocli.io.pairs.output_name`), then case-insensitive (``Tsukuba``
    results for ``tsukuba`` GT). Raises :class:`DataError` naming the candidates when several
    results match only case-insensitively."""
    from ..io.pairs import output_name

    for key in dict.fromkeys((name, output_name(name))):
        if key in results:
            return results[key]
    wanted = {name.casefold(), output_name(name).casefold()}
    found = [k for k in results if k.casefold() in wanted]
    if len(found) > 1:
        raise DataError(f"ambiguous result: {' and '.join(repr(k) for k in found)} both match {name!r} "
                        "(names compared without case); rename or remove all but one")
    return results[found[0]] if found else None


def read_time(path: Path | None) -> float | None:
    """Seconds from a MiddEval3 ``time.txt`` (one number); ``None`` when absent."""
    if path is None:
        return None
    try:
        return float(read_text_limited(path, "time file").split()[0])
    except (OSError, ValueError, IndexError):
        raise DataError(f"{path}: not a time file (one number of seconds expected)") from None


def load_estimate(path: Path, scene: Scene | None = None) -> np.ndarray:
    """Read an estimated disparity map (PFM/npy in px; 16-bit PNG /256; 8-bit with the v2 scale)."""
    path = Path(path)
    scale = None
    if path.suffix.lower() in (".png", ".pgm"):
        raw = read_image(path)
        if raw.dtype != np.uint16:
            if scene is not None and scene.gt_scale is not None:
                scale = scene.gt_scale  # v2 submissions: 8-bit with the scene's GT scale
            else:
                raise DataError(f"{path}: 8-bit disparity is a preview, not data; use PFM or 16-bit PNG")
    return read_disparity(path, scale=scale)
