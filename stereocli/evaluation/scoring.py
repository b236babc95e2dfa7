"""Scoring one disparity map against one ground-truth scene: the scoring options, a scene's
scores, a report of scenes and the rules applied, in words.

:func:`evaluate_pair` scores one estimate against one :class:`~stereocli.evaluation.datasets.Scene`;
:mod:`stereocli.evaluation.folders` scores the scenes of a folder with it, and
:mod:`stereocli.evaluation.api` is the library behind ``stereocli eval``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError, DataError
from . import datasets as ds
from .metrics import (
    DEFAULT_QUANTILES,
    DEFAULT_THRESHOLDS,
    check_estimate,
    clip_estimate,
    downsample_gt,
    downsample_mask,
    kitti_interpolate_background,
    kitti_stats,
    middlebury_stats,
    size_factor,
    upsample_nearest,
)

REGION_ORDER = ("nonocc", "all", "disc")


@dataclass
class EvalOptions:
    """Scoring options (defaults = the official rules of each benchmark).

    thresholds : bad-pixel thresholds, in the units chosen by ``threshold_units``.
    resolution : MiddEval3 resolution of the GT (``F``/``H``/``Q``); ``auto`` reads it from a
        ``trainingQ``-style folder name, else ``F``.
    threshold_units : ``full`` (default) reports thresholds and errors in full-resolution
        pixels: errors at a Q GT are multiplied by 4, so ``bad2.0`` = 0.5 px at Q. ``native``
        uses the pixels of the grid that is scored (unofficial for H/Q GT).
    same_resolution : unofficial: score at the estimate's size (GT subsampled by nearest
        neighbour, divided by the factor) instead of upsampling the estimate.
    ndisp : disparity range at the *estimate's* resolution for clipping (default: calib.txt
        for Middlebury 2014; no clipping for v2 unless given).
    dataset : layout override (``middlebury2014``, ``middlebury2003``/``2001``, ``middlebury2005``,
        ``kitti``); never ignored: a GT that does not fit it is an error.
    gt_scale : v2 8-bit GT scale override (default per scene: Tsukuba 16, Venus 8, Teddy/Cones 4;
        Middlebury 2005/2006: 1, 2 or 3 from the image width).
    keep_arrays : keep the scored arrays on each result (for error maps / HTML).
    """

    thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS
    quantiles: tuple[float, ...] = DEFAULT_QUANTILES
    resolution: str = "auto"
    threshold_units: str = "full"
    same_resolution: bool = False
    ndisp: float | None = None
    dataset: str | None = None
    gt_scale: float | None = None
    keep_arrays: bool = False

    def __post_init__(self) -> None:
        if self.resolution not in ("auto", "F", "H", "Q"):
            raise ConfigError(f"resolution must be auto, F, H or Q, got {self.resolution!r}")
        if self.threshold_units not in ("full", "native"):
            raise ConfigError(f"threshold units must be full or native, got {self.threshold_units!r}")
        if self.dataset is not None and self.dataset not in ds.DATASETS:
            raise ConfigError(f"unknown dataset {self.dataset!r}; choose from {', '.join(ds.DATASETS)}")
        if not self.thresholds or any(not np.isfinite(t) or t < 0 for t in self.thresholds):
            raise ConfigError(f"thresholds must be non-negative numbers, got {self.thresholds!r}")
        if self.gt_scale is not None and not 0 < self.gt_scale < np.inf:
            raise ConfigError(f"gt scale must be a positive finite number, got {self.gt_scale!r}")
        if self.ndisp is not None and not 0 < self.ndisp < np.inf:
            raise ConfigError(f"ndisp must be a positive finite number, got {self.ndisp!r}")

    def scene_resolution(self) -> str | None:
        return None if self.resolution == "auto" else self.resolution


@dataclass
class SceneResult:
    """Scores of one scene: ``metrics[region]`` is a dict of numbers, or ``None`` if unscored."""

    name: str
    kind: str
    weight: float
    metrics: dict[str, dict[str, Any] | None]
    size: tuple[int, int]  # estimate (width, height)
    factor: int  # GT size / estimate size
    unit: float  # reported px per scored-grid px
    time: float | None = None
    time_per_mp: float | None = None
    time_per_gd: float | None = None
    errors: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    mask_notes: dict[str, str] = field(default_factory=dict)
    arrays: dict[str, Any] = field(default_factory=dict, repr=False)
    left_image: Path | None = None
    #: The options it was scored with and the GT's resolution (for :meth:`as_report`).
    options: EvalOptions | None = field(default=None, repr=False)
    resolution: str = "F"

    def as_report(self) -> EvalReport:
        """This scene alone as a report (what ``stereocli eval`` gives for one pair), e.g. for
        :func:`~stereocli.evaluation.report.format_table`."""
        options = self.options or EvalOptions()
        failures = [{"name": self.name, "message": e, "partial": "true"} for e in self.errors]
        report = EvalReport(scenes=[self], failures=failures,
                            rules=rules_text([self.kind], options, [self.resolution]),
                            thresholds=tuple(options.thresholds), quantiles=tuple(options.quantiles), mode="pair")
        add_mask_notes(report)
        return report

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "dataset": self.kind, "weight": self.weight}
        for region, values in self.metrics.items():
            out[region] = values
        out.update({"time": self.time, "time_per_mp": self.time_per_mp, "time_per_gd": self.time_per_gd,
                    "size": list(self.size), "scale_factor": self.factor})
        if self.mask_notes:
            out["mask_notes"] = self.mask_notes
        if self.errors:
            out["errors"] = self.errors
        if self.notes:
            out["notes"] = self.notes
        return out


@dataclass
class EvalReport:
    """A scored batch: per-scene results, the weighted average, failures and the rules used.

    Attributes
    ----------
    scenes : one :class:`SceneResult` per scored scene; ``scenes[i].metrics[region][key]``
        (regions ``nonocc``, ``all``; keys ``bad0.5`` ... ``bad4.0``, ``invalid``, ``avgerr``,
        ``rms``, ``A50`` ... ``A99``, KITTI ``D1``, ``density``), in percent or px.
    average : the (weighted) average of every metric per region.
    failures : ``{"name", "message"}`` of scenes (or regions) that could not be scored.
    rules : the rules applied, in words (every report's header).
    thresholds : the bad-pixel thresholds, px.
    to_dict : the report as ``stereocli eval --format json`` prints it.
    """

    scenes: list[SceneResult]
    failures: list[dict[str, str]]
    rules: str
    thresholds: tuple[float, ...]
    quantiles: tuple[float, ...]
    mode: str = "folder"  # folder | pair
    notes: list[str] = field(default_factory=list)

    @property
    def regions(self) -> list[str]:
        seen = {r for s in self.scenes for r in s.metrics}
        return [r for r in REGION_ORDER if r in seen]

    @property
    def average(self) -> dict[str, Any]:
        return weighted_average(self.scenes)

    @property
    def exit_code(self) -> int:
        """0 all scored; 3 some scenes (or regions) failed; 1 nothing could be scored."""
        if not self.scenes:
            return 1
        return 3 if self.failures else 0

    def to_dict(self) -> dict[str, Any]:
        """The report as ``stereocli eval --format json`` prints it (plain JSON types; a
        non-finite number is None)."""
        import json

        return json.loads(json.dumps(json_ready(self.as_dict())))

    def as_dict(self) -> dict[str, Any]:
        return {
            "rules": self.rules,
            "thresholds": list(self.thresholds),
            "scenes": [s.as_dict() for s in self.scenes],
            "average": self.average,
            "failures": self.failures,
            "notes": self.notes,
        }


def json_ready(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (JSON has no inf or NaN)."""
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [json_ready(v) for v in obj]
    return obj


def weighted_average(scenes: Sequence[SceneResult]) -> dict[str, Any]:
    """Weighted mean of every metric per region over the scenes that have it.

    Weights are the MiddEval3 training weights (0.5 / 1.0), 1.0 for other datasets; the sum is
    divided by the sum of the weights of the scenes that contributed.
    """
    out: dict[str, Any] = {"name": "average", "weight": float(sum(s.weight for s in scenes)),
                           "scenes": len(scenes)}
    regions = [r for r in REGION_ORDER if any(s.metrics.get(r) for s in scenes)]
    for region in regions:
        keys: list[str] = []
        for s in scenes:
            for k in (s.metrics.get(region) or {}):
                if k not in keys and k not in ("n",):
                    keys.append(k)
        avg: dict[str, Any] = {}
        for k in keys:
            num = den = 0.0
            for s in scenes:
                v = (s.metrics.get(region) or {}).get(k)
                if v is not None:
                    num += s.weight * v
                    den += s.weight
            avg[k] = num / den if den else None
        out[region] = avg
    for k in ("time", "time_per_mp", "time_per_gd"):
        vals = [(s.weight, getattr(s, k)) for s in scenes if getattr(s, k) is not None]
        den = sum(w for w, _ in vals)
        out[k] = sum(w * v for w, v in vals) / den if den else None
    return out


def rules_text(kinds: Sequence[str], options: EvalOptions, resolutions: Sequence[str] = ("F",)) -> str:
    """One-paragraph statement of the rules used (printed in every report header)."""
    parts = []
    if "middlebury2014" in kinds or "generic" in kinds:
        s = ("MiddEval3 rules: estimates " + ("scored at their own size against the GT subsampled by "
             "nearest neighbour (--same-resolution: UNOFFICIAL)" if options.same_resolution else
             "upsampled to the GT size by nearest neighbour with disparities scaled")
             + "; valid estimates clipped to [0, ndisp]; GT inf not scored; invalid (inf) estimates counted "
             "in 'invalid' and as bad; avgerr/rms/quantiles over valid pixels only; average weighted "
             "(0.5 for PianoL, Playroom, Playtable, Shelves, Vintage)")
        parts.append(s)
    if "middlebury2005" in kinds:
        parts.append("Middlebury 2005/2006 rules: 8-bit GT stored in full-size units, divided by the size's factor "
                     "(Full 1, Half 2, Third 3, told from the image width; 0 unknown); no clipping; invalid estimates "
                     "count as bad; errors in px of the scored size; nonocc masks DERIVED from the GT (z-buffer "
                     "visibility, cross-checked with disp5)")
    if "middlebury-v2" in kinds:
        parts.append("Middlebury v2 rules: 8-bit GT decoded by the scene scale (0 unknown); no clipping; "
                     "invalid estimates count as bad; standard metric bad1.0; nonocc masks DERIVED from the GT "
                     "(z-buffer visibility; Teddy/Cones cross-checked with disp6) unless official masks are present")
    if "kitti" in kinds:
        parts.append("KITTI 2015 rules: missing estimates filled by the devkit background interpolation, "
                     "D1 outlier = |d-gt| > 3 px and > 5 % of gt; density = share of GT pixels with an estimate; "
                     "nonocc = disp_noc (disp_noc_0), all = disp_occ (disp_occ_0); a region without GT is not scored")
    res = sorted(set(resolutions) - {"F"})
    if res:
        letters = "/".join(res)
        if options.threshold_units == "full":
            factors = "/".join(str(ds.RESOLUTION_FACTORS[r]) for r in res)
            parts.append(f"GT at {letters} resolution (full-resolution GT not available): scored at {letters}, "
                         f"thresholds and errors in FULL-resolution px (errors x{factors})")
        else:
            parts.append(f"GT at {letters} resolution: thresholds and errors in {letters} px "
                         f"(native units: UNOFFICIAL, flatters vs full-resolution scoring)")
    return ". ".join(parts) + "."


def _read_estimate(estimate: np.ndarray | str | os.PathLike, scene: ds.Scene | None) -> tuple[np.ndarray, str]:
    if isinstance(estimate, (str, os.PathLike)):
        return ds.load_estimate(Path(estimate), scene), str(estimate)
    return check_estimate(estimate), "estimate"


def evaluate_pair(
    estimate: np.ndarray | str | os.PathLike,
    gt_scene: ds.Scene | str | os.PathLike,
    *,
    options: EvalOptions | None = None,
    time: float | None = None,
    name: str | None = None,
) -> SceneResult:
    """Score one disparity map against one GT scene.

    Parameters
    ----------
    estimate : (h, w) float32 disparity (px, +inf invalid) or a path (PFM, npy, 16-bit PNG).
    gt_scene : a loaded :class:`Scene`, a scene folder, or a GT file.
    time : seconds the matcher took (fills the time, s/MP and s/GD columns).

    Raises
    ------
    DataError on size mismatch (other than 1x/2x/4x), NaN, unreadable files.
    """
    options = options or EvalOptions()
    if not isinstance(gt_scene, ds.Scene):
        p = Path(gt_scene)
        loader = ds.load_gt_file if p.is_file() else ds.load_scene
        gt_scene = loader(p, dataset=options.dataset, gt_scale=options.gt_scale,
                          resolution=options.scene_resolution())
    scene = gt_scene
    if not np.isfinite(scene.gt).any():
        raise DataError(f"{scene.gt_path}: no pixel of the ground truth is known (all unknown/inf); nothing to score")
    est, label = _read_estimate(estimate, scene)
    metrics: dict[str, dict[str, Any] | None] = {}
    arrays: dict[str, Any] = {}
    if scene.kind == "kitti":
        factor, unit = 1, 1.0
        if est.shape != scene.gt.shape:
            raise DataError(f"{label}: size {est.shape[1]}x{est.shape[0]} differs from the KITTI GT size "
                            f"{scene.gt.shape[1]}x{scene.gt.shape[0]}")
        filled = kitti_interpolate_background(est)
        for region in ("nonocc", "all"):
            if region not in scene.masks:  # no GT of this region given: noted, not scored
                continue
            gt_r = scene.mask_gt.get(region)
            metrics[region] = None if gt_r is None else kitti_stats(
                est, gt_r, obj_map=scene.obj_map, filled=filled, thresholds=options.thresholds,
                quantiles=options.quantiles)
        scored_est, scored_gt, masks = filled, scene.gt, dict(scene.masks)
        ndisp_est = None
    else:
        factor = size_factor(est.shape, scene.gt.shape, label)
        full = ds.RESOLUTION_FACTORS[scene.resolution] if options.threshold_units == "full" else 1
        if options.ndisp is not None:
            ndisp_est = float(options.ndisp)
        elif scene.ndisp is not None:
            ndisp_est = scene.ndisp / factor
        else:
            ndisp_est = None
        clip_at = ndisp_est if (scene.kind != "middlebury-v2" or options.ndisp is not None) else None
        if options.same_resolution:
            scored_gt = downsample_gt(scene.gt, factor)
            masks = {r: None if m is None else downsample_mask(m, factor) for r, m in scene.masks.items()}
            scored_est = clip_estimate(est, clip_at)
            unit = float(full * factor) if options.threshold_units == "full" else 1.0
        else:
            scored_gt = scene.gt
            masks = dict(scene.masks)
            scored_est = clip_estimate(upsample_nearest(est, factor), None if clip_at is None else clip_at * factor)
            unit = float(full)
        for region in REGION_ORDER:
            if region not in masks:
                continue
            m = masks[region]
            metrics[region] = None if m is None else middlebury_stats(
                scored_est, scored_gt, m, thresholds=options.thresholds, quantiles=options.quantiles, unit=unit)
    h, w = est.shape
    result = SceneResult(name=name or scene.name, kind=scene.kind, weight=scene.weight, metrics=metrics,
                         size=(w, h), factor=factor, unit=unit, errors=list(scene.errors),
                         notes=list(scene.notes), mask_notes=dict(scene.mask_notes), left_image=scene.left_image,
                         options=options, resolution=scene.resolution)
    if time is not None:
        result.time = float(time)
        result.time_per_mp = time / (w * h / 1e6)
        if ndisp_est:
            result.time_per_gd = time / (w * h * ndisp_est / 1e9)
    if options.keep_arrays:
        arrays.update(estimate=scored_est, gt=scored_gt, masks=masks, unit=unit,
                      raw_estimate=est)
        result.arrays = arrays
    return result


def add_mask_notes(report: EvalReport) -> None:
    """The derived masks, and what each scene noted (its GT size, a region without GT), as report notes."""
    derived = sorted({s.name for s in report.scenes if "nonocc" in s.mask_notes})
    if derived:
        report.notes.append(f"nonocc masks DERIVED (not official) for: {', '.join(derived)}")
    report.notes += [f"{s.name}: {note}" for s in report.scenes for note in s.notes]


__all__ = ["EvalOptions", "EvalReport", "REGION_ORDER", "SceneResult", "add_mask_notes", "evaluate_pair",
           "json_ready", "rules_text", "weighted_average"]
