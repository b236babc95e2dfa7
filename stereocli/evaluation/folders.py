"""A results folder scored against a folder of ground truth, in three steps.

:func:`plan_folder` pairs GT scenes with results (paths only, one :class:`SceneTask` per scene
to score), a *scorer* runs :func:`score_scene` on every task (in-process by default;
:mod:`stereocli.jobs.evaluate` supplies one that runs the tasks on any executor), and
:func:`folder_report` assembles the report in GT-scene order, so it is the same whichever
scorer ran the scenes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from ..errors import ConfigError, DataError, StereoError
from . import datasets as ds
from .scoring import EvalOptions, EvalReport, SceneResult, add_mask_notes, evaluate_pair, rules_text


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
    remaining = iter(outcomes)
    scenes: list[SceneResult] = []
    failures: list[dict[str, str]] = []
    resolutions: set[str] = set()
    for slot in plan.slots:
        if not isinstance(slot, SceneTask):
            failures.append(slot)
            continue
        done = next(remaining)
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
    add_mask_notes(report)
    return report


__all__ = ["FolderPlan", "SceneScorer", "SceneTask", "folder_report", "plan_folder", "score_in_process",
           "score_scene"]
