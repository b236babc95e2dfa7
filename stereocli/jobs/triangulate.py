"""``stereocli triangulate`` as batch work: disparity maps -> work items, and the item
function workers run (depth map, point cloud, summary per disparity map)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io.pairs import output_name, unique_names
from ..io.text import read_text_limited
from .items import WorkItem, check_output_paths, settings_digest

DISPARITY_NAMES = ("disp0.pfm", "disp0.npy", "disp0.png")


def find_disparity(folder: Path) -> Path | None:
    """The left disparity in a scene/output folder: ``disp0.pfm`` (.npy, .png), else ``disp0*.pfm``."""
    for name in DISPARITY_NAMES:
        if (folder / name).is_file():
            return folder / name
    others = sorted(folder.glob("disp0*.pfm"))
    return others[0] if others else None


def _match_record(folder: Path) -> dict:
    """``params.json`` that ``stereocli match`` wrote beside its outputs ({} if none or unreadable)."""
    params = folder / "params.json"
    if not params.is_file():
        return {}
    try:
        recorded = json.loads(read_text_limited(params, "params.json"))
    except (OSError, ValueError):
        return {}
    return recorded if isinstance(recorded, dict) else {}


def _match_inputs(folder: Path) -> dict:
    """The inputs ``stereocli match`` recorded in ``params.json`` beside its outputs (calib, left,
    valid masks)."""
    recorded = _match_record(folder).get("inputs", {})
    if not isinstance(recorded, dict):
        return {}
    return {k: v for k, v in recorded.items() if isinstance(v, str) and Path(v).is_file()}


def _searched_range(folder: Path) -> dict | None:
    """``{"min_disp", "ndisp", "source"}``: the range ``stereocli match`` searched, from its
    ``params.json`` in ``folder``; None without one."""
    recorded = _match_record(folder)
    span = recorded.get("range")
    if not isinstance(span, dict):
        span = recorded
    low, ndisp = span.get("min_disp"), span.get("ndisp")
    if isinstance(low, int) and isinstance(ndisp, int) and not isinstance(low, bool) and ndisp > 0:
        return {"min_disp": low, "ndisp": ndisp, "source": str(folder / "params.json")}
    return None


def _find_inputs(inputs: list[str] | tuple[str, ...]) -> tuple[list[tuple[str, Path]], list[str]]:
    """``(name, disparity path)`` for each input file or folder, and folders without one."""
    found: list[tuple[str, Path]] = []
    problems: list[str] = []
    for raw in inputs:
        p = Path(raw)
        if p.is_file():
            found.append((p.resolve().parent.name if p.stem.startswith("disp0") else p.stem, p))
        elif p.is_dir():
            d = find_disparity(p)
            if d is not None:
                found.append((p.resolve().name, d))
                continue
            subs = sorted(x for x in p.iterdir() if x.is_dir() and not x.name.startswith("."))
            for sub in subs:
                d = find_disparity(sub)
                if d is not None:
                    found.append((sub.name, d))
                elif any(sub.iterdir()):
                    problems.append(f"{sub}: no disp0*.pfm / disp0.npy / disp0.png")
            if not subs:
                raise DataError(f"{p}: no disparity file (disp0.pfm, disp0*.pfm, disp0.npy, disp0.png)")
        else:
            raise DataError(f"{p}: no such file or folder")
    found = [(output_name(name), path) for name, path in found]
    unique_names([(name, str(path)) for name, path in found])
    return found, problems


def _scene_pairs(scenes: str) -> dict:
    """The pairs of ``--scenes`` by name, found by the rule of every subcommand
    (:func:`~stereocli.io.pairs.discover_pairs`), so a disparity named as ``match`` named it finds
    its pair's calib.txt and left image in any layout."""
    from ..io.pairs import discover_pairs

    pairs, _ = discover_pairs([scenes])
    return {pair.name: pair for pair in pairs}


