"""Build step of ``pip install``: the numba kernels of the ladder's presets (default, fast, accurate,
realtime, quality) compiled ahead of time into the package (``stereocli/match/kernels/aot.py``), so that
a ``stereocli`` process loads them as extension modules instead of starting numba's JIT, and
the first run of those presets compiles nothing. The project's metadata is in
``pyproject.toml``.

The modules are built for this machine's CPU and Python (the wheel is tagged for the platform).
If the build fails (no C compiler, a numba without ``numba.pycc``), the install goes on without
them and stereocli compiles the kernels on first use, as it does for the other presets.
``STEREOCLI_AOT=0`` at install skips the step.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py
from setuptools.dist import Distribution

KERNELS = Path("stereocli", "match", "kernels")


class BuildWithKernels(build_py):
    """``build_py``, then the kernels compiled into the built package (or into the source tree
    for an editable install)."""

    def run(self) -> None:
        super().run()
        if os.environ.get("STEREOCLI_AOT", "1") == "0":
            return
        editable = getattr(self, "editable_mode", False)
        root = Path.cwd() if editable else Path(self.build_lib)
        sys.path.insert(0, str(root))  # import stereocli from where it is being built
        try:
            from stereocli.match.kernels import aot

            print(f"stereocli: compiling the presets' kernels ahead of time into {root / KERNELS / '_aot'} "
                  "(about 45 s on two cores)", flush=True)
            seconds = aot.build(root / KERNELS / "_aot", log=lambda line: print(line, flush=True))
            print(f"stereocli: kernels compiled in {seconds:.0f} s", flush=True)
        except Exception as exc:  # noqa: BLE001 - the install goes on; the kernels compile on first use
            import shutil

            shutil.rmtree(root / KERNELS / "_aot", ignore_errors=True)
            print(f"stereocli: WARNING: kernels not compiled ahead of time ({type(exc).__name__}: {exc}); "
                  "stereocli compiles them on first use", flush=True)
        finally:
            sys.path.remove(str(root))


class PlatformDistribution(Distribution):
    """The wheel holds extension modules for this platform (not a pure-Python wheel)."""

    def has_ext_modules(self) -> bool:
        return True


setup(cmdclass={"build_py": BuildWithKernels}, distclass=PlatformDistribution)
