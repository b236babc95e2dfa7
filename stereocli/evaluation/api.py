"""Scoring one pair or a results folder against ground truth: the library behind ``stereocli eval``.

``evaluate_pair`` scores one estimate against one :class:`~stereocli.evaluation.datasets.Scene`
(:mod:`stereocli.evaluation.scoring`); ``evaluate_folder`` matches a results folder with a GT
folder by scene name (missing results are failures, never silently skipped;
:mod:`stereocli.evaluation.folders`); ``evaluate`` accepts whatever the command line got (a
file or a folder on either side). All return plain dataclasses whose ``as_dict()`` is the JSON
report.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataError
from . import datasets as ds
from .folders import SceneScorer, SceneTask, folder_report, plan_folder, score_in_process
from .metrics import threshold_key
from .scoring import EvalOptions, EvalReport, SceneResult, evaluate_pair, rules_text, weighted_average


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


def evaluate(
    results: str | os.PathLike,
    ground_truth: str | os.PathLike,
    *,
    options: EvalOptions | None = None,
    scorer: SceneScorer | None = None,
) -> EvalReport:
    """Do what ``stereocli eval RESULTS GROUND_TRUTH`` does: pair mode or folder mode.

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
    """Return the GT scene to score one estimate against.

    That is a GT file, a scene folder, the scene ``kitti_name`` (default ``name``) of a KITTI root,
    or the scene ``name`` of a folder of scenes (exact, then case-insensitive). ``label`` names the
    estimate in errors.
    """
    if ground_truth.is_file():
        return ds.load_gt_file(ground_truth, dataset=options.dataset, gt_scale=options.gt_scale,
                               resolution=options.scene_resolution())
    layout = ds.detect_layout(ground_truth)
    if layout == "kitti" or options.dataset == "kitti":
        scene_name = kitti_name or name
        if not scene_name:
            raise DataError(f"{ground_truth}: a KITTI root holds many scenes; name the one to score")
        return ds.load_kitti(ground_truth, scene_name)
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


__all__ = ["EvalOptions", "SceneResult", "EvalReport", "SceneScorer", "SceneTask", "evaluate", "evaluate_pair",
           "evaluate_folder", "pair_report", "pair_scene", "weighted_average", "rules_text", "threshold_key"]
