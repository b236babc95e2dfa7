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
  again, up to ``retries`` more times, avoiding the workers that failed it before where the
  cluster has others.

Each task first checks that its worker runs the client's stereocli (its version, kernel sources
and other sources): a worker that does not is refused and its items run on the others. An item
a worker reports done counts only once the client sees its completion marker and outputs.

Failures of the cluster itself are bounded: an address is probed (is a Dask scheduler
answering?) within :data:`CONNECT_SECONDS`; a scheduler lost mid-batch (the client cannot reach
it for :data:`LOST_SECONDS`) fails the items that had not finished, keeping those that had. Each
task checks that the worker sees the item's paths (workers need a shared filesystem);
``attempts`` counts every run, including Dask's own re-runs after a worker died.
Dask's log lines go to the captured third-party output (:func:`stereocli.process.noise_stream`).

Dask is an optional dependency (``pip install "stereocli[dask]"``); this module imports it
lazily and turns its absence into a :class:`~stereocli.errors.ConfigError`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import re
import signal
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence, cast

from ..errors import EXIT_USAGE, ConfigError, excerpt
from .items import ItemResult, WorkItem, finished_in_run, prepare_worker, run_one

INSTALL_HINT = 'pip install "stereocli[dask]"'
WORKER_WAIT_SECONDS = 60  # a remote scheduler with no workers would otherwise wait forever
CONNECT_SECONDS = 10  # probing an address: a Dask scheduler answers at once
LOST_SECONDS = 10  # a scheduler unreachable this long is lost: the unfinished items fail
SHARED_FS_HINT = "Dask workers need a shared filesystem with the same paths"
#: How long outputs a worker committed may take to appear to the client before the item fails
#: (an NFS client may cache a folder's absence for its attribute-cache time, 30 s by default).
VISIBLE_SECONDS = 30
#: How often the client looks for items restricted to workers that have all left (seconds).
REROUTE_SECONDS = 1.0
#: First element of what a task returns when its worker runs another stereocli (it ran nothing).
REFUSED = "stereocli-refused"
_ADDRESS = re.compile(r"^(?:([a-z][a-z0-9+.-]*)://)?[^\s/:]+:\d+$")


def require_distributed():
    """The ``distributed`` module, or a :class:`ConfigError` telling how to install it."""
    try:
        import distributed
    except ImportError:
        raise ConfigError(f"--scheduler needs Dask distributed, which is not installed: {INSTALL_HINT}") from None
    return distributed


def check_scheduler(scheduler: str | None) -> None:
    """Validate a ``--scheduler`` value (``local`` or ``[proto://]host:port`` with a protocol Dask
    knows) and that Dask is present."""
    if not scheduler:
        raise ConfigError("the dask executor needs --scheduler tcp://host:port (or --scheduler local)")
    m = _ADDRESS.match(scheduler)
    if scheduler != "local" and not m:
        raise ConfigError(f"--scheduler {excerpt(scheduler)}: expected tcp://host:port "
                          "(e.g. tcp://127.0.0.1:8786) or 'local'")
    require_distributed()
    if m and m.group(1):
        from distributed.comm.registry import backends

        if m.group(1) not in backends:
            raise ConfigError(f"--scheduler {excerpt(scheduler)}: Dask has no {m.group(1)!r} protocol; "
                              f"use one of {', '.join(sorted(backends))} (e.g. tcp://127.0.0.1:8786)")


