"""Batches of independent work items, for every subcommand.

This module knows nothing about stereo: it runs an *item function* over :class:`WorkItem`
objects (paths travel, not arrays) with one of several executors, applies the output policy
(refuse to clobber, ``overwrite``, ``skip_existing``), shows progress, records per-item
status and timings, and computes the exit code (0 all ok, 3 some failed).

Item functions must be importable top-level functions (they are pickled by name for process
pools and Dask) that write their outputs atomically (:mod:`stereocli.io.atomic`) and return a
JSON-able dict of details for the run record.
"""

from __future__ import annotations

import concurrent.futures as cf
import glob
import multiprocessing
import os
import sys
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from .errors import EXIT_OK, EXIT_PARTIAL, OutputExistsError, StereoError


@dataclass
class WorkItem:
    """One unit of work: a name, input paths, output paths and per-item options."""

    name: str
    inputs: dict[str, str]
    outputs: dict[str, str]
    options: dict[str, Any] = field(default_factory=dict)

    def existing_outputs(self) -> list[str]:
        return [p for p in self.outputs.values() if Path(p).exists()]


@dataclass
class ItemResult:
    name: str
    status: str  # ok | skipped | failed
    seconds: float = 0.0
    message: str = ""
    details: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, str] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    attempts: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class BatchResult:
    results: list[ItemResult]

    @property
    def failed(self) -> list[ItemResult]:
        return [r for r in self.results if r.status == "failed"]

    @property
    def exit_code(self) -> int:
        return EXIT_PARTIAL if self.failed else EXIT_OK


def check_outputs(items: list[WorkItem], *, overwrite: bool, skip_existing: bool) -> None:
    """Refuse (before any work starts) when outputs exist and no policy was chosen."""
    if overwrite or skip_existing:
        return
    clashes = [p for item in items for p in item.existing_outputs()]
    if clashes:
        more = f" and {len(clashes) - 1} more" if len(clashes) > 1 else ""
        raise OutputExistsError(
            f"{clashes[0]}{more} already exist(s); use --overwrite to replace or --skip-existing to resume"
        )


def _run_one(item_fn: Callable[[WorkItem], dict], item: WorkItem, verbose_errors: bool) -> ItemResult:
    t0 = time.perf_counter()
    try:
        remove_temporaries(item)  # left by an attempt whose process died (killed worker, earlier run)
        details = item_fn(item) or {}
        status, message = "ok", ""
    except StereoError as exc:
        details, status, message = {}, "failed", str(exc)
    except MemoryError:
        details, status, message = {}, "failed", "out of memory"
    except Exception as exc:  # noqa: BLE001 - one item's bug must not kill the batch
        details, status = {}, "failed"
        message = f"{type(exc).__name__}: {exc}"
        if verbose_errors:
            message += "\n" + traceback.format_exc()
    return ItemResult(item.name, status, round(time.perf_counter() - t0, 4), message, details,
                      item.inputs, item.outputs, 1)


def _init_worker(threads: int) -> None:
    # Split the cores between workers so --jobs N does not oversubscribe; the kernels are
    # written so their output does not depend on the thread count.
    os.environ["NUMBA_NUM_THREADS"] = str(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    try:
        import cv2

        cv2.setNumThreads(threads)
    except ImportError:
        pass


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
        if skip_existing and item.outputs and len(item.existing_outputs()) == len(item.outputs):
            results[i] = ItemResult(item.name, "skipped", message="outputs exist", inputs=item.inputs,
                                    outputs=item.outputs)
        else:
            todo.append(i)
    if executor is None and scheduler:
        executor = "dask"
    executor = executor or ("process" if jobs > 1 and len(todo) > 1 else "inline")
    if executor == "dask":
        from .distributed import check_scheduler

        check_scheduler(scheduler)  # fail before any work: bad address or Dask not installed
    bar = _progress(len(todo), desc, progress)
    try:
        attempt = 0
        pending = todo
        if executor == "dask" and pending:
            # The cluster retries within one session (no reconnect or new LocalCluster per round).
            from .distributed import run_dask

            done = run_dask([items[i] for i in pending], item_fn, verbose_errors, bar, scheduler, retries, jobs=jobs)
            results.update(zip(pending, done))
            pending = []
        while pending:
            attempt += 1
            done = _execute(executor, [items[i] for i in pending], item_fn, jobs, verbose_errors, bar,
                            scheduler, retries)
            for i, res in zip(pending, done):
                res.attempts = results[i].attempts + 1 if i in results else attempt
                results[i] = res
            pending = [i for i in pending if results[i].status == "failed"] if attempt <= retries else []
    finally:
        bar.close()
    for i in todo:
        if results[i].status == "failed":
            remove_temporaries(items[i])
    return BatchResult([results[i] for i in range(len(items))])


def remove_temporaries(item: WorkItem) -> None:
    """Delete temporary files a dead attempt may have left beside ``item``'s outputs.

    Matches only the names :func:`stereocli.io.atomic.atomic_path` gives the temporaries of
    these outputs (``.<stem>.<8 random chars>.tmp<suffix>``, from :func:`tempfile.mkstemp`), never
    files under final names nor temporaries of other outputs in the same folder.
    """
    for out in item.outputs.values():
        path = Path(out)
        if path.parent.is_dir():
            for tmp in path.parent.glob(f".{glob.escape(path.stem)}.{'?' * 8}.tmp{glob.escape(path.suffix)}"):
                tmp.unlink(missing_ok=True)


def _execute(executor, items, item_fn, jobs, verbose_errors, bar, scheduler, retries) -> list[ItemResult]:
    if executor == "inline":
        out = []
        for item in items:
            out.append(_run_one(item_fn, item, verbose_errors))
            bar.update(1)
        return out
    if executor == "process":
        threads = max(1, (os.cpu_count() or 1) // jobs)
        ctx = multiprocessing.get_context("spawn")  # fork is unsafe once numba threads exist
        out: list[ItemResult | None] = [None] * len(items)
        with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_init_worker,
                                    initargs=(threads,)) as pool:
            futures = {pool.submit(_run_one, item_fn, item, verbose_errors): k for k, item in enumerate(items)}
            for fut in cf.as_completed(futures):
                k = futures[fut]
                try:
                    out[k] = fut.result()
                except Exception as exc:  # noqa: BLE001 - a dead worker fails its item only
                    out[k] = ItemResult(items[k].name, "failed", message=f"worker died: {exc}",
                                        inputs=items[k].inputs, outputs=items[k].outputs)
                bar.update(1)
        return out  # type: ignore[return-value]
    if executor == "dask":
        from .distributed import run_dask

        return run_dask(items, item_fn, verbose_errors, bar, scheduler, retries, jobs=jobs)
    raise ValueError(f"unknown executor {executor!r}")
