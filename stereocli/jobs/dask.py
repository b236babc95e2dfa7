"""The Dask executor: batches of work items on a cluster, and tasks inside a task.

``--scheduler tcp://host:port`` connects to a running Dask scheduler (the workers must be able
to import ``stereocli`` and read/write the same paths: inputs and the output folder are
shared); ``--scheduler local`` starts a :class:`distributed.LocalCluster` of worker processes on
this machine (for testing, or for one machine without a process pool).

Semantics are those of :func:`stereocli.jobs.executors.run_batch` for every executor: only
paths travel (a :class:`~stereocli.jobs.items.WorkItem`, never arrays), item functions write
their outputs atomically into the shared output folder, each item's result is recorded once,
in input order. Two kinds of retry:

* a worker that dies mid-item (killed, out of memory) takes its task with it; the scheduler
  re-runs the task on another worker (Dask's own rescheduling, up to
  ``distributed.scheduler.allowed-failures`` deaths) and the runner removes the dead attempt's
  temporary files before writing (:func:`stereocli.jobs.items.run_one`);
* an item that *fails* (the item function raised, or the scheduler gave up on it) is submitted
  again, up to ``retries`` more times.

Dask is an optional dependency (``pip install "stereocli[dask]"``); this module imports it
lazily and turns its absence into a :class:`~stereocli.errors.ConfigError`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
from typing import Any, Callable, Iterator, Sequence

from ..errors import ConfigError
from .items import ItemResult, WorkItem, prepare_worker, run_one

INSTALL_HINT = 'pip install "stereocli[dask]"'
WORKER_WAIT_SECONDS = 60  # a remote scheduler with no workers would otherwise wait forever
_ADDRESS = re.compile(r"^(?:[a-z][a-z0-9+.-]*://)?[^\s/:]+:\d+$")


def require_distributed():
    """The ``distributed`` module, or a :class:`ConfigError` telling how to install it."""
    try:
        import distributed
    except ImportError:
        raise ConfigError(f"--scheduler needs Dask distributed, which is not installed: {INSTALL_HINT}") from None
    return distributed


def check_scheduler(scheduler: str | None) -> None:
    """Validate a ``--scheduler`` value (``local`` or ``[proto://]host:port``) and that Dask is present."""
    if not scheduler:
        raise ConfigError("the dask executor needs --scheduler tcp://host:port (or --scheduler local)")
    if scheduler != "local" and not _ADDRESS.match(scheduler):
        raise ConfigError(f"--scheduler {scheduler}: expected tcp://host:port (e.g. tcp://127.0.0.1:8786) or 'local'")
    require_distributed()


def local_cluster_shape(jobs: int | None) -> tuple[int, int]:
    """``(n_workers, kernel_threads)`` for ``--scheduler local``: --jobs workers (default 2),
    each running one item at a time whose compiled kernels use its share of the cores (so the
    machine is not oversubscribed, and no two parallel kernels run concurrently in one process,
    which numba's fallback ``workqueue`` threading layer does not allow)."""
    n_workers = jobs if jobs and jobs > 1 else 2
    threads = max(1, (os.cpu_count() or 1) // n_workers)
    return n_workers, threads


@contextlib.contextmanager
def connect(scheduler: str, jobs: int | None = None) -> Iterator[Any]:
    """A :class:`distributed.Client` for ``scheduler``; a started LocalCluster for ``local``.

    Everything started here is closed on exit; a remote cluster is left running.
    """
    check_scheduler(scheduler)
    distributed = require_distributed()
    cluster = None
    try:
        if scheduler == "local":
            n_workers, threads = local_cluster_shape(jobs)
            # Worker processes get the core share in their environment before numba loads
            # (NUMBA_NUM_THREADS is read once at import); outputs do not depend on it.
            env = {"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}
            cluster = distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                               dashboard_address=None, silence_logs=logging.ERROR, env=env)
            client = distributed.Client(cluster, set_as_default=False)
        else:
            try:
                client = distributed.Client(scheduler, timeout="10s", set_as_default=False)
            except (OSError, asyncio.TimeoutError) as exc:
                raise ConfigError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
            try:
                client.wait_for_workers(1, timeout=WORKER_WAIT_SECONDS)
            except (OSError, asyncio.TimeoutError, TimeoutError):
                client.close()
                raise ConfigError(f"--scheduler {scheduler}: no worker joined within {WORKER_WAIT_SECONDS} s "
                                  f"(start some with: dask worker {scheduler})") from None
        try:
            yield client
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()


def _run_on_worker(item_fn: Callable, item: WorkItem, verbose_errors: bool) -> ItemResult:
    """Task body: run one item with the batch's error handling; note which worker ran it."""
    prepare_worker()
    result = run_one(item_fn, item, verbose_errors)
    try:
        from distributed import get_worker

        result.details = {**result.details, "worker": get_worker().address}
    except (ImportError, ValueError):
        pass
    return result


def run_dask(items: Sequence[WorkItem], item_fn: Callable, verbose_errors: bool, bar, scheduler: str | None,
             retries: int, jobs: int | None = None) -> list[ItemResult]:
    """Run ``item_fn`` over ``items`` on a Dask cluster; per-item results in input order.

    Failed items are resubmitted up to ``retries`` times (``attempts`` counts submissions; a
    task re-run by the scheduler after its worker died is one attempt). ``bar`` advances once
    per item, when its final result is known.
    """
    distributed = require_distributed()
    items = list(items)
    results: list[ItemResult | None] = [None] * len(items)
    if not items:
        return []
    with connect(scheduler, jobs) as client:
        attempts = [0] * len(items)
        index: dict[Any, int] = {}

        def submit(k: int):
            attempts[k] += 1
            future = client.submit(_run_on_worker, item_fn, items[k], verbose_errors, pure=False)
            index[future.key] = k
            return future

        pending = distributed.as_completed([submit(k) for k in range(len(items))], loop=client.loop)
        for future in pending:
            k = index.pop(future.key)
            try:
                res = future.result()
            except (Exception, asyncio.CancelledError) as exc:  # noqa: BLE001 - lost task fails its item only
                lost = f"{items[k].name}: lost on the cluster ({type(exc).__name__}: {exc})"
                res = ItemResult.failure(items[k], lost)
            future.release()
            res.attempts = attempts[k]
            if res.status == "failed" and attempts[k] <= retries:
                pending.add(submit(k))
                continue
            results[k] = res
            bar.update(1)
    return results  # type: ignore[return-value]


# --- tasks inside a task ------------------------------------------------------------------


def in_worker() -> bool:
    """True when called from a task running on a Dask worker."""
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


def worker_map(fn: Callable, args_list: Sequence[tuple], *, big_first_arg: bool = True) -> list:
    """``[fn(*args) for args in args_list]`` as tasks spread over the cluster, from inside a task.

    The calling task leaves the worker's thread pool while it waits (so even one-thread workers
    can run the sub-tasks, no deadlock). With ``big_first_arg`` the first argument of each call
    (e.g. an image strip) is scattered to the cluster instead of riding in the task graph.
    Results come back in order. Outside a worker this is a plain loop.
    """
    if not in_worker():
        return [fn(*args) for args in args_list]
    from distributed import worker_client

    with worker_client() as client:
        args_list = [tuple(a) for a in args_list]
        if big_first_arg and args_list:
            data = client.scatter([a[0] for a in args_list], hash=False)
            args_list = [(d, *a[1:]) for d, a in zip(data, args_list)]
        futures = [client.submit(fn, *args, pure=False) for args in args_list]
        return client.gather(futures)