def probe_scheduler(scheduler: str, timeout: float | None = None) -> None:
    """Raise :class:`ConfigError` unless a Dask scheduler answers at ``scheduler`` within
    ``timeout`` seconds (default :data:`CONNECT_SECONDS`; a closed port, an HTTP server or a
    silent peer all fail in time)."""
    from distributed.comm import connect as comm_connect
    from distributed.security import Security

    timeout = CONNECT_SECONDS if timeout is None else timeout

    async def identify() -> dict:
        args = Security().get_connection_args("client")
        comm = await comm_connect(scheduler, timeout=timeout, **args)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    async def bounded() -> dict:
        return await asyncio.wait_for(identify(), timeout)

    try:
        reply = asyncio.run(bounded())
    except (asyncio.TimeoutError, TimeoutError):
        raise ConfigError(f"--scheduler {excerpt(scheduler)}: no Dask scheduler answered "
                          f"within {timeout:g} s") from None
    except Exception as exc:  # noqa: BLE001 - refused, reset, garbled handshake: not a scheduler
        raise ConfigError(f"--scheduler {excerpt(scheduler)}: not a reachable Dask scheduler "
                          f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise ConfigError(f"--scheduler {excerpt(scheduler)}: the peer is not a Dask scheduler")


def quiet_dask_logs() -> None:
    """Send the ``distributed`` loggers' console output to the captured third-party output."""
    from ..process import noise_stream

    for name in ["distributed", *[n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]]:
        for handler in logging.getLogger(name).handlers:
            if isinstance(handler, logging.StreamHandler) and not isinstance(handler, logging.FileHandler):
                handler.setStream(noise_stream())


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

    Everything started here is closed on exit (within seconds, even when the scheduler is
    gone); a remote cluster is left running.
    """
    check_scheduler(scheduler)
    distributed = require_distributed()
    quiet_dask_logs()
    cluster, local_pids = None, {}
    try:
        if scheduler == "local":
            n_workers, threads = local_cluster_shape(jobs)
            # Worker processes get the core share in their environment before numba loads
            # (NUMBA_NUM_THREADS is read once at import); outputs do not depend on it.
            env = {"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}
            cluster = distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                               dashboard_address=None, silence_logs=logging.ERROR, env=env)
            client = distributed.Client(cluster, set_as_default=False)
            local_pids = client.run(os.getpid)
        else:
            probe_scheduler(scheduler)
            try:
                client = distributed.Client(scheduler, timeout=f"{CONNECT_SECONDS}s", set_as_default=False)
            except (OSError, asyncio.TimeoutError) as exc:
                raise ConfigError(f"--scheduler {excerpt(scheduler)}: cannot connect ({exc})") from None
            try:
                client.wait_for_workers(1, timeout=WORKER_WAIT_SECONDS)
            except (OSError, asyncio.TimeoutError, TimeoutError):
                _close(client)
                raise ConfigError(f"--scheduler {excerpt(scheduler)}: no worker joined within {WORKER_WAIT_SECONDS} s "
                                  f"(start some with: dask worker {scheduler})") from None
        try:
            yield client
        except BaseException:
            # Interrupted or failed: stop the local workers now (a graceful close waits for
            # their running items); their staged outputs are removed by the caller.
            for pid in local_pids.values():
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
            raise
        finally:
            _close(client)
    finally:
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=5)


def _close(client) -> None:
    with contextlib.suppress(Exception):
        client.close(timeout=2)


def _missing_path(item: WorkItem) -> str | None:
    """The first of ``item``'s inputs, or its output folder's parent, this process cannot see."""
    for path in item.inputs.values():
        if not os.path.exists(path):
            return path
    if item.folder and not Path(item.folder).parent.is_dir():
        return str(Path(item.folder).parent)
    return None


def _identity_probe() -> Callable[[], dict[str, str]]:
    """A function returning what identifies the stereocli of the process that calls it: its
    version, the digest of its kernel sources and that of all its Python sources. It is made
    here, inside a function, so that Dask sends its code along (cloudpickle pickles nested
    functions by value): a worker running another stereocli runs this code, not that version's
    own. The digests are computed once per probe (a worker keeps the probe it unpickled)."""
    known: dict[str, str] = {}

    def identity() -> dict[str, str]:
        if known:
            return dict(known)
        import hashlib
        from pathlib import Path

        try:
            import stereocli

            version = str(stereocli.__version__)
            root = Path(stereocli.__file__).parent
            digest = hashlib.sha256()
            for path in sorted(root.rglob("*.py")):
                digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
            sources = digest.hexdigest()[:16]
        except Exception:  # noqa: BLE001 - a worker without a usable stereocli
            version = sources = "unknown"
        try:
            from stereocli.runtime.aot import kernel_sources_hash

            kernels = kernel_sources_hash()
        except Exception:  # noqa: BLE001
            kernels = "unknown"
        known.update(stereocli=version, kernels=kernels, sources=sources)
        return dict(known)

    return identity


def _checked(fn: Callable, expected: dict[str, str]) -> Callable:
    """``fn`` as a task that first checks its worker runs the stereocli ``expected`` (version and
    sources, see :func:`_identity_probe`); a worker that does not returns ``(REFUSED, address,
    its identity)`` without running anything. Sent by value, like the probe."""
    identity = _identity_probe()

    def checked(*args):
        mine = identity()
        if mine != expected:
            from distributed import get_worker

            return (REFUSED, get_worker().address, mine)
        return fn(*args)

    checked.__name__ = fn.__name__  # Dask names the task's key after it (the qualname keeps it sent by value)
    return checked


def _refusal(value) -> tuple[str, dict] | None:
    """``(worker address, its identity)`` when ``value`` is a :func:`_checked` task's refusal."""
    if isinstance(value, tuple) and len(value) == 3 and value[0] == REFUSED:
        return value[1], value[2]
    return None


def refusal_message(address: str, theirs: dict[str, str], ours: dict[str, str]) -> str:
    """Why worker ``address`` was refused: both stereocli versions and source digests."""

    def describe(identity: dict[str, str]) -> str:
        return (f"stereocli {identity.get('stereocli')} (kernels {identity.get('kernels')}, "
                f"sources {identity.get('sources')})")

    return (f"worker {address} runs {describe(theirs)}, this client {describe(ours)}; refused: install the same "
            "stereocli on every worker")


def _unseen_output(item: WorkItem) -> str | None:
    """The first of ``item``'s committed paths (completion marker, outputs) this process does not
    see as this run wrote it; None when it sees them all."""
    if not item.outputs or finished_in_run(item):
        return None
    for path in ([str(item.marker)] if item.marker is not None else []) + list(item.outputs.values()):
        if not os.path.exists(path):
            return path
    return str(item.marker) if item.marker is not None else None  # another run's marker


def _run_on_worker(item_fn: Callable, item: WorkItem, verbose_errors: bool) -> ItemResult:
    """Task body: check the paths are visible here, run one item with the batch's error
    handling; note which worker ran it."""
    from distributed import get_worker

    worker = get_worker()
    prepare_worker()
    missing = _missing_path(item)
    if missing is not None:
        result = ItemResult.failure(item, f"{missing}: not found on worker {worker.address} ({SHARED_FS_HINT})")
    else:
        result = run_one(item_fn, item, verbose_errors)
    result.details = {**result.details, "worker": worker.address}
    return result


def run_dask(items: Sequence[WorkItem], item_fn: Callable, verbose_errors: bool, scheduler: str | None,
             retries: int, jobs: int | None = None,
             record: Callable[[int, ItemResult, bool], None] | None = None) -> list[ItemResult]:
    """Run ``item_fn`` over ``items`` on a Dask cluster; per-item results in input order.

    Failed items are resubmitted up to ``retries`` times. ``attempts`` counts the runs each item
    started (a task re-run by the scheduler after its worker died counts again). ``record(k,
    result, final)`` is called as each outcome is known. A lost scheduler fails the unfinished
    items; an interrupt cancels the outstanding tasks and propagates.
    """
    require_distributed()
    if not items:
        return []
    with connect(cast(str, scheduler), jobs) as client:  # connect refuses a missing scheduler itself
        batch = _DaskBatch(client, list(items), item_fn, verbose_errors, retries,
                           record or (lambda k, res, final: None))
        try:
            batch.run()
        except BaseException:
            with contextlib.suppress(Exception):
                client.cancel(list(batch.pending.futures), force=True)
            raise
    return cast("list[ItemResult]", batch.results)  # every item has its result once run() returns


class _DaskBatch:
    """The items of one :func:`run_dask` call on a connected client: submissions, outcomes.

    Each task checks that its worker runs this client's stereocli (:func:`_checked`); a worker
    that does not is refused: its item goes to the other workers without counting an attempt,
    and the item fails only when no other worker is left. A retry avoids the workers that
    failed that item before while the cluster has others (if those all leave, the item is
    submitted again to the workers there are then: :meth:`reroute`). An item a worker reports
    done is ok only once this client sees its committed outputs (:data:`VISIBLE_SECONDS` at
    most); else it fails as a failure on that worker.
    """

    def __init__(self, client, items: list[WorkItem], item_fn: Callable, verbose_errors: bool, retries: int,
                 record: Callable[[int, ItemResult, bool], None]) -> None:
        import distributed

        self.client, self.items, self.item_fn, self.verbose_errors = client, items, item_fn, verbose_errors
        self.retries, self.record = retries, record
        self.identity = _identity_probe()()
        self.task = _checked(_run_on_worker, self.identity)
        self.results: list[ItemResult | None] = [None] * len(items)
        self.submitted = [0] * len(items)  # submissions that ran (a refused one does not count)
        self.tried: list[list[str]] = [[] for _ in items]  # the worker of each run
        self.avoid: list[set[str]] = [set() for _ in items]  # workers that failed or refused each item
        self.refused: dict[str, dict] = {}  # worker address -> the stereocli it runs
        self.notes: list[list[str]] = [[] for _ in items]  # warnings for the item's record
        self.unverified: dict[int, tuple[ItemResult, float]] = {}  # reported done, outputs not seen yet
        self.index: dict[Any, int] = {}  # key of each outstanding task -> item
        self.restricted: dict[Any, tuple[Any, set[str]]] = {}  # key -> (future, the workers it may run on)
        self.pending = distributed.as_completed([self.submit(k) for k in range(len(items))], loop=client.loop)

    def submit(self, k: int, counted: bool = True):
        """Submit item ``k``, restricted to the workers that neither failed nor refused it when
        the cluster has such workers (``counted``: a new attempt, not a re-routed one)."""
        self.submitted[k] += counted
        avoid = self.avoid[k] | set(self.refused)
        others = [w for w in self._workers() if w not in avoid] if avoid else []
        # A strict restriction: with a loose one an idle avoided worker would steal the task.
        future = self.client.submit(self.task, self.item_fn, self.items[k], self.verbose_errors, pure=False,
                                    workers=others or None)
        self.index[future.key] = k
        if others:
            self.restricted[future.key] = (future, set(others))
        return future

    def reroute(self) -> None:
        """Submit again, to the workers there are now, the items restricted to workers that have
        all left (died or were removed): such a task would wait forever."""
        current = set(self._workers())
        for key, (future, allowed) in list(self.restricted.items()):
            if current and not allowed & current:
                del self.restricted[key]
                k = self.index.pop(key)
                self.client.cancel([future])
                self.pending.add(self.submit(k, counted=False))

    def _workers(self) -> list[str]:
        """The addresses of the cluster's workers now ([] when the scheduler does not answer)."""
        try:
            return list(self.client.nthreads())
        except Exception:  # noqa: BLE001 - a scheduler being lost: the run loop handles it
            return []

    def run(self) -> None:
        """Take finished tasks until every item has its final result or the scheduler is lost
        (then the unfinished items fail)."""
        lost_since = None
        next_reroute = time.monotonic() + REROUTE_SECONDS
        while self.index or self.unverified:
            self.check_visible()
            done = self.pending.next_batch(block=False)
            if done:
                if not self.take(done):
                    break
                continue
            if self.client.status == "running":
                lost_since = None
                if self.restricted and time.monotonic() > next_reroute:
                    self.reroute()
                    next_reroute = time.monotonic() + REROUTE_SECONDS
            elif self.index:
                lost_since = lost_since or time.monotonic()
                if self.client.status in ("closing", "closed") or time.monotonic() - lost_since > LOST_SECONDS:
                    break
            time.sleep(0.05)
        self.check_visible(final=True)
        for k in sorted(set(self.index.values())):
            res = ItemResult.failure(self.items[k], "the Dask scheduler was lost before this item finished; "
                                                    "run again with --skip-existing to resume")
            res.attempts = self.submitted[k]
            self.results[k] = res
            self.record(k, res, True)

    def take(self, futures) -> bool:
        """Record the outcomes of finished ``futures``, resubmitting failures that have retries
        left; False when they show that the scheduler is gone."""
        for future in futures:
            k = self.index.get(future.key)
            if k is None:  # cancelled by reroute(), submitted again
                future.release()
                continue
            try:
                res = future.result(timeout=LOST_SECONDS)
            except (Exception, asyncio.CancelledError) as exc:  # noqa: BLE001 - lost task fails its item only
                if self.client.status != "running" or "connection-lost" in str(exc):
                    return False
                detail = str(exc).splitlines()[0] if str(exc) else "no detail"
                res = ItemResult.failure(self.items[k], f"lost on the cluster ({type(exc).__name__}: {detail})")
            del self.index[future.key]
            self.restricted.pop(future.key, None)
            future.release()
            refusal = _refusal(res)
            if refusal is not None:
                self.refuse(k, *refusal)
                continue
            # Submissions, plus the runs Dask started again after a worker died (run_one counts
            # the staging folders those left).
            res.attempts = self.submitted[k] + max(0, res.attempts - 1)
            if res.details.get("worker"):
                self.tried[k].append(res.details["worker"])
            if res.status == "ok" and _unseen_output(self.items[k]) is not None:
                self.unverified[k] = (res, time.monotonic() + VISIBLE_SECONDS)
                continue
            self.conclude(k, res)
        return True

    def refuse(self, k: int, address: str, theirs: dict) -> None:
        """Item ``k`` was refused by worker ``address`` (another stereocli): send it to the other
        workers, or fail it when none is left (or that worker refused it before)."""
        self.submitted[k] -= 1  # that submission ran nothing
        message = refusal_message(address, theirs, self.identity)
        first = address not in self.refused
        self.refused[address] = theirs
        again = address not in self.avoid[k]
        self.avoid[k].add(address)
        if again and self.client.status == "running" and set(self._workers()) - self.avoid[k] - set(self.refused):
            if first:
                self.notes[k].append(f"{message}; its items run on the other workers")
            self.pending.add(self.submit(k))
            return
        res = ItemResult.failure(self.items[k], message, EXIT_USAGE)
        res.details = {"worker": address}
        res.attempts = self.submitted[k]
        self.conclude(k, res, can_retry=False)

    def check_visible(self, final: bool = False) -> None:
        """Conclude the items reported done whose outputs this client now sees, and those whose
        outputs are still not here after :data:`VISIBLE_SECONDS` (or ``final``ly): failed."""
        for k, (res, deadline) in list(self.unverified.items()):
            unseen = _unseen_output(self.items[k])
            if unseen is not None and not final and time.monotonic() < deadline:
                continue
            del self.unverified[k]
            if unseen is not None:
                worker = res.details.get("worker", "?")
                failed = ItemResult.failure(self.items[k], f"{unseen}: not visible to this client although worker "
                                                           f"{worker} committed the item ({SHARED_FS_HINT}; is the "
                                                           "output folder on the worker's own disk?)")
                failed.details, failed.attempts, failed.seconds = {"worker": worker}, res.attempts, res.seconds
                res = failed
            self.conclude(k, res, can_retry=not final)

    def conclude(self, k: int, res: ItemResult, can_retry: bool = True) -> None:
        """Record item ``k``'s outcome ``res`` of its latest run, and submit it again when it
        failed with retries left (avoiding the worker that ran it)."""
        if len(self.tried[k]) > 1:
            res.details = {**res.details, "workers": list(self.tried[k])}
        if self.notes[k]:
            res.details = {**res.details, "warnings": [*res.details.get("warnings", []), *self.notes[k]]}
        if res.status == "failed" and res.details.get("worker"):
            self.avoid[k].add(res.details["worker"])
        retry = (can_retry and res.status == "failed" and self.submitted[k] <= self.retries
                 and self.client.status == "running")
        self.results[k] = res
        self.record(k, res, not retry)
        if retry:
            self.pending.add(self.submit(k))


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
    Sub-tasks lost with a dead worker (with their scattered data) run again, up to Dask's
    ``distributed.scheduler.allowed-failures`` times; a worker running another stereocli is
    refused (:func:`_checked`) and the sub-tasks go to the others. Results come back in order;
    a sub-task's own error is raised. Outside a worker this is a plain loop.
    """
    if not in_worker():
        return [fn(*args) for args in args_list]
    import dask
    import distributed
    from distributed import worker_client

    args_list = [tuple(a) for a in args_list]
    identity = _identity_probe()()
    task = _checked(fn, identity)
    results: list = [None] * len(args_list)
    todo = list(range(len(args_list)))
    refused: dict[str, dict] = {}
    lost_rounds = 0
    with worker_client() as client:
        while todo:
            # This worker is never refused (it runs this code), so the restriction never empties.
            where = {"workers": [w for w in client.nthreads() if w not in refused]} if refused else {}
            calls = [args_list[k] for k in todo]
            if big_first_arg:
                data = client.scatter([a[0] for a in calls], hash=False, **where)
                calls = [(d, *a[1:]) for d, a in zip(data, calls)]
            futures = [client.submit(task, *a, pure=False, **where) for a in calls]
            with contextlib.suppress(*_CANCELLED):  # raised once all are done, when some were lost: see below
                distributed.wait(futures)
            again, lost = [], 0
            for k, future in zip(todo, futures):
                if future.status != "finished" and _lost(future):
                    again.append(k)
                    lost += 1
                    continue
                value = future.result()  # raises the sub-task's own error
                refusal = _refusal(value)
                if refusal is None:
                    results[k] = value
                elif refusal[0] in refused:  # refused twice: the restriction did not hold
                    raise RuntimeError(refusal_message(*refusal, identity))
                else:
                    refused[refusal[0]] = refusal[1]
                    again.append(k)
            lost_rounds += bool(lost)
            if lost and lost_rounds > dask.config.get("distributed.scheduler.allowed-failures", 3):
                raise RuntimeError(f"{lost} of {len(args_list)} sub-tasks were lost with their workers "
                                   f"{lost_rounds} times")
            todo = again
    return results


#: What a sub-task lost with its worker raises (Dask's FutureCancelledError is the first).
_CANCELLED = (concurrent.futures.CancelledError, asyncio.CancelledError)


def _lost(future) -> bool:
    """True when a sub-task's ``future`` ended without running to its end because a worker died
    (cancelled, or its scattered input lost with that worker), not by its own error."""
    if future.status in ("cancelled", "lost"):
        return True
    try:
        return isinstance(future.exception(), _CANCELLED)
    except _CANCELLED:
        return True
