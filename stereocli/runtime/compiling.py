"""numba for the kernels, started on first use: the decorators the kernel modules use (through
:mod:`stereocli.runtime`), and the options of a chunk kernel.

The kernel modules take ``njit``, ``prange`` and ``intrinsic`` from here rather than from numba:
they are numba's, made lazy (:class:`LazyKernel`), so that importing the kernels does not import
numba, which every process would otherwise pay for. numba starts when a kernel first has to run from its JIT;
kernels compiled ahead of time (:mod:`.aot`) run without it.
"""

from __future__ import annotations

import functools
import sys
import threading
import warnings
from dataclasses import dataclass, field
from typing import Any

# The expected note of numba's parallel pipeline on a :func:`chunk_kernel` (it has no prange).
warnings.filterwarnings("ignore", message="(?s).*no transformation for parallel execution was possible")

_numba_threads = threading.local()  # .count: the calling thread's count for numba's prange kernels (0: its default)


def prange_only() -> dict:
    """``parallel=`` option of a kernel whose only parallel loops are its ``prange`` loops.

    With ``parallel=True`` numba also turns every array allocation or expression in the kernel
    (``np.full``, ``np.zeros``, copies, sums) into a parallel loop of its own: each one is
    compiled separately (in the first run) and launched on the threads for a few elements' work.
    (A fresh dict per call: numba consumes it.)
    """
    return {"comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False, "numpy": False,
            "stencil": False, "fusion": False, "prange": True}


# --- numba, started on first use -------------------------------------------------------------------

@dataclass
class _NumbaStart:
    """Whether numba has started in this process (:func:`start_numba`), and what waits for it."""

    #: Set last, once every lazy object is replaced: other threads use the dispatchers only then.
    started: bool = False
    #: Every :class:`LazyKernel` and :class:`LazyIntrinsic` made before numba started.
    lazy_objects: list = field(default_factory=list)
    #: Held while numba starts: threads (a Dask worker's) may need the JIT at once.
    lock: threading.Lock = field(default_factory=threading.Lock)


_NUMBA = _NumbaStart()


class LazyKernel:
    """``numba.njit(**options)(func)``, made when first needed: called (from the JIT), or asked
    for an attribute of numba's dispatcher. ``py_func`` (what :mod:`.aot` looks kernels up by)
    needs no numba. When numba starts, every module of stereocli that holds a lazy kernel gets
    the dispatcher in its place (:func:`start_numba`), so that numba, compiling a kernel, finds
    dispatchers for the helpers it calls."""

    def __init__(self, func, options: dict) -> None:
        functools.update_wrapper(self, func)
        self.py_func = func
        self._options = options
        self._made = None

    def _make(self, numba) -> None:
        options = dict(self._options)
        if options.pop("noalias", False) and _allow_noalias():
            options["noalias"] = True
        self._made = numba.njit(**options)(self.py_func)

    def dispatcher(self):
        """numba's dispatcher (starting numba if needed)."""
        if not _NUMBA.started:
            start_numba()
        if self._made is None:  # made while numba was starting (a module imported meanwhile)
            import numba

            self._make(numba)
        return self._made

    def __call__(self, *args):
        return self.dispatcher()(*args)

    def __getattr__(self, name: str):  # only for what this object lacks: numba's attributes
        if name.startswith("__") or name in ("_made", "_options", "py_func"):
            raise AttributeError(name)
        return getattr(self.dispatcher(), name)


class LazyIntrinsic:
    """``numba.extending.intrinsic(func)``, made when numba starts (see :class:`LazyKernel`)."""

    def __init__(self, func) -> None:
        # update_wrapper copies __name__, __doc__... onto any object; typeshed asks for a callable.
        functools.update_wrapper(self, func)  # type: ignore[arg-type]
        self.py_func = func
        self._made: Any = None  # numba's intrinsic, once made

    def _make(self, numba) -> None:
        from numba.extending import intrinsic as numba_intrinsic

        self._made = numba_intrinsic(self.py_func)


