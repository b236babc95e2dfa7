"""Process-wide settings, applied by the entry points (the command line, benchmarks), never by
importing the library.

:func:`keep_freed_memory` keeps freed large buffers in the process (glibc ``mallopt``), so
matching does not pay for fresh pages on every pair.

Each pair allocates and frees tens of MiB (cost volumes, path sums, maps). glibc serves blocks
above ``M_MMAP_THRESHOLD`` (128 KiB, rising to at most 32 MiB) with fresh ``mmap`` pages and
returns them on ``free``, so the next pair touches new pages again: thousands of page faults
per MiddEval3 Q pair, which OpenCV's SGBM avoids by keeping its buffers inside the matcher object
between calls. Raising both
thresholds keeps the blocks on the heap for reuse. The price is that RSS stays near the peak
between pairs instead of dropping.

Applied once by ``stereocli`` at start-up; set ``STEREOCLI_KEEP_FREED_MEMORY=0`` to leave the
allocator alone. A no-op where the C library has no ``mallopt`` (non-glibc).

Under a ``runtime.memory_gb`` below the default (8 GiB), ``match`` keeps only blocks up to 1/256
of the budget (:func:`keep_freed_memory_within`): freed memory kept for reuse does not count as
in use, yet it is resident, and a heap that keeps blocks up to 1 GiB grows beyond what is in use
when a pair frees strips and whole-image maps of many sizes (a 6000x4000 colour pair in 84
strips under a 1 GiB budget: 0.90 GiB resident, against 0.75 GiB keeping blocks up to 4 MiB).

:func:`prepare_kernels` sets what the compiled kernels need before numba starts: idle kernel
threads sleep instead of spinning (a busy machine), and a faster start (see its docstring).
:func:`limit_blas_threads`, before numpy is imported, keeps BLAS to the calling thread.
"""

from __future__ import annotations

import atexit
import ctypes
import ctypes.util
import gc
import importlib.abc
import os
import sys
from typing import IO, TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from typing import Callable

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap, and the heap keeps this much free memory.
KEEP_BYTES = 1 << 30
#: ``runtime.memory_gb``'s default; under a smaller budget less is kept (:func:`kept_bytes`).
DEFAULT_BUDGET_GB = 8.0
#: ``STEREOCLI_KEEP_FREED_MEMORY``: "0" leaves the allocator alone, a number above 1 sets the
#: bytes kept (how ``match`` hands a budget's setting to its worker processes).
KEEP_ENV = "STEREOCLI_KEEP_FREED_MEMORY"

class _Allocator:
    """What :func:`keep_freed_memory` set in this process (one per process; the entry points
    call it from their main thread)."""

    applied: bool | None = None  # whether the C library took the thresholds; None: not tried yet


