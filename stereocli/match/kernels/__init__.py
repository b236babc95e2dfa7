"""numba kernels used by the matching stages (each with a pure-numpy reference in the tests)."""


import itertools
import os
import threading
import warnings

# The expected note of numba's parallel pipeline on a :func:`chunk_kernel` (it has no prange).
warnings.filterwarnings("ignore", message="(?s).*no transformation for parallel execution was possible")


def prange_only() -> dict:
    """``parallel=`` option of a kernel whose only parallel loops are its ``prange`` loops.

    With ``parallel=True`` numba also turns every array allocation or expression in the kernel
    (``np.full``, ``np.zeros``, copies, sums) into a parallel loop of its own: each one is
    compiled separately (about a quarter of a second of the first run each) and launched on the
    threads for microseconds of work. (A fresh dict per call: numba consumes it.)
    """
    return {"comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False, "numpy": False,
            "stencil": False, "fusion": False, "prange": True}


# --- kernel threads -------------------------------------------------------------------------
#
# A kernel that splits its work into chunks runs each chunk as a serial ``nogil`` kernel on a
# pool of Python threads (:func:`for_chunks`) rather than as numba's ``prange`` loop: numba's
# parallel compiler takes about three times as long to compile a kernel (the first run after
# installing), and its thread team spins between regions on a shared machine.

def chunk_kernel(func):
    """``@njit`` for the serial, ``nogil`` kernel of one chunk (:func:`for_chunks`), cached.

    Compiled as numba compiles the body of a ``prange`` loop, to run as fast:

    * by numba's parallel pipeline although it holds no ``prange``: its simplification passes
      drop the reference counting of the arrays that inlined helpers (``inline="always"``)
      pass around (without them the geodesic vote's chunk ran 10x slower; numba's note that
      nothing could be parallelised is expected and filtered);
    * with ``error_model="numpy"``: float division by zero gives inf or NaN rather than
      raising, so the division needs no test and its loop can be vectorised;
    * with ``noalias``: the kernel's array arguments never overlap (each output is allocated
      by its wrapper), so LLVM may vectorise loops that read one and write another (the LR
      check ran 6x slower without). numba accepts the flag from ``prange`` lowering only; the
      decorator option is added to its CPU target options here, and left out if that fails.
    """
    from numba import njit

    flags = dict(cache=True, nogil=True, error_model="numpy", parallel=prange_only())
    if _allow_noalias():
        flags["noalias"] = True
    return njit(**flags)(func)


def _allow_noalias() -> bool:
    try:
        from numba.core import cpu, options

        if not hasattr(cpu.CPUTargetOptions, "noalias"):
            cpu.CPUTargetOptions.noalias = options.TargetOptions.Mapping("noalias")
        return True
    except (ImportError, AttributeError):  # another numba: the kernels run, only slower
        return False


_threads = [0]  # 0: one per core
_pool: list = [None, 0, 0]  # (executor, its size, the process it belongs to: a forked child makes its own)


def set_threads(threads: int) -> None:
    """Threads of :func:`for_chunks` (0: one per core, ``NUMBA_NUM_THREADS``)."""
    _threads[0] = max(0, int(threads))


def kernel_threads() -> int:
    """The number of threads :func:`for_chunks` uses."""
    import numba

    cap = numba.config.NUMBA_NUM_THREADS
    return min(_threads[0], cap) if _threads[0] > 0 else cap


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
    threads = kernel_threads()
    helpers = min(threads, len(calls)) - 1  # the calling thread works too
    if helpers <= 0:
        for call in calls:
            kernel(*call)
        return
    # One pool of threads − 1 for every call, whatever its number of chunks: a call with fewer
    # chunks than threads (SGM's two stripes) just leaves some idle.
    if _pool[0] is None or _pool[1] != threads - 1 or _pool[2] != os.getpid():
        from concurrent.futures import ThreadPoolExecutor

        if _pool[0] is not None and _pool[2] == os.getpid():
            _pool[0].shutdown()
        _pool[:] = ThreadPoolExecutor(threads - 1, thread_name_prefix="stereocli-kernel"), threads - 1, os.getpid()
    # Every thread takes the next call from a shared counter (next() is atomic) until none is
    # left. The caller waits for the calls taken, not for the helpers: a small kernel's calls
    # may all be done before a helper wakes up (tens of microseconds), which then finds none.
    n = len(calls)
    taken = itertools.count()
    lock = threading.Lock()
    progress = {"done": 0, "error": None}
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
        _pool[0].submit(work)
    work()
    finished.wait()
    if progress["error"] is not None:
        raise progress["error"]
