"""Scoring one pair or a results folder against ground truth: the library behind ``stereocli eval``.

``evaluate_pair`` scores one estimate against one :class:`~stereocli.evaluation.datasets.Scene`;
``evaluate_folder`` matches a results folder with a GT folder by scene name (missing results
are failures, never silently skipped); ``evaluate`` accepts whatever the command line got (a
file or a folder on either side). All return plain dataclasses whose ``as_dict()`` is the JSON
report.

Folder mode is three steps: :func:`plan_folder` pairs GT scenes with results (paths only, one
:class:`SceneTask` per scene to score), a *scorer* runs :func:`score_scene` on every task
(in-process by default; :mod:`stereocli.jobs.evaluate` supplies one that runs the tasks on any
executor), and :func:`folder_report` assembles the report in GT-scene order, so it is the same
whichever scorer ran the scenes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import ConfigError, DataError, StereoError
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
    threshold_key,
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
        _add_mask_notes(report)
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
            parts.append(f"GT at {letters} resolution (full-resolution GT not available): scored at {letters}, "
                         f"thresholds and errors in FULL-resolution px (errors x{'/'.join(str(ds.RESOLUTION_FACTORS[r]) for r in res)})")
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


@dataclass
class SceneTask:
    """One GT scene to score, as paths (picklable, cheap to send to a worker).

    ``kind`` is the GT layout (:class:`~stereocli.evaluation.datasets.GTEntry`), ``gt`` the scene
    folder or KITTI root, ``result`` the disparity file, ``time`` its ``time.txt`` if any.
    """

    name: str
    kind: str
    gt: str
    result: str
    time: str | None = None


#: ``scorer(tasks, options) -> outcomes``, one :func:`score_scene` outcome per task, in order.
SceneScorer = Callable[[Sequence[SceneTask], EvalOptions], list[dict[str, Any]]]


def score_scene(task: SceneTask, options: EvalOptions) -> dict[str, Any]:
    """Load one GT scene and score its result.

    Returns ``{"scene": SceneResult | None, "resolution": str | None, "failure": str | None,
    "config_error": str | None}``: bad data (:class:`DataError`) is a *scored outcome*
    (``failure``, the one-line message), not an exception, so an executor's retries only re-run
    scenes that crashed. The :class:`SceneResult` holds numbers only, plus its arrays when
    ``keep_arrays`` is set.
    """
    entry = ds.GTEntry(task.name, task.kind, Path(task.gt))
    out: dict[str, Any] = {"scene": None, "resolution": None, "failure": None, "config_error": None}
    try:
        scene = ds.load_entry(entry, gt_scale=options.gt_scale, resolution=options.scene_resolution())
        out["resolution"] = scene.resolution
        out["scene"] = evaluate_pair(task.result, scene, options=options,
                                     time=ds.read_time(Path(task.time) if task.time else None), name=entry.name)
    except ConfigError as exc:
        out["config_error"] = str(exc)
    except StereoError as exc:
        out["failure"] = str(exc)
    return out


def score_in_process(tasks: Sequence[SceneTask], options: EvalOptions) -> list[dict[str, Any]]:
    """The default scorer: :func:`score_scene` on each task, one after the other."""
    return [score_scene(task, options) for task in tasks]


@dataclass
class FolderPlan:
    """GT scenes paired with results: per GT scene, in order, a :class:`SceneTask` or a failure
    found while pairing (``{"name", "message"}``); the dataset kinds seen; unused result names."""

    slots: list[SceneTask | dict[str, str]]
    kinds: list[str]
    unused: list[str]

    @property
    def tasks(self) -> list[SceneTask]:
        return [s for s in self.slots if isinstance(s, SceneTask)]


def plan_folder(results_dir: str | os.PathLike, gt_dir: str | os.PathLike, options: EvalOptions) -> FolderPlan:
    """Pair every GT scene under ``gt_dir`` with the result of the same name in ``results_dir``.

    Exact names claim their results first; a case-insensitive match (Tsukuba vs tsukuba) only
    takes a result no other scene claims exactly, so v2 "teddy" never scores MiddEval3 "Teddy";
    a scene that several results match case-insensitively fails, naming them.
    """
    entries = ds.find_gt_scenes(Path(gt_dir), dataset=options.dataset)
    results = ds.find_results(Path(results_dir))
    kinds: set[str] = set()
    slots: list[SceneTask | dict[str, str]] = []
    exact = {e.name for e in entries if e.name in results}
    used: set[str] = set()
    for entry in entries:
        kinds.add("middlebury-v2" if entry.kind in ("middlebury2003", "middlebury2001") else entry.kind)
        res = results.get(entry.name)
        if res is None:
            spare = {k: v for k, v in results.items() if k not in exact and k not in used}
            try:
                res = ds.match_name(entry.name, spare)
            except DataError as exc:  # several candidates: this scene fails, the others go on
                used.update(k for k in spare if k.casefold() == entry.name.casefold())
                slots.append({"name": entry.name, "message": str(exc)})
                continue
        if res is None:
            slots.append({"name": entry.name, "message": f"missing result (no {entry.name}/disp0*.pfm or "
                                                         f"{entry.name}.pfm in {results_dir})"})
            continue
        used.add(res.name)
        if res.path is None:
            slots.append({"name": entry.name, "message": res.problem or "no result"})
            continue
        slots.append(SceneTask(entry.name, entry.kind, str(entry.path), str(res.path),
                               None if res.time_path is None else str(res.time_path)))
    return FolderPlan(slots, sorted(kinds), sorted(set(results) - used))


def folder_report(plan: FolderPlan, outcomes: Sequence[dict[str, Any]], options: EvalOptions) -> EvalReport:
    """The report of a planned folder from one :func:`score_scene` outcome per task, in order.

    An outcome of ``{"failure": message}`` alone (a scene whose scoring crashed) is a failure.
    Raises :class:`ConfigError` when a scene reported a configuration error.
    """
    outcomes = iter(outcomes)
    scenes: list[SceneResult] = []
    failures: list[dict[str, str]] = []
    resolutions: set[str] = set()
    for slot in plan.slots:
        if not isinstance(slot, SceneTask):
            failures.append(slot)
            continue
        done = next(outcomes)
        if done.get("config_error"):
            raise ConfigError(done["config_error"])
        if done.get("resolution"):
            resolutions.add(done["resolution"])
        if done.get("failure") is not None:
            failures.append({"name": slot.name, "message": done["failure"]})
            continue
        result: SceneResult = done["scene"]
        scenes.append(result)
        for err in result.errors:
            failures.append({"name": slot.name, "message": err, "partial": "true"})
    notes = []
    if plan.unused:
        notes.append(f"results without ground truth (not scored): {', '.join(plan.unused)}")
    report = EvalReport(scenes=scenes, failures=failures,
                        rules=rules_text(plan.kinds, options, sorted(resolutions) or ["F"]),
                        thresholds=tuple(options.thresholds), quantiles=tuple(options.quantiles),
                        mode="folder", notes=notes)
    _add_mask_notes(report)
    return report


def evaluate_folder(
    results_dir: str | os.PathLike,
    gt_dir: str | os.PathLike,
    *,
    options: EvalOptions | None = None,
    dataset: str | None = None,
    scorer: SceneScorer | None = None,
) -> EvalReport:
    """Score every GT scene under ``gt_dir`` with the result of the same name in ``results_dir``.

    GT scenes without a result are failures ("missing result"); results without GT are noted
    (not scored). A scene that fails to load or score is a failure with a one-line message.
    ``scorer`` runs the scene tasks (default :func:`score_in_process`); the report does not
    depend on it.
    """
    options = options or EvalOptions(dataset=dataset)
    if dataset is not None and options.dataset is None:
        options.dataset = dataset
    plan = plan_folder(results_dir, gt_dir, options)
    outcomes = (scorer or score_in_process)(plan.tasks, options)
    return folder_report(plan, outcomes, options)


def _add_mask_notes(report: EvalReport) -> None:
    """The derived masks, and what each scene noted (its GT size, a region without GT), as report notes."""
    derived = sorted({s.name for s in report.scenes if "nonocc" in s.mask_notes})
    if derived:
        report.notes.append(f"nonocc masks DERIVED (not official) for: {', '.join(derived)}")
    report.notes += [f"{s.name}: {note}" for s in report.scenes for note in s.notes]


def evaluate(
    results: str | os.PathLike,
    ground_truth: str | os.PathLike,
    *,
    options: EvalOptions | None = None,
    scorer: SceneScorer | None = None,
) -> EvalReport:
    """What ``stereocli eval RESULTS GROUND_TRUTH`` does: pair mode or folder mode.

    Pair mode (RESULTS is a file, or a folder holding ``disp0*.pfm`` itself): errors raise
    :class:`DataError`; the one pair is scored in-process. Folder mode: per-scene failures are
    collected in the report; ``scorer`` runs the scenes (see :func:`evaluate_folder`).
    """
    options = options or EvalOptions()
    results, ground_truth = Path(results), Path(ground_truth)
    if not results.exists():
        raise DataError(f"{results}: no such file or folder")
    if not ground_truth.exists():
        raise DataError(f"{ground_truth}: no such file or folder")
    pair_file: Path | None = None
    time_path: Path | None = None
    if results.is_file():
        pair_file = results
        time_path = ds._time_file(results.parent) if results.name.startswith("disp0") else None
    elif any(results.glob("disp0*.pfm")) and (ground_truth.is_file() or options.dataset == "kitti"
                                              or ds.detect_layout(ground_truth) is not None):
        entry = ds.result_in_folder(results)
        if entry.path is None:
            raise DataError(entry.problem or f"{results}: no result")
        pair_file, time_path = entry.path, entry.time_path
    if pair_file is None:
        if ground_truth.is_file():
            raise ConfigError(f"{results} is a folder but {ground_truth} is a file; give a GT folder")
        return evaluate_folder(results, ground_truth, options=options, scorer=scorer)
    # Pair mode: a folder of scenes gives the one named like the result (its folder or file stem).
    name = pair_file.parent.name if pair_file.name.startswith("disp0") else pair_file.stem
    # A KITTI frame is named like the result too (its folder for disp0*.pfm).
    scene = pair_scene(ground_truth, options, name=name, kitti_name=name, label=str(pair_file))
    return evaluate_pair(pair_file, scene, options=options, time=ds.read_time(time_path)).as_report()


def pair_scene(ground_truth: Path, options: EvalOptions, *, name: str | None, kitti_name: str | None = None,
               label: str = "estimate") -> ds.Scene:
    """The GT scene to score one estimate against: a GT file, a scene folder, the scene
    ``kitti_name`` (default ``name``) of a KITTI root, or the scene ``name`` of a folder of
    scenes (exact, then case-insensitive). ``label`` names the estimate in errors."""
    if ground_truth.is_file():
        return ds.load_gt_file(ground_truth, dataset=options.dataset, gt_scale=options.gt_scale,
                               resolution=options.scene_resolution())
    layout = ds.detect_layout(ground_truth)
    if layout == "kitti" or options.dataset == "kitti":
        if not (kitti_name or name):
            raise DataError(f"{ground_truth}: a KITTI root holds many scenes; name the one to score")
        return ds.load_kitti(ground_truth, kitti_name or name)
    if layout is not None:
        return ds.load_scene(ground_truth, dataset=options.dataset, gt_scale=options.gt_scale,
                             resolution=options.scene_resolution())
    entries = ds.find_gt_scenes(ground_truth, dataset=options.dataset)
    if not name:
        raise DataError(f"{ground_truth}: a folder of {len(entries)} scenes; name the one to score")
    match = [e for e in entries if e.name == name] or [e for e in entries if e.name.casefold() == name.casefold()]
    if not match:
        raise DataError(f"{label}: no GT scene named {name!r} under {ground_truth}")
    if len(match) > 1:
        raise DataError(f"{label}: ambiguous GT scene: {' and '.join(str(e.path) for e in match)} both match "
                        f"{name!r} (names compared without case); give the scene folder itself")
    return ds.load_entry(match[0], gt_scale=options.gt_scale, resolution=options.scene_resolution())


def pair_report(
    estimate: np.ndarray | str | os.PathLike,
    ground_truth: ds.Scene | str | os.PathLike,
    *,
    options: EvalOptions | None = None,
    time: float | None = None,
    name: str | None = None,
) -> EvalReport:
    """One estimate scored against one GT scene, as a report (``stereocli eval`` in pair mode).

    ``ground_truth``: a loaded :class:`Scene`, or a path as :func:`pair_scene` takes it (with
    ``name`` for a folder of scenes or a KITTI root); ``name`` also names the row.
    """
    options = options or EvalOptions()
    if not isinstance(ground_truth, ds.Scene):
        path = Path(ground_truth)
        if not path.exists():
            raise DataError(f"{path}: no such file or folder")
        label = str(estimate) if isinstance(estimate, (str, os.PathLike)) else "estimate"
        ground_truth = pair_scene(path, options, name=name, label=label)
    return evaluate_pair(estimate, ground_truth, options=options, time=time, name=name).as_report()


__all__ = ["EvalOptions", "SceneResult", "EvalReport", "FolderPlan", "SceneScorer", "SceneTask", "evaluate",
           "evaluate_pair", "evaluate_folder", "folder_report", "pair_report", "pair_scene", "plan_folder",
           "score_in_process", "score_scene", "weighted_average", "rules_text", "threshold_key"]