def kept_bytes(memory_gb: float | None = None) -> int:
    """The largest block the heap keeps (and the free memory it keeps) under a memory budget of
    ``memory_gb`` GiB: :data:`KEEP_BYTES` at the default budget and above (or with None), 1/256
    of a smaller budget."""
    if memory_gb is None or memory_gb >= DEFAULT_BUDGET_GB:
        return KEEP_BYTES
    return max(1 << 17, int(memory_gb * (1 << 30)) // 256)


def keep_freed_memory() -> bool:
    """Apply the thresholds (once): :data:`KEEP_BYTES`, or the bytes ``STEREOCLI_KEEP_FREED_MEMORY``
    gives; True if the C library accepted them."""
    if _Allocator.applied is not None:
        return _Allocator.applied
    value = os.environ.get(KEEP_ENV, "1")
    if value == "0":
        _Allocator.applied = False
        return False
    return _set_thresholds(int(value) if value.isdigit() and int(value) > 1 else KEEP_BYTES)


def keep_freed_memory_within(memory_gb: float) -> bool:
    """Lower the thresholds to :func:`kept_bytes` of a budget below the default, in this process
    and (through ``STEREOCLI_KEEP_FREED_MEMORY``) in the worker processes it starts; nothing
    when the user set that variable. True if a setting is in force."""
    keep_freed_memory()
    keep = kept_bytes(memory_gb)
    if KEEP_ENV in os.environ or keep >= KEEP_BYTES:
        return bool(_Allocator.applied)
    os.environ[KEEP_ENV] = str(keep)
    return _set_thresholds(keep)


def _set_thresholds(keep: int) -> bool:
    _Allocator.applied = False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    _Allocator.applied = bool(mallopt(_M_MMAP_THRESHOLD, keep)) and bool(mallopt(_M_TRIM_THRESHOLD, keep))
    return _Allocator.applied


# --- the compiled kernels' start-up -----------------------------------------------------------

#: Environment of the kernels' OpenMP thread team, set before numba starts it (a value the user
#: set wins). Between two parallel regions GNU OpenMP's idle threads spin by default
#: (``GOMP_SPINCOUNT`` 300000); with the other core busy (another job, ``make -j``) a spinning
#: thread holds the core the working one needs, and a batch takes longer than with one thread.
#: With these settings idle threads spin 10000 rounds (long enough for the next region of the
#: same pair), then sleep; sleeping at once (``GOMP_SPINCOUNT=0``) would make every region wake a
#: sleeping thread on an idle machine (``benchmarks/shared_machine.py`` measures both). Other
#: OpenMP runtimes read ``OMP_WAIT_POLICY`` only.
KERNEL_THREAD_ENV = {"OMP_WAIT_POLICY": "passive", "GOMP_SPINCOUNT": "10000"}


class _NumbaStart(importlib.abc.MetaPathFinder):
    """Acts when numba starts its compiler runtime, before any kernel is compiled or loaded from
    the cache (numba then imports ``numba.np.arraymath``; an import hook, so that commands that
    never start numba do not import it).

    * Starts the compile watch of :func:`notify_compilation`.
    * Fails the one ``scipy.linalg`` import numba makes there: ``numba.np.arraymath`` imports
      ``scipy.linalg.cython_blas`` while it is being imported itself, only to choose how
      ``np.convolve``/``np.correlate`` are compiled; with SciPy installed every process would pay
      for that import. No stereocli kernel uses those functions or BLAS, and a fresh
      install has no SciPy at all (it is no dependency), so the probe fails, as there. Every
      other ``scipy.linalg`` import proceeds normally.
    * Fails the ``cffi`` import of ``numba.core.typing.cffi_utils`` in the same way: with cffi
      installed (other packages bring it), numba imports it and builds a C parser in every
      process, to type cffi functions passed to kernels; stereocli passes none.
    """

    def find_spec(self, name, path=None, target=None):
        if name == "numba.np.arraymath":
            _watch_compilation()
        elif name == "scipy.linalg" or name.startswith("scipy.linalg."):
            arraymath = sys.modules.get("numba.np.arraymath")
            if arraymath is not None and not hasattr(arraymath, "_HAVE_BLAS"):  # arraymath is starting
                raise ImportError("stereocli: numba's BLAS probe skipped")
        elif name == "cffi":
            support = sys.modules.get("numba.core.typing.cffi_utils")
            if support is not None and not hasattr(support, "SUPPORTED"):  # cffi_utils is starting
                raise ImportError("stereocli: numba's cffi support skipped")
        return None


class _KernelsPrepared:
    """Whether :func:`prepare_kernels` ran in this process (one per process)."""

    done = False

#: Environment of the BLAS libraries (numpy's OpenBLAS, and the one OpenCV bundles), set before
#: numpy is imported (a value the user set wins). stereocli multiplies no large matrices (its
#: largest BLAS call is an image's pixels times three luma weights; plane fits are a few
#: hundred rows), but a multi-threaded OpenBLAS starts a thread per core when numpy is imported,
#: and that thread spins, waiting for work, on the cores the kernels need. With one BLAS thread
#: there is none; the CPU time it frees counts most when the machine is shared
#: (``benchmarks/startup.py``).
BLAS_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1"}


def limit_blas_threads() -> bool:
    """:data:`BLAS_THREAD_ENV`, unless numpy is imported already (then too late); True if applied."""
    if "numpy" in sys.modules:
        return False
    for key, value in BLAS_THREAD_ENV.items():
        os.environ.setdefault(key, value)
    return True


def prepare_kernels() -> None:
    """Settings for the compiled kernels that must precede numba's start (once per process):
    :data:`KERNEL_THREAD_ENV`, and the start hook :class:`_NumbaStart`. Also freezes the
    objects left at exit (``gc.freeze`` as the last exit handler), so the interpreter's final
    cycle collections do not walk numba's many compiler objects. Every output is closed by then."""
    if _KernelsPrepared.done:
        return
    _KernelsPrepared.done = True
    for key, value in KERNEL_THREAD_ENV.items():
        os.environ.setdefault(key, value)
    if "numba.np.arraymath" in sys.modules:
        _watch_compilation()
    else:
        sys.meta_path.insert(0, _NumbaStart())
    atexit.register(gc.freeze)


class _CompileWatch:
    """State of :func:`notify_compilation` (one per process)."""

    notice = None  # called once, when the first kernel starts compiling
    listening = False


def notify_compilation(notice) -> None:
    """Call ``notice()`` when this process next compiles a kernel (a cache miss: the first run
    after installing, a preset or input type not compiled before), so the command line can say
    why it is slow. It is called once, unless it returns True: then again at the next compile
    (it waits for a later moment). ``None`` stops watching. Needs :func:`prepare_kernels` (or
    numba already started)."""
    _CompileWatch.notice = notice
    if notice is not None and "numba.np.arraymath" in sys.modules:
        _watch_compilation()


def _watch_compilation() -> None:
    if _CompileWatch.listening or _CompileWatch.notice is None:
        return
    from numba.core import event

    class FirstCompile(event.Listener):
        def on_start(self, _event) -> None:
            notice, _CompileWatch.notice = _CompileWatch.notice, None  # once per process...
            if notice is not None and notice() is True:
                _CompileWatch.notice = notice  # ...unless it asks to be called again

        def on_end(self, _event) -> None:
            pass

    event.register("numba:compile", FirstCompile())
    _CompileWatch.listening = True


# --- interrupts, orphaned workers and third-party output ----------------------------------------
#
# The entry points (``stereocli`` and the batch runner) turn SIGINT and SIGTERM into
# :class:`~stereocli.errors.Interrupted` in the main thread, so a batch stops where it is, cleans
# up and records what finished; worker processes ignore both and leave stopping to their parent
# (and exit by themselves when it is gone). Output that libraries write straight to file
# descriptor 2 (libpng, OpenCV, child processes, Python warnings) is collected instead of
# interleaving with stereocli's one-line messages.


class _SignalState:
    """What :func:`interrupts_raise` saw (one per process)."""

    installed = 0  # nesting depth of interrupts_raise
    received: list[int] = []  # signals since the outermost interrupts_raise began
    deferred = 0  # nesting depth of deferred_interrupts
    pending: int | None = None  # a signal held back by deferred_interrupts


def _on_signal(signum: int, _frame) -> None:
    from .errors import Interrupted

    state = _SignalState
    state.received.append(signum)
    if len(state.received) >= 3:
        os._exit(128 + state.received[0])  # asked three times: stop without cleaning up
    if len(state.received) > 1:
        return  # the first one is being handled (cleaning up); a second is not a new request
    if state.deferred:
        state.pending = signum
        return
    raise Interrupted(signum)


class interrupts_raise:
    """Context manager: while active, SIGINT and SIGTERM raise
    :class:`~stereocli.errors.Interrupted` in the main thread (the first signal only; a second
    is ignored while cleaning up, a third exits at once). Nests; a no-op outside the main thread.
    """

    def __enter__(self) -> interrupts_raise:
        import signal
        import threading

        self._old: dict = {}
        if threading.current_thread() is not threading.main_thread():
            return self
        if _SignalState.installed == 0:
            _SignalState.received, _SignalState.pending = [], None
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, _on_signal)
        _SignalState.installed += 1
        return self

    def __exit__(self, *exc) -> None:
        import signal

        if not self._old:
            return
        _SignalState.installed -= 1
        for sig, handler in self._old.items():
            signal.signal(sig, handler)


