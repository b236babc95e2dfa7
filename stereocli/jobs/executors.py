"""Executors: run an item function over work items in-process, in a process pool or on Dask.

Every executor gives the same outcomes in input order; :func:`run_batch` applies the output
policy (refuse to clobber, ``overwrite``, ``skip_existing``), shows progress, retries failed
items, removes the temporaries of items that finally failed, and stops cleanly on SIGINT or
SIGTERM: queued items are cancelled, running ones stopped (pool workers are killed), their
staged outputs removed, and the finished items returned with the signal number.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import signal
import sys
import uuid
from dataclasses import replace
from typing import Callable, Iterable

from .items import (BatchResult, ItemResult, WorkItem, check_outputs, finished_in_run, is_done, prepare_worker,
                    remove_staging_roots, remove_temporaries, run_one)

EXECUTORS = ("inline", "process", "dask")

#: ``record(index, result, final)``: an item's outcome; ``final`` is False for a failure that
#: will be retried.
Record = Callable[[int, ItemResult, bool], None]


def init_worker(threads: int, parent_pid: int | None = None) -> None:
    """Process-pool initialiser: the worker's share of the cores, signals left to the parent
    (and an exit when the parent is gone), then :func:`prepare_worker`."""
    # Split the cores between workers so --jobs N does not oversubscribe; the kernels are
    # written so their output does not depend on the thread count.
    os.environ["NUMBA_NUM_THREADS"] = str(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    if parent_pid is not None:
        from ..process import worker_signals

        worker_signals(parent_pid)
    try:
        import cv2

        cv2.setNumThreads(threads)
    except ImportError:
        pass
    prepare_worker()


def _progress(total: int, desc: str, enabled: bool | None):
    from tqdm import tqdm

    if enabled is None:
        enabled = sys.stderr.isatty()
    return tqdm(total=total, desc=desc, unit="item", file=sys.stderr, disable=not enabled or total <= 1)


def run_batch(
    items: Iterable[WorkItem],
    item_fn: Callable[[WorkItem], dict],
    *,
    jobs: int = 1,
    overwrite: bool = False,
    skip_existing: bool = False,
    retries: int = 0,
    progress: bool | None = None,
    desc: str = "",
    verbose_errors: bool = False,
    executor: str | None = None,
    scheduler: str | None = None,
) -> BatchResult:
    """Run ``item_fn`` over ``items``; returns per-item results in input order.

    ``executor``: ``"inline"`` (default for 1 job), ``"process"`` (default for ``jobs > 1``)
    or ``"dask"`` (``scheduler`` = ``tcp://host:port`` or ``local``; the default whenever
    ``scheduler`` is given). Paths are made absolute first. Items whose planning failed
    (``item.error``) fail without running. Failed items are retried up to ``retries`` times.
    Each item's outputs are committed together (:func:`~stereocli.jobs.items.run_one`); what a
    failed or interrupted item staged is removed. On SIGINT/SIGTERM the result holds the
    finished items and ``interrupted`` (the signal number).
    """
    from ..process import interrupts_raise

    run_id = uuid.uuid4().hex[:16]
    items = [replace(item.absolute(), run_id=run_id) for item in items]
    results, todo = _triage(items, skip_existing)
    check_outputs([items[i] for i in todo], overwrite=overwrite, skip_existing=skip_existing)
    if executor is None and scheduler:
        executor = "dask"
    executor = executor or ("process" if jobs > 1 and len(todo) > 1 else "inline")
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}")
    if executor == "dask":
        from .dask import check_scheduler

        check_scheduler(scheduler)  # fail before any work: bad address or Dask not installed
    for root in {os.path.dirname(items[i].folder) for i in todo if items[i].folder}:
        os.makedirs(root, exist_ok=True)  # workers check they see it (a shared filesystem)
    bar = _progress(len(todo), desc, progress)
    final: set[int] = set()

    def record(i: int, res: ItemResult, is_final: bool) -> None:
        results[i] = res
        if is_final:
            final.add(i)
            bar.update(1)

    interrupted = None
    with interrupts_raise():
        try:
            if executor == "dask":
                # The cluster retries within one session (no reconnect or new LocalCluster per round).
                from .dask import run_dask

                run_dask([items[i] for i in todo], item_fn, verbose_errors, scheduler, retries, jobs=jobs,
                         record=lambda k, res, is_final: record(todo[k], res, is_final))
            else:
                _run_rounds(executor, items, todo, item_fn, jobs, verbose_errors, retries, record)
        except KeyboardInterrupt as exc:
            interrupted = getattr(exc, "signum", signal.SIGINT)
        finally:
            _recover_committed(items, todo, results, final, record)
            bar.close()
            _tidy(items, todo, results, final, remote=executor == "dask" and scheduler != "local")
    if interrupted:
        return BatchResult([results[i] for i in range(len(items)) if i in results], interrupted=interrupted,
                           total=len(items))
    return BatchResult([results[i] for i in range(len(items))])


def _triage(items: list[WorkItem], skip_existing: bool) -> tuple[dict[int, ItemResult], list[int]]:
    """Outcomes known before running (planning failures, items skipped as done) and the indices
    of the items to run."""
    results: dict[int, ItemResult] = {}
    todo = []
    for i, item in enumerate(items):
        if item.error:  # planning failed: fails without running
            results[i] = ItemResult.failure(item, item.error, item.error_code)
        elif skip_existing and is_done(item):
            remove_temporaries(item)  # what a killed later attempt staged
            results[i] = ItemResult(item.name, "skipped", message="outputs exist", inputs=item.inputs,
                                    outputs=item.outputs)
        else:
            todo.append(i)
    return results, todo


def _tidy(items: list[WorkItem], todo: list[int], results: dict, final: set[int], remote: bool) -> None:
    """Remove what failed and unfinished items staged, then the empty staging roots. On a remote
    Dask cluster an interrupted item may still be running on its worker: its folder is left."""
    for i in todo:
        if (i in final and results[i].status == "failed") or (i not in final and not remote):
            remove_temporaries(items[i])
    remove_staging_roots(items)


def _recover_committed(items, todo, results, final, record: Record) -> None:
    """Items whose outputs this run committed although their result never arrived (the parent
    was interrupted, or the scheduler lost, between the commit and the report) are ok."""
    for i in todo:
        if (i not in final or results[i].status == "failed") and finished_in_run(items[i]):
            res = ItemResult(items[i].name, "ok", message="finished; its details were lost (interrupted, or the "
                             "scheduler was lost)", inputs=items[i].inputs, outputs=items[i].outputs,
                             attempts=max(1, results[i].attempts if i in results else 1))
            record(i, res, i not in final)


def _run_rounds(executor, items, todo, item_fn, jobs, verbose_errors, retries, record: Record) -> None:
    """Run the pending items, then the failed ones again, up to ``retries`` more rounds."""
    pending = todo
    attempt = 0
    while pending:
        attempt += 1
        failed: list[int] = []

        def done(k: int, res: ItemResult) -> None:
            i = pending[k]
            res.attempts = attempt
            retry = res.status == "failed" and attempt <= retries
            if retry:
                failed.append(i)
            record(i, res, not retry)

        batch = [items[i] for i in pending]
        if executor == "process":
            _process_pool(batch, item_fn, jobs, verbose_errors, done)
        else:
            for k, item in enumerate(batch):
                done(k, run_one(item_fn, item, verbose_errors))
        pending = sorted(failed)


def _process_pool(items: list[WorkItem], item_fn, jobs: int, verbose_errors: bool,
                  done: Callable[[int, ItemResult], None]) -> None:
    """Run ``items`` in ``jobs`` spawned worker processes; ``done(k, result)`` as each finishes.

    On an interrupt the workers are killed (their items' staged outputs are removed by the
    caller) and the interrupt propagates.
    """
    from ..process import interrupts_blocked

    threads = max(1, (os.cpu_count() or 1) // jobs)
    ctx = multiprocessing.get_context("spawn")  # fork is unsafe once numba threads exist
    pool = cf.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=init_worker,
                                  initargs=(threads, os.getpid()))
    try:
        # Workers start with SIGINT/SIGTERM blocked and then ignore them: a Ctrl-C sent to the
        # whole process group is handled here alone.
        with interrupts_blocked():
            futures = {pool.submit(run_one, item_fn, item, verbose_errors): k for k, item in enumerate(items)}
        for fut in cf.as_completed(futures):
            k = futures[fut]
            try:
                res = fut.result()
            except Exception as exc:  # noqa: BLE001 - a dead worker fails its item only
                res = ItemResult.failure(items[k], f"worker died: {exc}")
            done(k, res)
    except BaseException:
        _kill_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _kill_workers(pool: cf.ProcessPoolExecutor) -> None:
    """SIGKILL the pool's worker processes and wait for them (their items are abandoned)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for proc in processes:
        if proc.is_alive():
            proc.kill()
    for proc in processes:
        proc.join(timeout=5)
