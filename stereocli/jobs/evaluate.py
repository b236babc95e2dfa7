"""``stereocli eval`` as batch work: a results folder's scenes scored on any executor.

Only paths travel to the workers (:func:`eval_item`); each returns its scene's outcome
(:func:`stereocli.evaluation.folders.score_scene`), and the report is assembled in GT-scene order
(:func:`stereocli.evaluation.folders.folder_report`), so it is the same whichever executor ran the
scenes.
"""

from __future__ import annotations

import os
from typing import Any, Sequence

from ..api import evaluate as evaluate_inputs
from ..errors import Interrupted
from ..evaluation.folders import SceneScorer, SceneTask, score_scene
from ..evaluation.scoring import EvalOptions, EvalReport
from .executors import run_batch
from .items import WorkItem


def plan_items(tasks: Sequence[SceneTask], options: EvalOptions) -> list[WorkItem]:
    """One :class:`WorkItem` per scene task (no outputs: the outcome returns to the caller)."""
    items = []
    for task in tasks:
        inputs = {"gt": task.gt, "result": task.result}
        if task.time is not None:
            inputs["time"] = task.time
        items.append(WorkItem(task.name, inputs, {}, {"kind": task.kind, "eval_options": options}))
    return items


def eval_item(item: WorkItem) -> dict[str, Any]:
    """Score one scene; returns its :func:`~stereocli.evaluation.folders.score_scene` outcome."""
    task = SceneTask(item.name, item.options["kind"], item.inputs["gt"], item.inputs["result"],
                     item.inputs.get("time"))
    return score_scene(task, item.options["eval_options"])


def batch_scorer(*, jobs: int = 1, scheduler: str | None = None, retries: int = 0, executor: str | None = None,
                 progress: bool | None = None, verbose_errors: bool = False) -> SceneScorer:
    """A scorer that runs the scene tasks with :func:`~stereocli.jobs.executors.run_batch`.

    A scene whose scoring crashed on every attempt (bug, dead worker, lost task) becomes a
    ``{"failure": message}`` outcome; bad data is already an outcome and is not retried.
    """

    def score(tasks: Sequence[SceneTask], options: EvalOptions) -> list[dict[str, Any]]:
        batch = run_batch(plan_items(tasks, options), eval_item, jobs=jobs, scheduler=scheduler, retries=retries,
                          executor=executor, progress=progress, desc="eval", verbose_errors=verbose_errors)
        if batch.interrupted:
            raise Interrupted(batch.interrupted)
        # The report names each scene beside its message already.
        return [r.details if r.status == "ok" else {"failure": r.message.removeprefix(f"{r.name}: ") or "failed"}
                for r in batch.results]

    return score


def evaluate(
    results: str | os.PathLike,
    ground_truth: str | os.PathLike,
    *,
    options: EvalOptions | None = None,
    jobs: int = 1,
    scheduler: str | None = None,
    retries: int = 0,
    executor: str | None = None,
    progress: bool | None = None,
    verbose_errors: bool = False,
) -> EvalReport:
    """:func:`stereocli.evaluate` with folder-mode scenes on an executor.

    ``jobs``, ``scheduler``, ``retries``, ``executor``, ``progress``: as in
    :func:`~stereocli.jobs.executors.run_batch` (in-process by default; ``jobs > 1`` a process
    pool; ``scheduler`` = ``tcp://host:port`` or ``local`` Dask). The report does not depend on
    them. A bad ``scheduler`` or a missing Dask raises :class:`~stereocli.errors.ConfigError`
    before anything is read, in pair and folder mode.
    """
    if scheduler is not None or executor == "dask":
        from .dask import check_scheduler

        check_scheduler(scheduler)
    scorer = batch_scorer(jobs=jobs, scheduler=scheduler, retries=retries, executor=executor, progress=progress,
                          verbose_errors=verbose_errors)
    return evaluate_inputs(results, ground_truth, options=options, scorer=scorer)