class deferred_interrupts:
    """Context manager: a signal arriving inside the block is raised when the block ends, so a
    short sequence (renaming a pair's outputs into place) is never cut in half."""

    def __enter__(self) -> deferred_interrupts:
        _SignalState.deferred += 1
        return self

    def __exit__(self, *exc) -> None:
        from .errors import Interrupted

        _SignalState.deferred -= 1
        if _SignalState.deferred == 0 and _SignalState.pending is not None and exc[0] is None:
            signum, _SignalState.pending = _SignalState.pending, None
            raise Interrupted(signum)


def interrupt_received() -> int | None:
    """The first SIGINT/SIGTERM received under :func:`interrupts_raise`, if any."""
    return _SignalState.received[0] if _SignalState.received else None


class interrupts_blocked:
    """Context manager: SIGINT and SIGTERM are held (not lost) by this thread while it starts
    worker processes, which inherit the blocked mask until :func:`worker_signals` ignores them."""

    def __enter__(self) -> interrupts_blocked:
        import signal

        self._sigs = {signal.SIGINT, signal.SIGTERM}
        self._old = signal.pthread_sigmask(signal.SIG_BLOCK, self._sigs) if hasattr(signal, "pthread_sigmask") else None
        return self

    def __exit__(self, *exc) -> None:
        import signal

        if self._old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, self._old)


