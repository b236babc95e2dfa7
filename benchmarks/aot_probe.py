#!/usr/bin/env python3
"""What ahead-of-time kernels would give: the default path's heaviest chunk kernels compiled by
``numba.pycc`` into an extension module, against the same kernels from numba's JIT cache.

The kernels run as they do in stereocli (``for_chunks`` on the kernel thread pool), compiled with
the options :func:`stereocli.match.kernels.chunk_kernel` gives numba's JIT (parallel pipeline
without ``prange``, ``error_model="numpy"``, ``noalias``), plus ``release_gil`` (pycc's exports
otherwise hold the GIL, and the pool's threads would take turns) and the host CPU as the target
(pycc's default, a generic x86-64, has no AVX: the SGM then runs 15–40 % slower). Printed:

* the compile time of the extension module;
* per kernel and pair: the best time of each (``--repeat`` turns, alternating) and whether the
  outputs are bit-identical;
* a whole process that imports numpy and OpenCV and calls one kernel: from the extension
  module, and from numba's cache (what a ``stereocli`` process pays today before any work).

It writes only to a temporary folder; stereocli itself does not use the module.

    python benchmarks/aot_probe.py               # two MiddEval3-Q pairs (synthetic without data)
    python benchmarks/aot_probe.py --repeat 9
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stereocli.process import keep_freed_memory, prepare_kernels  # noqa: E402

keep_freed_memory()
prepare_kernels()

DATA = REPO.parent / "shared" / "data" / "middlebury2014" / "trainingQ"
SCENES = ("Adirondack", "Teddy")
#: (module attribute, kernel module, chunk kernel) compiled ahead of time.
KERNELS = (("sgm_window", "sgm_window", "_sgm_window_two_pass_chunk"),
           ("sgm_full", "sgm", "_sgm_two_pass_chunk"),
           ("geodesic_vote", "segment", "_vote_chunk"))


def kernel_module(name: str):
    import importlib

    return importlib.import_module(f"stereocli.match.kernels.{name}")


def pairs() -> list[tuple[str, np.ndarray, np.ndarray, int]]:
    from stereocli.io.images import read_image
    from stereocli.io.middlebury import read_calib_txt
    from stereocli.match.warmup import synthetic_pair

    if DATA.is_dir():
        return [(s, read_image(DATA / s / "im0.png"), read_image(DATA / s / "im1.png"),
                 read_calib_txt(DATA / s / "calib.txt").ndisp) for s in SCENES]
    left, right = synthetic_pair(640, 480, 64)
    return [("synthetic 640x480", left, right, 64)]


def build(folder: Path, name: str) -> float:
    """Compile the KERNELS at the signatures a default run gives them into ``folder/name``;
    returns the seconds."""
    from numba.core import types
    from numba.core.compiler import Flags
    from numba.core.cpu import ParallelOptions
    import numba.pycc.compiler as pycc_compiler
    from numba.pycc import CC

    from stereocli.match.kernels import prange_only

    class ChunkKernelFlags(Flags):
        """What chunk_kernel asks of numba's JIT, and a wrapper that releases the GIL."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True
            self.error_model = "numpy"
            self.noalias = True
            self.auto_parallel = ParallelOptions(prange_only())

    pycc_compiler.Flags = ChunkKernelFlags  # pycc compiles its exports with these flags
    cc = CC(name)
    cc.output_dir = str(folder)
    cc.target_cpu = "host"
    for attribute, module, kernel in KERNELS:
        dispatcher = getattr(kernel_module(module), kernel)
        for i, signature in enumerate(dispatcher.signatures):
            cc.export(f"{attribute}_{i}", types.void(*signature))(dispatcher.py_func)
    t0 = time.perf_counter()
    cc.compile()
    return time.perf_counter() - t0


