"""The compiled-kernel runtime: the threads that run the kernels, numba started on first use
(:mod:`.compiling`) and the kernels compiled ahead of time (:mod:`.aot`). One low layer that the
kernel modules of matching, evaluation and features take their decorators and threads from.
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Iterator

from .compiling import (
    LazyKernel,
    chunk_kernel,
    get_numba_threads,
    intrinsic,
    njit,
    numba_started,
    prange,
    prange_only,
    set_numba_threads,
)

if TYPE_CHECKING:
    from concurrent.futures import ThreadPoolExecutor

__all__ = ["chunk_kernel", "for_chunks", "for_rows", "get_threads", "intrinsic", "kernel_threads", "njit", "prange",
           "prange_only", "set_threads", "side_by_side", "threads_for_call"]


# --- kernel threads -------------------------------------------------------------------------
#
# A kernel that splits its work into chunks runs each chunk as a serial ``nogil`` kernel on a
# pool of Python threads (:func:`for_chunks`) rather than as numba's ``prange`` loop: numba's
# parallel compiler takes about three times as long to compile a kernel (the first run after
# installing), and its thread team spins between regions on a shared machine.

# The thread count is the calling thread's own setting: two threads matching at once with
# different counts each run their kernels on theirs (the output never depends on it).
_threads = threading.local()  # .count: this thread's setting (0, or unset: one per core)


class _HelperPool:
    """The kernel threads' executor of this process, made on first use: up to
    :func:`max_threads` − 1 helpers beside a calling thread, one pool for every call whatever its
    thread count or number of chunks (a call asks for as many helpers as it uses; calls from
    several threads share the helpers). Never shut down while the process runs, so a call in one
    thread never loses the pool another started; a forked child makes its own."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.executor: ThreadPoolExecutor | None = None
        self._pid = 0  # the process the executor belongs to

    def get(self) -> ThreadPoolExecutor:
        with self._lock:
            if self.executor is None or self._pid != os.getpid():
                from concurrent.futures import ThreadPoolExecutor

                self.executor = ThreadPoolExecutor(max(1, max_threads() - 1), thread_name_prefix="stereocli-kernel")
                self._pid = os.getpid()
            return self.executor


_HELPERS = _HelperPool()


def set_threads(threads: int) -> None:
    """Threads of the calling thread's kernel calls, :func:`for_chunks` and numba's ``prange``
    kernels (0: one per core, ``NUMBA_NUM_THREADS``); other threads keep theirs. numba's count
    is set in the calling thread now if numba has started, else when it starts."""
    _threads.count = max(0, int(threads))
    set_numba_threads(_threads.count)


def get_threads() -> int:
    """The calling thread's setting of :func:`set_threads` (0: one per core)."""
    return getattr(_threads, "count", 0)


@contextmanager
def threads_for_call(threads: int) -> Iterator[None]:
    """:func:`set_threads` for the calling thread while the ``with`` block runs, then its
    earlier setting back (numba's count too, where numba had started)."""
    before, numba_before = get_threads(), get_numba_threads()
    set_threads(threads)
    try:
        yield
    finally:
        _threads.count = before
        set_numba_threads(before, numba_before)


def kernel_threads() -> int:
    """The number of threads :func:`for_chunks` uses in the calling thread (at most numba's
    ``NUMBA_NUM_THREADS``)."""
    cap = max_threads()
    count = get_threads()
    return min(count, cap) if count > 0 else cap


def max_threads() -> int:
    """numba's ``NUMBA_NUM_THREADS`` (the environment variable, else the cores this process may
    use), read without importing numba."""
    if numba_started():
        return sys.modules["numba"].config.NUMBA_NUM_THREADS
    value = os.environ.get("NUMBA_NUM_THREADS", "")
    if value.strip().isdigit() and int(value) > 0:
        return int(value)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def for_chunks(kernel, n_chunks: int, *args) -> None:
    """``kernel(*args, chunk)`` for every ``chunk`` in ``range(n_chunks)``, on
    :func:`kernel_threads` threads (``kernel`` a :func:`chunk_kernel`; chunks write disjoint
    parts of their outputs, so the result does not depend on the thread count)."""
    _run(kernel, [args + (chunk,) for chunk in range(n_chunks)])


def for_rows(kernel, n_rows: int, *args) -> None:
    """``kernel(*args, y0, y1)`` over row ranges covering ``[0, n_rows)``, on
    :func:`kernel_threads` threads: four ranges per thread, so that threads finishing early
    take more (``kernel`` a :func:`chunk_kernel` whose rows are independent)."""
    threads = kernel_threads()
    n_chunks = max(1, min(n_rows, 4 * threads if threads > 1 else 1))
    bounds = [n_rows * i // n_chunks for i in range(n_chunks + 1)]
    _run(kernel, [args + (bounds[i], bounds[i + 1]) for i in range(n_chunks)])


def _run(kernel, calls: list[tuple]) -> None:
    from .aot import find

    if not calls:
        return
    compiled = find(kernel, calls[0])  # the same kernel compiled ahead of time, if built
    if compiled is not None:
        kernel = compiled
    elif isinstance(kernel, LazyKernel):
        kernel = kernel.dispatcher()  # numba starts in this thread, not in the pool's
    threads = kernel_threads()
    helpers = min(threads, len(calls)) - 1  # the calling thread works too
    if helpers <= 0:
        for call in calls:
            kernel(*call)
        return
    pool = _HELPERS.get()
    # Every thread takes the next call from a shared counter (next() is atomic) until none is
    # left. The caller waits for the calls taken, not for the helpers: a small kernel's calls
    # may all be done before a helper wakes up, which then finds none.
    n = len(calls)
    taken = itertools.count()
    lock = threading.Lock()
    progress: dict[str, Any] = {"done": 0, "error": None}  # calls done (int), the first error raised
    finished = threading.Event()

    def work() -> None:
        while (i := next(taken)) < n:
            try:
                kernel(*calls[i])
            except BaseException as exc:  # noqa: BLE001 - raised again in the calling thread
                progress["error"] = progress["error"] or exc
            with lock:
                progress["done"] += 1
                if progress["done"] == n:
                    finished.set()

    for _ in range(helpers):
        pool.submit(work)
    work()
    finished.wait()
    if progress["error"] is not None:
        raise progress["error"]


def side_by_side(first, second) -> tuple:
    """``(first(), second())``, the second on a kernel thread when there are two or more
    (:func:`kernel_threads`); for work that releases the GIL (OpenCV's), between kernels."""
    threads = kernel_threads()
    if threads < 2:
        return first(), second()
    later = _HELPERS.get().submit(second)
    return first(), later.result()