def plan_items(inputs: list[str] | tuple[str, ...], output: str, *, calib: str | None = None,
               image: str | None = None, scenes: str | None = None, confidence: str | None = None,
               npy: bool = False, depth_format: str | None = None, depth_png16: bool = False,
               summary: bool = False, options: dict | None = None) -> tuple[list[WorkItem], list[str]]:
    """Work items for ``triangulate``; returns (items, problems).

    ``output`` ending in ``.ply``/``.npy`` names the cloud of a single disparity file;
    otherwise it is a folder receiving ``<name>/cloud.ply`` (+ depth, summary).
    Calibration and colour image default to ``calib.txt``/``im0.png`` beside the disparity,
    then in ``scenes/<name>/``.
    """
    out = Path(output)
    single = out.suffix.lower() in (".ply", ".npy")
    found, problems = _find_inputs(inputs)
    if not found:
        raise DataError(f"{', '.join(inputs)}: no disparity maps found"
                        + (f" ({problems[0]})" if problems else ""))
    if single and len(found) > 1:
        raise DataError(f"{output}: one output file for {len(found)} disparity maps; give a folder instead")
    scene_pairs = _scene_pairs(scenes) if scenes else {}
    items = []
    for name, disp in found:
        def beside(fname: str, disp: Path = disp, name: str = name) -> str | None:
            for folder in [disp.parent] + ([Path(scenes) / name] if scenes else []):
                if (folder / fname).is_file():
                    return str(folder / fname)
            return None

        recorded = _match_inputs(disp.parent)
        scene = scene_pairs.get(name)
        if scene is not None:  # --scenes paired as match pairs them: the pair of the same name
            recorded = {**recorded, **{k: v for k, v in (("calib", scene.calib), ("left", scene.left)) if v}}
        cal = calib or beside("calib.txt") or recorded.get("calib")
        if cal is None:
            problems.append(f"{disp}: no calibration (give --calib, or put calib.txt beside it or in --scenes/{name}/)")
            continue
        inputs_ = {"disparity": str(disp), "calibration": str(cal)}
        img = image or beside("im0.png") or recorded.get("left")
        if img:
            inputs_["image"] = str(img)
        conf = confidence or beside("conf0.pfm")
        if conf:
            inputs_["confidence"] = str(conf)
        # What the match saw: the valid masks (unmatched pixels) and the range it searched.
        for key, fname in (("left_valid", "valid0.png"), ("right_valid", "valid1.png")):
            mask = recorded.get(key) or beside(fname)
            if mask:
                inputs_[key] = str(mask)
        searched = _searched_range(disp.parent)
        if searched is not None:
            inputs_["params"] = searched["source"]
        if single:
            stem = out.with_suffix("")
            outputs = {"cloud": str(out)}
            if depth_format:
                outputs["depth"] = f"{stem}_depth.{depth_format}"
            if depth_png16:
                outputs["depth_png16"] = f"{stem}_depth_mm.png"
            if summary:
                outputs["summary"] = f"{stem}_summary.json"
        else:
            folder = out / name
            outputs = {"cloud": str(folder / ("cloud.npy" if npy else "cloud.ply")),
                       "depth": str(folder / f"depth.{depth_format or 'pfm'}")}
            if depth_png16:
                outputs["depth_png16"] = str(folder / "depth_mm.png")
            if summary:
                outputs["summary"] = str(folder / "summary.json")
        items.append(WorkItem(name, inputs_, outputs, dict(options or {}), folder="" if single else str(out / name),
                              command="triangulate", config_digest=settings_digest(dict(options or {}))))
    check_output_paths(items, None if single else out)
    return items, problems


def _item_range(item: WorkItem) -> dict | None:
    """The range the match searched: from ``params.json`` beside the disparity, else from the
    calib.txt (``[0, ndisp)``, or ``[mindisp, ndisp)`` as ``rectify`` writes it); None if neither
    says."""
    if "params" in item.inputs:
        searched = _searched_range(Path(item.inputs["params"]).parent)
        if searched is not None:
            return searched
    path = item.inputs["calibration"]
    if Path(path).suffix.lower() == ".txt":
        from ..io.middlebury import calib_range, read_calib_txt

        span = calib_range(read_calib_txt(path), path)
        if span is not None:
            return {"min_disp": span[0], "ndisp": span[1], "source": str(path)}
    return None


def triangulate_item(item: WorkItem) -> dict:
    """Triangulate one disparity map (:func:`stereocli.triangulate`); write cloud, depth and
    summary; returns the summary."""
    from ..api import triangulate
    from ..io.atomic import atomic_path, write_text
    from ..io.ply import write_ply
    from ..triangulation import FRAME, write_depth, write_depth_png16_mm

    o = item.options
    image = item.inputs["image"] if "image" in item.inputs and o.get("color", True) else None
    searched = _item_range(item)
    result = triangulate(item.inputs["disparity"], item.inputs["calibration"], image=image,
                         confidence=item.inputs.get("confidence"), units=o.get("units"), use_q=o.get("use_q", False),
                         min_depth=o.get("min_depth"), max_depth=o.get("max_depth"), stride=o.get("stride", 1),
                         normals=o.get("normals", False), scale=o.get("scale"),
                         disparity_range=(searched["min_disp"], searched["ndisp"]) if searched else None,
                         left_valid=item.inputs.get("left_valid"), right_valid=item.inputs.get("right_valid"),
                         min_confidence=o.get("min_confidence"), supported=not o.get("keep_unsupported"))
    geom = result.geometry
    out = item.outputs
    comments = [f"stereocli triangulate: units {geom.units}; frame {FRAME}",
                f"Z = f*B/(d + doffs), f {geom.f:.6g} px, B {geom.baseline:.6g} {geom.units}, "
                f"doffs {geom.doffs:.6g} px, cx {geom.cx:.6g}, cy {geom.cy:.6g}"]
    if out["cloud"].lower().endswith(".npy"):
        with atomic_path(out["cloud"]) as tmp, open(tmp, "wb") as fh:
            np.save(fh, result.points)
    else:
        write_ply(out["cloud"], result.points, colors=result.colors, normals=result.normals,
                  confidence=result.confidence, comments=comments, ascii=o.get("ascii", False))
    if "depth" in out:
        write_depth(out["depth"], result.depth)
    clipped = 0
    if "depth_png16" in out:
        clipped = write_depth_png16_mm(out["depth_png16"], result.depth, geom.units)
    info = result.summary()
    info["range"] = searched
    if clipped:
        info["depth_png16_unrepresentable"] = clipped
    if "summary" in out:
        write_text(out["summary"], json.dumps(info, indent=2) + "\n")
    return info