def timed_kernels(items, config, module, repeat: int) -> None:
    """Each kernel from the JIT and from ``module`` in turns; best seconds and identity."""
    from stereocli.match.pipeline import match_pair

    jit = {attribute: getattr(kernel_module(m), k) for attribute, m, k in KERNELS}

    def aot_kernel(attribute):
        """The export whose signature the arguments have (the JIT's signatures, in order)."""
        from numba import typeof

        exports = [getattr(module, f"{attribute}_{i}") for i in range(len(jit[attribute].signatures))]
        signatures = [tuple(s) for s in jit[attribute].signatures]

        def call(*args):
            return exports[signatures.index(tuple(typeof(a) for a in args))](*args)
        return call

    aot = {attribute: aot_kernel(attribute) for attribute in jit}
    print("\n| pair | kernel | JIT ms | AOT ms | identical |\n|---|---|---|---|---|")
    for scene, left, right, ndisp in items:
        seconds = {}
        maps = {}
        for _ in range(repeat):
            for which, table in (("jit", jit), ("aot", aot)):
                clocks = {attribute: [] for attribute in jit}  # list.append is atomic across threads
                for attribute, m, k in KERNELS:
                    def clocked(*args, _kernel=table[attribute], _clock=clocks[attribute]):
                        t0 = time.perf_counter()
                        _kernel(*args)
                        _clock.append(time.perf_counter() - t0)
                    setattr(kernel_module(m), k, clocked)
                try:
                    result = match_pair(left, right, config, ndisp=ndisp)
                finally:
                    for attribute, m, k in KERNELS:
                        setattr(kernel_module(m), k, jit[attribute])
                maps[which] = result.disparity
                for attribute, values in clocks.items():
                    key = (attribute, which)
                    seconds[key] = min(seconds.get(key, np.inf), sum(values))
                time.sleep(0.05)
        same = np.array_equal(maps["jit"], maps["aot"])
        for attribute in jit:
            # Per chunk call, summed over the pair's calls (the pool runs chunks concurrently,
            # so the sum of chunk times exceeds the wall time; the ratio is what matters).
            print(f"| {scene} | {attribute} | {seconds[(attribute, 'jit')] * 1e3:.1f} | "
                  f"{seconds[(attribute, 'aot')] * 1e3:.1f} | {'yes' if same else 'NO'} |")


def process_seconds(code: str, env: dict, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True, env=env)
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    from stereocli.match.config import build_config
    from stereocli.match.kernels import set_threads
    from stereocli.match.pipeline import match_pair

    set_threads(2)
    config = build_config([], ["runtime.threads=2"])
    items = pairs()
    for _, left, right, ndisp in items:  # the JIT signatures of a real run (and a warm cache)
        match_pair(left, right, config, ndisp=ndisp)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        seconds = build(folder, "stereocli_aot_probe")
        print(f"pycc compile of {len(KERNELS)} kernels: {seconds:.1f} s")
        sys.path.insert(0, str(folder))
        import stereocli_aot_probe

        timed_kernels(items, config, stereocli_aot_probe, args.repeat)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(folder), str(REPO)]))
        call = ("import numpy as np; a = np.zeros((8, 8), np.float32); b = np.zeros((8, 8), np.int32); "
                "c = np.zeros((8, 8), np.int64); m = np.zeros((8, 8), np.bool_); p = np.ones(4, np.float64); "
                "o = a.copy()\n")
        aot_code = ("import cv2, stereocli_aot_probe as k\n" + call
                    + "getattr(k, [n for n in dir(k) if n.startswith('geodesic_vote_')][0])"
                      "(a, b, c, m, p, 2, 3, 4, False, o, 1, 0)")
        jit_code = ("import cv2\nfrom stereocli.process import prepare_kernels; prepare_kernels()\n"
                    "from stereocli.match.kernels import segment\n" + call
                    + "segment._vote_chunk(a, b, c, m, p, 2, 3, 4, False, o, 1, 0)")
        base = process_seconds("import numpy, cv2", env, args.repeat)
        print(f"\nprocess: import numpy, cv2: {base:.2f} s; + one AOT kernel: "
              f"{process_seconds(aot_code, env, args.repeat):.2f} s; + the same kernel from numba's cache: "
              f"{process_seconds(jit_code, env, args.repeat):.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
