"""Executors: run an item function over work items in-process, in a process pool or on Dask.

Every executor gives the same outcomes in input order; :func:`run_batch` applies the output
policy (refuse to clobber, ``overwrite``, ``skip_existing``), shows progress, retries failed
items, removes the temporaries of items that finally failed, and stops cleanly on SIGINT or
SIGTERM: queued items are cancelled, running ones stopped (pool workers are killed), their
staged outputs removed, and the finished items returned with the signal number.
"""

from __future__ import annotations

import collections
import contextlib
import multiprocessing
import multiprocessing.connection as mp_connection
import os
import pickle
import signal
import sys
import uuid
from dataclasses import replace
from multiprocessing.reduction import ForkingPickler
from typing import Callable, Iterable

from .items import (
    BatchResult,
    ItemResult,
    WorkItem,
    check_outputs,
    finished_in_run,
    is_done,
    prepare_worker,
    remove_staging_roots,
    remove_temporaries,
    run_one,
)

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

        # done() runs within its round (the executor returns before the next), so it sees this round's values.
        def done(k: int, res: ItemResult) -> None:
            i = pending[k]  # noqa: B023
            res.attempts = attempt  # noqa: B023
            retry = res.status == "failed" and attempt <= retries  # noqa: B023
            if retry:
                failed.append(i)  # noqa: B023
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

    Each worker has a pipe of its own and is handed its next item only when it is idle, so the
    parent knows which item every worker runs: a worker that dies (killed, out of memory) fails
    that item alone (ok when it had committed its outputs), a fresh worker takes its place and
    the queue goes on. On an interrupt the workers are killed (their items' staged outputs are
    removed by the caller) and the interrupt propagates.
    """
    threads = max(1, (os.cpu_count() or 1) // jobs)
    ctx = multiprocessing.get_context("spawn")  # fork is unsafe once numba threads exist
    queue = collections.deque(range(len(items)))
    workers: list[_PoolWorker] = []
    failed_starts = 0  # workers in a row that died before they were ready
    try:
        while queue or any(w.item is not None for w in workers):
            busy = sum(w.item is not None for w in workers)
            while len(workers) < min(jobs, busy + len(queue)):
                workers.append(_PoolWorker(ctx, threads))
            for worker in workers:
                if worker.ready and worker.item is None and queue:
                    k = queue.popleft()
                    try:
                        sent = worker.give(k, (item_fn, items[k], verbose_errors))
                    except _Unsendable as exc:  # this item fails; the worker is fine
                        done(k, ItemResult.failure(items[k], str(exc)))
                        continue
                    if not sent:  # the worker is dead (seen below): the item goes back in the queue
                        queue.appendleft(k)
            mp_connection.wait([w.conn for w in workers] + [w.process.sentinel for w in workers])
            for worker in list(workers):
                for k, res in worker.receive(items):
                    done(k, res)
                if worker.ready:
                    failed_starts = 0
                if worker.process.is_alive():
                    continue
                workers.remove(worker)
                worker.close()
                if worker.item is not None:
                    done(worker.item, _dead_worker_result(items[worker.item], worker.process.exitcode))
                elif not worker.ready:
                    failed_starts += 1
                    if failed_starts >= MAX_FAILED_STARTS:
                        reason = f"worker processes fail to start ({_exit_reason(worker.process.exitcode)})"
                        while queue:
                            k = queue.popleft()
                            done(k, ItemResult.failure(items[k], reason))
    except BaseException:
        _kill_workers(workers)
        raise
    finally:
        for worker in workers:
            worker.stop()
        _kill_workers(workers, grace=5)
        for worker in workers:
            worker.conn.close()


#: Workers in a row that may die before they are ready (a broken installation) before the
#: queued items fail.
MAX_FAILED_STARTS = 3
_READY, _RESULT, _ERROR = "ready", "result", "error"


class _Unsendable(Exception):
    """An item that cannot be pickled for a worker process."""


class _PoolWorker:
    """One spawned worker process of :func:`_process_pool`, its pipe, and the index of the item
    it runs (None when idle)."""

    def __init__(self, ctx, threads: int) -> None:
        from ..process import interrupts_blocked

        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_pool_worker_main, args=(child, threads, os.getpid()),
                                   name="stereocli-worker")
        # Workers start with SIGINT/SIGTERM blocked and then ignore them: a Ctrl-C sent to the
        # whole process group is handled here alone.
        with interrupts_blocked():
            self.process.start()
        child.close()  # the worker's end: the parent sees EOF when the worker dies
        self.ready = False
        self.item: int | None = None

    def give(self, k: int, task: tuple) -> bool:
        """Send item ``k`` (the ``task`` tuple); False when the worker is gone. Raises
        :class:`_Unsendable` when the task cannot be pickled."""
        try:
            payload = ForkingPickler.dumps(task)
        except Exception as exc:  # noqa: BLE001 - e.g. an item function that is not importable
            raise _Unsendable(f"cannot send the item to a worker process ({type(exc).__name__}: {exc})") from None
        try:
            self.conn.send_bytes(payload)
        except OSError:
            return False
        self.item = k
        return True

    def receive(self, items: list[WorkItem]) -> list[tuple[int, ItemResult]]:
        """The ``(k, result)`` outcomes the worker has sent (marking it ready or idle)."""
        finished = []
        while self.has_message():
            try:
                kind, *payload = self.conn.recv()
            except (EOFError, OSError):
                break  # died mid-message: the caller sees its process end
            if kind == _READY:
                self.ready = True
            elif self.item is not None:
                k = self.item
                res = payload[0] if kind == _RESULT else ItemResult.failure(items[k], payload[0])
                finished.append((k, res))
                self.item = None
        return finished

    def has_message(self) -> bool:
        """True when the pipe holds a message (or its end: the worker died)."""
        try:
            return not self.conn.closed and self.conn.poll()
        except (EOFError, OSError):
            return False

    def stop(self) -> None:
        """Ask an idle worker to exit."""
        with contextlib.suppress(OSError, ValueError):
            self.conn.send_bytes(ForkingPickler.dumps(None))

    def close(self) -> None:
        self.process.join(timeout=5)
        self.conn.close()


def _pool_worker_main(conn, threads: int, parent_pid: int) -> None:
    """A pool worker's loop: one item at a time from ``conn``, its outcome sent back."""
    init_worker(threads, parent_pid)
    conn.send((_READY,))
    while True:
        try:
            data = conn.recv_bytes()
        except (EOFError, OSError):
            return
        try:
            task = pickle.loads(data)
        except Exception as exc:  # noqa: BLE001 - e.g. the item function's module is missing here
            conn.send((_ERROR, f"the worker process cannot load the item ({type(exc).__name__}: {exc})"))
            continue
        if task is None:
            return
        item_fn, item, verbose_errors = task
        result = run_one(item_fn, item, verbose_errors)
        try:
            conn.send((_RESULT, result))
        except Exception as exc:  # noqa: BLE001 - details that cannot be pickled
            conn.send((_ERROR, f"its outcome cannot be sent back ({type(exc).__name__}: {exc})"))


def _exit_reason(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def _dead_worker_result(item: WorkItem, exitcode: int | None) -> ItemResult:
    """The outcome of an item whose worker process died while running it: failed, or ok when
    the worker had committed its outputs before it died (its details are lost)."""
    if finished_in_run(item):
        return ItemResult(item.name, "ok", message="finished; its details were lost (its worker process died "
                          "after committing)", inputs=item.inputs, outputs=item.outputs)
    return ItemResult.failure(item, f"worker process died while running this item ({_exit_reason(exitcode)})")


def _kill_workers(workers: list[_PoolWorker], grace: float = 0) -> None:
    """SIGKILL the worker processes still alive after ``grace`` seconds and wait for them (their
    items are abandoned)."""
    for worker in workers:
        worker.process.join(timeout=grace)
    for worker in workers:
        if worker.process.is_alive():
            worker.process.kill()
    for worker in workers:
        worker.process.join(timeout=5)