def worker_signals(parent_pid: int, interval: float = 0.5) -> None:
    """In a worker process: ignore SIGINT/SIGTERM (the parent stops its workers itself, so a
    Ctrl-C sent to the whole process group leaves no tracebacks), and exit at once when the
    parent process is gone (killed with SIGKILL): a thread checks every ``interval`` seconds."""
    import signal
    import threading
    import time

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(interval)
        os._exit(1)

    threading.Thread(target=watch, name="stereocli-parent-watch", daemon=True).start()


class _NoiseState:
    file: IO[bytes] | None = None  # the temporary file fd 2 points to while capturing
    saved_fd: int | None = None  # the real stderr
    old_stderr: TextIO | None = None
    old_showwarning: Callable[..., None] | None = None
    sink: list[str] = []  # lines routed here while not capturing (library use, tests)


def _write_noise(text: str) -> None:
    if _NoiseState.file is not None:
        os.write(2, text.encode("utf-8", "backslashreplace"))
    else:
        _NoiseState.sink.extend(text.splitlines())
        del _NoiseState.sink[:-1000]  # the latest lines only


class _NoiseStream:
    """A text stream into the captured output (for loggers of third-party libraries)."""

    def write(self, text: str) -> int:
        _write_noise(text)
        return len(text)

    def flush(self) -> None:
        pass


def noise_stream() -> _NoiseStream:
    """Where third-party log handlers should write: the capture of :func:`capture_native_stderr`
    when it is active, else an in-memory list (never the terminal)."""
    return _NoiseStream()


class capture_native_stderr:
    """Context manager: file descriptor 2 goes to a temporary file (libpng and OpenCV warnings,
    child processes' output, Python warnings land there); ``sys.stderr`` keeps writing to the real
    stderr, so stereocli's own messages stay in order. :meth:`lines` returns what was captured.
    ``enabled=False`` captures nothing (``-vv`` shows everything as it happens)."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._lines: list[str] = []

    def __enter__(self) -> capture_native_stderr:
        import tempfile
        import warnings

        if not self.enabled or _NoiseState.file is not None:
            self.enabled = False
            return self
        sys.stderr.flush()
        _NoiseState.saved_fd = os.dup(2)
        _NoiseState.file = tempfile.TemporaryFile()
        os.dup2(_NoiseState.file.fileno(), 2)
        _NoiseState.old_stderr = sys.stderr
        sys.stderr = open(_NoiseState.saved_fd, "w", buffering=1, encoding="utf-8", errors="backslashreplace",
                          closefd=False)
        _NoiseState.old_showwarning = warnings.showwarning
        warnings.showwarning = lambda message, category, filename, lineno, file=None, line=None: _write_noise(
            warnings.formatwarning(message, category, filename, lineno, line))
        return self

    def __exit__(self, *exc) -> None:
        import warnings

        if not self.enabled:
            return
        f, saved_fd = _NoiseState.file, _NoiseState.saved_fd
        old_stderr, old_showwarning = _NoiseState.old_stderr, _NoiseState.old_showwarning
        if f is None or saved_fd is None or old_stderr is None or old_showwarning is None:
            raise RuntimeError("capture_native_stderr: no capture to end")  # (never: enabled, __enter__ set them)
        with deferred_interrupts():  # a signal now waits until stderr is restored
            sys.stderr.flush()
            warnings.showwarning = old_showwarning
            sys.stderr = old_stderr
            os.dup2(saved_fd, 2)
            os.close(saved_fd)
            _NoiseState.file, _NoiseState.saved_fd = None, None
            f.seek(0)
            data = f.read(1 << 20)
            f.close()
            self._lines = [line for line in data.decode("utf-8", "backslashreplace").splitlines() if line.strip()]

    def lines(self) -> list[str]:
        """The non-empty lines captured (available after the block)."""
        return list(self._lines)
