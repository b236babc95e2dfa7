"""Executors: run an item function over work items in-process, in a process pool or on Dask.

Every executor gives the same outcomes in input order; :func:`run_batch` applies the output
policy (refuse to clobber, ``overwrite``, ``skip_existing``), shows progress, retries failed
items and removes the temporaries of items that finally failed.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import sys
from typing import Callable, Iterable

from .items import (BatchResult, ItemResult, WorkItem, check_outputs, is_done, prepare_worker, remove_temporaries,
                    run_one)

EXECUTORS = ("inline", "process", "dask")


def init_worker(threads: int) -> None:
    """Process-pool initialiser: the worker's share of the cores, then :func:`prepare_worker`."""
    # Split the cores between workers so --jobs N does not oversubscribe; the kernels are
    # written so their output does not depend on the thread count.
    os.environ["NUMBA_NUM_THREADS"] = str(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)
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
    ``scheduler`` is given). Failed items are retried up to ``retries`` times. Outputs are never
    half-written because item functions write atomically; temporaries left beside the outputs
    of items that finally failed are removed.
    """
    items = list(items)
    check_outputs(items, overwrite=overwrite, skip_existing=skip_existing)
    results: dict[int, ItemResult] = {}
    todo = []
    for i, item in enumerate(items):
        if skip_existing and is_done(item):
            results[i] = ItemResult(item.name, "skipped", message="outputs exist", inputs=item.inputs,
                                    outputs=item.outputs)
        else:
            todo.append(i)
    if executor is None and scheduler:
        executor = "dask"
    executor = executor or ("process" if jobs > 1 and len(todo) > 1 else "inline")
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}")
    if executor == "dask":
        from .dask import check_scheduler

        check_scheduler(scheduler)  # fail before any work: bad address or Dask not installed
    bar = _progress(len(todo), desc, progress)
    try:
        if executor == "dask":
            # The cluster retries within one session (no reconnect or new LocalCluster per round).
            from .dask import run_dask

            done = run_dask([items[i] for i in todo], item_fn, verbose_errors, bar, scheduler, retries, jobs=jobs)
            results.update(zip(todo, done))
        else:
            _run_rounds(executor, items, todo, item_fn, jobs, verbose_errors, bar, retries, results)
    finally:
        bar.close()
    for i in todo:
        if results[i].status == "failed":
            remove_temporaries(items[i])
    return BatchResult([results[i] for i in range(len(items))])


def _run_rounds(executor, items, todo, item_fn, jobs, verbose_errors, bar, retries, results) -> None:
    """Run the pending items, then the failed ones again, up to ``retries`` more rounds."""
    pending = todo
    attempt = 0
    while pending:
        attempt += 1
        batch = [items[i] for i in pending]
        if executor == "process":
            done = _process_pool(batch, item_fn, jobs, verbose_errors, bar)
        else:
            done = _inline(batch, item_fn, verbose_errors, bar)
        for i, res in zip(pending, done):
            res.attempts = attempt
            results[i] = res
        pending = [i for i in pending if results[i].status == "failed"] if attempt <= retries else []


def _inline(items: list[WorkItem], item_fn, verbose_errors: bool, bar) -> list[ItemResult]:
    out = []
    for item in items:
        out.append(run_one(item_fn, item, verbose_errors))
        bar.update(1)
    return out


def _process_pool(items: list[WorkItem], item_fn, jobs: int, verbose_errors: bool, bar) -> list[ItemResult]:
    threads = max(1, (os.cpu_count() or 1) // jobs)
    ctx = multiprocessing.get_context("spawn")  # fork is unsafe once numba threads exist
    out: list[ItemResult | None] = [None] * len(items)
    with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=init_worker,
                                initargs=(threads,)) as pool:
        futures = {pool.submit(run_one, item_fn, item, verbose_errors): k for k, item in enumerate(items)}
        for fut in cf.as_completed(futures):
            k = futures[fut]
            try:
                out[k] = fut.result()
            except Exception as exc:  # noqa: BLE001 - a dead worker fails its item only
                out[k] = ItemResult.failure(items[k], f"worker died: {exc}")
            bar.update(1)
    return out  # type: ignore[return-value]
