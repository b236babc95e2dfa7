"""Build step of ``pip install``: the numba kernels of the ladder's presets (default, fast, accurate,
realtime, quality) compiled ahead of time into the package (``stereocli/runtime/aot.py``), so that
a ``stereocli`` process loads them as extension modules instead of starting numba's JIT, and
the first run of those presets compiles nothing. The project's metadata is in
``pyproject.toml``.

The modules are built for this machine's CPU and Python; only then is the wheel tagged for the
platform. If the build fails (no C compiler, a numba without ``numba.pycc``), the install goes on
without them: the wheel is pure Python, ``_aot/BUILD_FAILED.txt`` records why, and stereocli says
so (with the fix) the first time it has to compile a kernel. ``STEREOCLI_AOT=0`` at install skips
the step.

``STEREOCLI_AOT_CACHE=DIR`` keeps a copy of each build in ``DIR`` and reuses it for an install of
the same kernel sources, CPU, Python and NumPy major version (CI installs the package twice and
compiles once).
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.bdist_wheel import bdist_wheel
from setuptools.command.build_py import build_py
from setuptools.dist import Distribution

#: The package folder of the compiled-kernel runtime, whose ``_aot`` folder holds the build.
RUNTIME = Path("stereocli", "runtime")
FAILED_NOTE = "BUILD_FAILED.txt"


class BuildWithKernels(build_py):
    """``build_py``, then the kernels compiled into the built package (or into the source tree
    for an editable install)."""

    def run(self) -> None:
        super().run()
        editable = getattr(self, "editable_mode", False)
        root = Path.cwd() if editable else Path(self.build_lib)
        if not editable:  # never ship what an earlier build left in build/
            shutil.rmtree(root / RUNTIME / "_aot", ignore_errors=True)
        if os.environ.get("STEREOCLI_AOT", "1") == "0":
            _write_failed_note(root / RUNTIME / "_aot", "STEREOCLI_AOT=0 at install")
            return
        sys.path.insert(0, str(root))  # import stereocli from where it is being built
        try:
            from stereocli.runtime import aot

            self.distribution.kernels_built = _build_or_reuse(aot, root / RUNTIME / "_aot")
        except Exception as exc:  # noqa: BLE001 - the install goes on; the kernels compile on first use
            shutil.rmtree(root / RUNTIME / "_aot", ignore_errors=True)
            reason = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
            _write_failed_note(root / RUNTIME / "_aot", reason)
            print(f"stereocli: WARNING: kernels not compiled ahead of time ({reason}); "
                  "stereocli compiles them on first use", flush=True)
        finally:
            sys.path.remove(str(root))


def _build_or_reuse(aot, folder: Path) -> bool:
    """Build the kernels into ``folder``, or copy a matching build from ``$STEREOCLI_AOT_CACHE``."""
    cache = os.environ.get("STEREOCLI_AOT_CACHE")
    key = aot.build_key() if cache else ""
    cached = Path(cache, key) if cache else None
    if cached is not None and aot.read_manifest(cached) is not None:
        shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(cached, folder)
        print(f"stereocli: kernels copied from the build cache {cached}", flush=True)
        return True
    print(f"stereocli: compiling the presets' kernels ahead of time into {folder}", flush=True)
    seconds = aot.build(folder, log=lambda line: print(line, flush=True))
    print(f"stereocli: kernels compiled in {seconds:.0f} s", flush=True)
    if cached is not None:
        partial = cached.with_name(cached.name + f".{os.getpid()}.tmp")
        shutil.copytree(folder, partial)
        os.replace(partial, cached) if not cached.exists() else shutil.rmtree(partial)
    return True


def _write_failed_note(folder: Path, reason: str) -> None:
    """Leave why the kernels were not built where the runtime looks for them."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / FAILED_NOTE).write_text(reason + "\n")


class WheelTaggedByKernels(bdist_wheel):
    """A wheel tagged for this platform only when it holds the compiled kernels (they are
    extension modules for this CPU and Python); a pure-Python wheel otherwise."""

    def run(self) -> None:
        if not self.skip_build:
            self.run_command("build")  # the kernels are built (or not) before the tag is chosen
        self.root_is_pure = not self.distribution.kernels_built
        super().run()


class KernelsDistribution(Distribution):
    """Holds extension modules exactly when the kernels were built (the install then puts the
    package with the platform's libraries)."""

    kernels_built = False

    def has_ext_modules(self) -> bool:
        return self.kernels_built


setup(cmdclass={"build_py": BuildWithKernels, "bdist_wheel": WheelTaggedByKernels}, distclass=KernelsDistribution)
