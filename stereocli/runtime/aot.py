"""The chunk kernels of the usual presets compiled ahead of time (``numba.pycc``), so that a process
that matches with them loads machine code like any extension module instead of starting numba's
JIT runtime and loading each kernel from its cache (a cost every ``stereocli`` process would pay),
and a first run after installing compiles nothing on that path.

``pip install .`` builds them into the installed package (``setup.py``; a failure there only
leaves them out), ``python -m stereocli.runtime.aot`` into the source tree (for a checkout).
:func:`find` hands :func:`stereocli.runtime._run` the compiled function for a kernel and the
types of its arguments, or None: then the kernel runs from numba's JIT as before. The results
are the same bit for bit (``tests/test_aot.py``).

A kernel is named by its module within the ``stereocli`` package and its function
(:func:`kernel_name`: ``matching.kernels.census._census_rows``). A built folder holds one
extension module per kernel and ``manifest.json``; it is used only if the manifest matches this
process: the same kernel sources (a hash of the runtime's files and of the packages holding the
listed kernels, so an edited kernel never runs stale), the same CPU (the modules are compiled
for the host CPU's instruction set: AVX-512 code would crash an older CPU) and the same NumPy
major version. ``STEREOCLI_AOT=0`` turns them off.

The kernels and argument types compiled are those of the ``default``, ``fast``, ``accurate``,
``realtime`` and ``quality`` presets, listed in :data:`SIGNATURES_FILE` (``tests/test_aot.py``
checks the list against runs of those presets).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, cast

import numpy as np

RUNTIME_DIR = Path(__file__).resolve().parent
#: The ``stereocli`` package's folder: kernels are named by their module within it.
PACKAGE_DIR = RUNTIME_DIR.parent
#: Where ``pip install .`` and ``python -m stereocli.runtime.aot`` put the modules.
BUILD_DIR = RUNTIME_DIR / "_aot"
#: One line per compiled kernel: ``module.kernel<TAB>type, type, ...`` (:func:`kernel_name`;
#: numba's type names).
SIGNATURES_FILE = RUNTIME_DIR / "aot_signatures.txt"
MANIFEST = "manifest.json"
#: Written by ``setup.py`` into :data:`BUILD_DIR` when the build at install failed: the reason.
FAILED_NOTE = "BUILD_FAILED.txt"
#: Name prefix of the built extension modules (``_aot`` is a plain folder: they are loaded by
#: path, never imported by name).
MODULE_PREFIX = "stereocli_aot_"


def read_signatures(path: Path = SIGNATURES_FILE) -> dict[str, list[tuple[str, ...]]]:
    """``{"module.kernel": [argument type names, ...]}`` of :data:`SIGNATURES_FILE`."""
    table: dict[str, list[tuple[str, ...]]] = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, types = line.split("\t")
            table.setdefault(name, []).append(tuple(_split_types(types)))
    return table


def _split_types(text: str) -> list[str]:
    """``"array(float32, 2d, C), int64"`` → ``["array(float32, 2d, C)", "int64"]``."""
    parts, depth, start = [], 0, 0
    for i, char in enumerate(text):
        depth += {"(": 1, ")": -1}.get(char, 0)
        if char == "," and depth == 0:
            parts.append(text[start:i].strip())
            start = i + 1
    parts.append(text[start:].strip())
    return parts


def type_name(value) -> str | None:
    """numba's name for the type of a kernel argument (``numba.typeof(value)``) without importing
    numba; None for a value no compiled kernel takes (read-only or unaligned arrays, others)."""
    kind = type(value)
    if kind is np.ndarray:
        flags = value.flags
        if not (flags.writeable and flags.aligned):
            return None
        layout = "C" if flags.c_contiguous else "F" if flags.f_contiguous else "A"
        return f"array({_DTYPE_NAMES.get(value.dtype) or _dtype_name(value.dtype)}, {value.ndim}d, {layout})"
    return _SCALAR_NAMES.get(kind) or (value.dtype.name if isinstance(value, np.generic) else None)


#: numba's names of Python scalars and NumPy booleans (other NumPy scalars: their dtype's name).
_SCALAR_NAMES = {int: "int64", float: "float64", bool: "bool", np.bool_: "bool"}
_DTYPE_NAMES: dict = {}


def _dtype_name(dtype: np.dtype) -> str:
    name = _DTYPE_NAMES[dtype] = "bool" if dtype == np.bool_ else dtype.name
    return name


def kernel_name(function) -> str | None:
    """``"module.function"`` of a kernel's Python function, its module named within the
    ``stereocli`` package (``matching.kernels.census._census_rows``); None outside it."""
    module = getattr(function, "__module__", None) or ""
    if not module.startswith("stereocli."):
        return None
    return f"{module.removeprefix('stereocli.')}.{function.__name__}"


def kernel_sources_hash() -> str:
    """Hash of the Python files of the runtime (how the kernels are compiled) and of every package
    holding a listed kernel (each kernel and the helpers it inlines). Without the list (a damaged
    install), the runtime's alone: no build matches it."""
    try:
        listed = {line.split("\t", 1)[0] for line in SIGNATURES_FILE.read_text().splitlines()
                  if line.strip() and not line.startswith("#")}
    except OSError:
        listed = set()
    folders = {RUNTIME_DIR} | {PACKAGE_DIR.joinpath(*kernel.split(".")[:-2]) for kernel in listed}
    digest = hashlib.sha256()
    for path in sorted(path for folder in folders for path in folder.glob("*.py")):
        digest.update(path.relative_to(PACKAGE_DIR).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def cpu_fingerprint() -> str:
    """What identifies the instruction set the modules were compiled for: the CPU model and
    feature flags from ``/proc/cpuinfo``, or LLVM's host CPU name and features elsewhere."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            text = cpuinfo.read(1 << 16)  # the first processor's entry is enough
        lines = text.split("\n\n")[0].splitlines()
        wanted = [line for line in lines if line.split(":")[0].strip() in ("vendor_id", "model name", "flags")]
        if wanted:
            return hashlib.sha256("\n".join(wanted).encode()).hexdigest()[:16]
    except OSError:
        pass
    import llvmlite.binding as llvm

    llvm.initialize_native_target()
    description = llvm.get_host_cpu_name() + llvm.get_host_cpu_features().flatten()
    return hashlib.sha256(description.encode()).hexdigest()[:16]


# --- using a built folder -----------------------------------------------------------------------

class _BuiltKernel:
    """One kernel of a usable build: its extension module, loaded on the kernel's first call."""

    def __init__(self, name: str, path: Path, signatures: list[list[str]]) -> None:
        self.name, self.path, self.signatures = name, path, signatures
        self.functions: dict | None = None  # {argument type names: compiled function}

    def load(self) -> dict:
        """The compiled functions ({} if the module does not load: the kernel then runs from
        numba's JIT, and :func:`describe` says so)."""
        if self.functions is None:
            try:
                extension = _import_extension(self.path)
                self.functions = {tuple(types): getattr(extension, export_name(self.name, i))
                                  for i, types in enumerate(self.signatures)}
            except Exception as exc:  # noqa: BLE001 - a damaged module: this kernel from the JIT
                self.functions = {}
                _BUILD.not_loaded.append(f"{self.name} ({exc})")
        return self.functions


@dataclass
class _UsedBuild:
    """The built folder this process uses, read on its first kernel lookup (once per process)."""

    #: ``{"module.function": _BuiltKernel}`` of the usable build ({} if none); None before the
    #: first lookup.
    table: dict | None = None
    #: Why the build is not used ("" while it is, or before the first lookup).
    why_not: str = ""
    #: Kernels of the build whose module did not load (they run from numba's JIT).
    not_loaded: list = field(default_factory=list)
    #: Held while the table is read and while a module loads: threads of a Dask worker may match
    #: pairs at once.
    lock: threading.Lock = field(default_factory=threading.Lock)


_BUILD = _UsedBuild()


def find(kernel, args: tuple):
    """The compiled function for ``kernel`` (a chunk kernel's dispatcher) called with ``args``,
    or None (no usable built folder, or a kernel or signature it does not hold).

    A kernel's extension module is loaded on its first call, so a process loads only the
    modules of the kernels its stages run (and imports no other kernel module)."""
    used = _BUILD
    table = used.table
    if table is None:
        table = _loaded_table()
    if not table:
        return None
    function = getattr(kernel, "py_func", None)
    if function is None:
        return None
    built = table.get(kernel_name(function))
    if built is None:
        return None
    functions = built.functions
    if functions is None:
        with used.lock:
            functions = built.load()
    return functions.get(tuple(type_name(a) for a in args))


def _loaded_table() -> dict:
    """The table of the built folder, read on first use (once per process)."""
    used = _BUILD
    with used.lock:
        if used.table is None:
            used.table, used.why_not = _usable_build()
        return used.table


def _usable_build() -> tuple[dict, str]:
    """``({"module.function": _BuiltKernel}, "")`` of the built folder if it is usable, else
    ``({}, why not)``. Usable: its manifest matches this process and every module file is
    there (a module that is there but does not load is found on the kernel's first call)."""
    if os.environ.get("STEREOCLI_AOT", "1") == "0":
        return {}, "STEREOCLI_AOT=0"
    folder = Path(os.environ.get("STEREOCLI_AOT_DIR") or BUILD_DIR)
    manifest = read_manifest(folder)
    if manifest is None:
        failed = install_failure(folder)
        return {}, f"not built at install: {failed}" if failed else f"no build in {folder}"
    expected = expected_manifest(manifest.get("kernels", {}))
    for key, what in (("sources", "other kernel sources"), ("cpu", "another CPU"), ("numpy", "another NumPy"),
                      ("python", "another Python")):
        if manifest.get(key) != expected[key]:
            return {}, f"the build in {folder} is for {what}"
    table: dict = {}
    for kernel, entry in manifest["kernels"].items():
        path = _extension_path(folder, entry["module"])
        if path is None:
            return {}, f"the build in {folder} is incomplete ({entry['module']} is missing)"
        table[kernel] = _BuiltKernel(kernel, path, entry["signatures"])
    return table, ""


def describe() -> str:
    """One line on the kernels compiled at install, for records and ``--show-versions``."""
    table = _loaded_table()
    not_loaded = _BUILD.not_loaded
    if table:
        broken = f"; {len(not_loaded)} did not load: {', '.join(not_loaded)}" if not_loaded else ""
        return f"{len(table)} compiled at install; others from numba's JIT{broken}"
    return f"none compiled at install ({_BUILD.why_not}): numba's JIT"


def install_failure(folder: Path = BUILD_DIR) -> str:
    """Why ``pip install`` did not build the kernels into ``folder`` (``setup.py`` leaves the
    reason in :data:`FAILED_NOTE`), or "" when it did not say (a checkout, or a build)."""
    try:
        return (Path(folder) / FAILED_NOTE).read_text().strip()[:300]
    except OSError:
        return ""


def missing_build_advice() -> str:
    """One line for a process whose kernels were not compiled ahead of time: why, and the fix;
    "" when the build is in use (or was turned off with ``STEREOCLI_AOT=0``)."""
    if _loaded_table() or os.environ.get("STEREOCLI_AOT", "1") == "0":
        return ""
    checkout = (PACKAGE_DIR.parent / "pyproject.toml").is_file()
    fix = ("python -m stereocli.runtime.aot" if checkout else
           "pip install --force-reinstall --no-deps <stereocli source> with a C compiler "
           "and a numba that has numba.pycc")
    return (f"the kernels were not compiled ahead of time ({_BUILD.why_not}); numba compiles them now, once "
            f"(later runs load them from its cache); to build them: {fix}")


def build_key() -> str:
    """What a build depends on (kernel sources, CPU, Python, NumPy major, numba), as a folder
    name for a build cache."""
    import numba

    parts = expected_manifest({})
    text = "|".join(str(parts[key]) for key in ("sources", "cpu", "numpy", "python")) + "|" + numba.__version__
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def read_manifest(folder: Path) -> dict | None:
    try:
        return json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def expected_manifest(kernels: dict) -> dict:
    """The manifest a folder built by this process would have, for ``kernels``."""
    return {"sources": kernel_sources_hash(), "cpu": cpu_fingerprint(),
            "numpy": np.__version__.split(".")[0], "python": "%d.%d" % sys.version_info[:2],
            "kernels": kernels}


def _extension_path(folder: Path, name: str) -> Path | None:
    """The file of extension module ``name`` built in ``folder``, or None."""
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = folder / (name + suffix)
        if path.is_file():
            return path
    return None


def _import_extension(path: Path):
    """The extension module in ``path``; raises if it does not load."""
    spec = importlib.util.spec_from_file_location(path.name.split(".")[0], path)
    if spec is None or spec.loader is None:  # (never: the path ends in an extension suffix)
        raise ImportError(f"{path}: not an extension module")
    extension = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(extension)
    return extension


# --- building -----------------------------------------------------------------------------------

def build(folder: Path = BUILD_DIR, jobs: int = 0, log=print, only: list[str] | None = None) -> float:
    """Compile every kernel of :data:`SIGNATURES_FILE` (or those named in ``only``) into
    ``folder``, one extension module per kernel, in ``jobs`` processes (0: one per core), then
    write the manifest; returns the seconds. Raises on any failure, leaving no manifest (so the
    folder is not used).

    One module per kernel because pycc's modules of several kernels were not always correct
    (``_fill_background_rows`` beside ``_hamming_rows`` wrote nothing, with the same machine
    code); numba's C runtime, which each module links, is compiled once per process."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    started = time.perf_counter()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MANIFEST).unlink(missing_ok=True)
    kernels = read_signatures()
    if only is not None:
        kernels = {kernel: kernels[kernel] for kernel in only}
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(kernels)))
    # Largest first (argument count: a rough measure), so that the last to finish are small.
    order = sorted(kernels, key=lambda k: (-len(kernels[k][0]), k))
    context = multiprocessing.get_context("spawn")  # a clean numba in each worker
    with tempfile.TemporaryDirectory(prefix="stereocli-aot-") as scratch, \
            ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        work = [(str(folder), MODULE_PREFIX + export_name(k, 0)[:-2], {k: kernels[k]}, scratch) for k in order]
        for (_, name, _, _), seconds in zip(work, pool.map(_build_module, work)):
            log(f"  {name}: {seconds:.1f} s")
    manifest = expected_manifest({kernel: {"module": name, "signatures": [list(s) for s in group[kernel]]}
                                  for _, name, group, _ in work for kernel in group})
    (folder / (MANIFEST + ".tmp")).write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    os.replace(folder / (MANIFEST + ".tmp"), folder / MANIFEST)
    return time.perf_counter() - started


@dataclass
class _BuildProcess:
    """What a build process (:func:`_build_module`'s worker) keeps between its modules."""

    #: numba's C runtime objects, compiled for the first module, linked into every module.
    runtime_objects: list | None = None


_BUILD_PROCESS = _BuildProcess()


def _build_module(job: tuple[str, str, dict[str, list[tuple[str, ...]]], str]) -> float:
    """Compile kernels into one extension module (in a worker process; ``scratch``: a folder for
    numba's C runtime objects), exporting :func:`export_name` for each signature."""
    folder, name, kernels, scratch = job
    started = time.perf_counter()
    import numba.pycc.compiler as pycc_compiler
    from numba.core import types
    from numba.core.compiler import Flags
    from numba.core.cpu import ParallelOptions
    from numba.pycc import CC

    from .compiling import _allow_noalias, prange_only, start_numba

    start_numba()  # the kernels' helpers become numba's dispatchers
    noalias = _allow_noalias()

    class ChunkKernelFlags(Flags):
        """What :func:`chunk_kernel` asks of numba's JIT, and an entry point that releases the
        GIL (pycc's hold it: the pool's threads would take turns)."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True
            self.error_model = "numpy"
            self.noalias = noalias
            self.auto_parallel = ParallelOptions(prange_only())

    # pycc reads its Flags class from its module: replaced, not subclassed at the call site.
    pycc_compiler.Flags = ChunkKernelFlags  # type: ignore[misc]

    class SharedRuntimeCC(CC):
        """Compiles ``modulemixin.c`` (the module's own entry point) for each module, and the
        rest of numba's C runtime (the same for every module) once per process."""

        def _compile_mixins(self, build_dir):
            sources = [os.path.normpath(source) for source in self._get_mixin_sources()]
            own, shared = sources[:1], sources[1:]
            options = dict(include_dirs=self._toolchain.get_python_include_dirs(), macros=self._get_mixin_defines(),
                           extra_cflags=self._get_extra_cflags())
            if _BUILD_PROCESS.runtime_objects is None:
                runtime_dir = tempfile.mkdtemp(prefix="runtime-", dir=scratch)
                _BUILD_PROCESS.runtime_objects = self._toolchain.compile_objects(shared, runtime_dir, **options)
            return self._toolchain.compile_objects(own, build_dir, **options) + _BUILD_PROCESS.runtime_objects

    cc = SharedRuntimeCC(name)
    cc.output_dir = folder
    cc.target_cpu = "host"
    cc.verbose = False
    for kernel, signatures in kernels.items():
        for i, names in enumerate(signatures):
            argument_types = [numba_type(n) for n in names]
            cc.export(export_name(kernel, i), types.void(*argument_types))(_python_function(kernel))
    cc.compile()
    return time.perf_counter() - started


def numba_type(name: str):
    """The numba type named ``name`` (:func:`type_name`'s names: ``int64``, ``bool``,
    ``array(float32, 2d, C)``, ...)."""
    from numba.core import types

    scalar = {"bool": types.boolean}
    if name.startswith("array("):
        dtype, ndim, layout = (part.strip() for part in name[len("array("):-1].split(","))
        # type_name writes C, F or A
        return types.Array(numba_type(dtype), int(ndim.rstrip("d")), cast(Literal["C", "F", "A"], layout))
    return scalar.get(name) or getattr(types, name)


def export_name(kernel: str, i: int) -> str:
    """Name of ``"module.kernel"``'s ``i``-th signature in its extension module (a C name)."""
    module, function = kernel.rsplit(".", 1)
    return f"{module.replace('.', '_')}__{function.lstrip('_')}_{i}"


def _python_function(kernel: str):
    module, function = kernel.rsplit(".", 1)
    value = getattr(importlib.import_module(f"stereocli.{module}"), function)
    return getattr(value, "py_func", value)


def main(argv: list[str] | None = None) -> int:
    """``python -m stereocli.runtime.aot [FOLDER]``: build into FOLDER (default: the package)."""
    argv = sys.argv[1:] if argv is None else argv
    folder = Path(argv[0]) if argv else BUILD_DIR
    print(f"compiling the usual presets' kernels ahead of time into {folder} ...")
    seconds = build(folder)
    print(f"done in {seconds:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