def njit(*args, **options):
    """``numba.njit``, lazy: ``@njit`` or ``@njit(cache=True, ...)`` (keyword options only)."""
    def decorate(func):
        if _NUMBA.started:
            import numba

            return numba.njit(**options)(func)
        kernel = LazyKernel(func, options)
        _NUMBA.lazy_objects.append(kernel)
        return kernel

    return decorate(args[0]) if args else decorate


def intrinsic(func):
    """``numba.extending.intrinsic``, lazy."""
    if _NUMBA.started:
        from numba.extending import intrinsic as numba_intrinsic

        return numba_intrinsic(func)
    made = LazyIntrinsic(func)
    _NUMBA.lazy_objects.append(made)
    return made


def prange(*args):
    """``numba.prange`` once numba starts (each kernel module's ``prange`` is replaced); a plain
    ``range`` when a kernel's Python function runs."""
    return range(*args)


def start_numba() -> None:
    """Import numba, make every lazy kernel and intrinsic, and put them (and ``numba.prange``) in
    place of the lazy objects in stereocli's modules, before anything compiles."""
    with _NUMBA.lock:
        if _NUMBA.started:
            return
        import numba

        for made in _NUMBA.lazy_objects:
            made._make(numba)
        for name, module in list(sys.modules.items()):
            if not name.startswith("stereocli.") or module is None:
                continue
            namespace = vars(module)
            for key, value in list(namespace.items()):
                if isinstance(value, (LazyKernel, LazyIntrinsic)):
                    namespace[key] = value._made
                elif value is prange and module is not sys.modules[__name__]:
                    namespace[key] = numba.prange
        _NUMBA.lazy_objects.clear()
        globals()["prange"] = numba.prange  # for kernel modules imported from now on
        _NUMBA.started = True  # last: other threads use the dispatchers only once all are in place
    set_numba_threads(getattr(_numba_threads, "count", 0))


def set_numba_threads(threads: int, numba_threads: int | None = None) -> None:
    """numba's thread count for the calling thread's ``prange`` kernels (0: its default,
    ``NUMBA_NUM_THREADS``), set now if numba has started, else when it starts in this thread
    (numba keeps the count per thread). ``numba_threads``: numba's own count to set instead
    (what :func:`get_numba_threads` gave), to restore it."""
    _numba_threads.count = threads
    if _NUMBA.started:
        import numba

        # numba.config sets its options at import time (from the environment): its stubs miss them.
        default = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]
        count = numba_threads or threads or default
        numba.set_num_threads(min(count, default))


def get_numba_threads() -> int | None:
    """numba's thread count in the calling thread, None before numba has started."""
    if not _NUMBA.started:
        return None
    import numba

    return numba.get_num_threads()


def numba_started() -> bool:
    return _NUMBA.started


def chunk_kernel(func):
    """``@njit`` for the serial, ``nogil`` kernel of one chunk (:func:`for_chunks`), cached.

    Compiled as numba compiles the body of a ``prange`` loop, to run as fast:

    * by numba's parallel pipeline although it holds no ``prange``: its simplification passes
      drop the reference counting of the arrays that inlined helpers (``inline="always"``)
      pass around (the atomic increments and decrements they would otherwise do in the inner
      loops dominate a chunk such as the geodesic vote's; numba's note that nothing could be
      parallelised is expected and filtered);
    * with ``error_model="numpy"``: float division by zero gives inf or NaN rather than
      raising, so the division needs no test and its loop can be vectorised;
    * with ``noalias``: the kernel's array arguments never overlap (each output is allocated
      by its wrapper), so LLVM may vectorise loops that read one and write another (the LR
      check's, for one). numba accepts the flag from ``prange`` lowering only; the
      decorator option is added to its CPU target options here, and left out if that fails.
    """
    return njit(cache=True, nogil=True, error_model="numpy", parallel=prange_only(), noalias=True)(func)


def _allow_noalias() -> bool:
    try:
        from numba.core import cpu, options

        if not hasattr(cpu.CPUTargetOptions, "noalias"):
            cpu.CPUTargetOptions.noalias = options.TargetOptions.Mapping("noalias")
        return True
    except (ImportError, AttributeError):  # another numba: the kernels run, only slower
        return False
