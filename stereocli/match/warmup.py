"""Compile a matching config's kernels before its first real pair.

Numba compiles each kernel the first time it runs and caches the machine code on disk (beside
the installed package, or in ``NUMBA_CACHE_DIR``); every later process loads it in
milliseconds. Compiling takes seconds per kernel and holds one core, so it is worth doing ahead
(``stereocli warmup``: Docker images, CI caches) and on several cores at once.

The warm-up runs the config's own pipeline on small synthetic pairs, so every kernel compiles
for exactly the argument types a real run gives it (RGB 8-bit input), split into tasks that run
in parallel processes and share the disk cache:

* ``volume_large``: the volume stages (cost, optimizer, volume refinements) of a 448×320 pair
  with 96 disparities, a volume large enough for the default SGM's coarse-to-fine search;
* ``maps``: the map refinements (LR check, fill, median, votes, smoothing) on a synthetic
  disparity map, without running the volume stages;
* ``volume_small``: the volume stages of a 128×96 pair with 16 disparities (the full-range
  search of small problems).

The command line also runs ``maps`` in a helper process when the first kernel of a run starts
compiling (:func:`compile_aside`): the run compiles its volume stages meanwhile and later loads
the map stages from the cache.
"""

from __future__ import annotations

import atexit
import json
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import numpy as np

from .config import PipelineConfig, validate

#: Tasks in order of decreasing compile time (the order a pool takes them in).
TASKS = ("volume_large", "maps", "volume_small")
#: (width, height, ndisp) of each task's synthetic pair.
SIZES = {"volume_large": (448, 320, 96), "maps": (128, 96, 16), "volume_small": (128, 96, 16)}


def synthetic_pair(width: int, height: int, ndisp: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A textured RGB uint8 pair: a background plane at ``ndisp // 4`` px and a box in front
    at ``ndisp // 2`` px (occlusions beside it, so the LR check rejects some pixels)."""
    rng = np.random.default_rng(seed)
    back = rng.integers(0, 256, (height, width + ndisp, 3), dtype=np.uint8)
    front = rng.integers(0, 256, (height, width + ndisp, 3), dtype=np.uint8)
    d_back, d_front = ndisp // 4, ndisp // 2
    y0, y1, x0, x1 = height // 4, 3 * height // 4, width // 3, 2 * width // 3
    left = back[:, :width].copy()
    left[y0:y1, x0:x1] = front[y0:y1, x0:x1]
    right = back[:, d_back:d_back + width].copy()
    right[y0:y1, x0 - d_front:x1 - d_front] = front[y0:y1, x0:x1]
    return left, right


def _synthetic_disparity(shape: tuple[int, int], ndisp: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    disp = (rng.random(shape) * (ndisp - 1)).astype(np.float32)
    disp[rng.random(shape) < 0.1] = np.inf
    return disp


def run_task(task: str, config: PipelineConfig) -> float:
    """Run one warm-up task (see the module docstring) in this process; returns its seconds."""
    from .pipeline import StripResult, finish, prepare, run_strips

    t0 = time.perf_counter()
    width, height, ndisp = SIZES[task]
    left, right = synthetic_pair(width, height, ndisp)
    prepared = prepare(left, right, config, ndisp=ndisp)
    if task == "maps":
        state = prepared.state
        strip = StripResult(0, height, _synthetic_disparity(state.shape, ndisp, 1))
        if state.wants.right:
            strip.disparity_right = _synthetic_disparity(state.shape, ndisp, 2)
        if state.wants.integer_maps:
            strip.integer_disparity = np.floor(strip.disparity)
            if state.wants.right:
                strip.integer_disparity_right = np.floor(strip.disparity_right)
        finish(prepared, [strip], config)
    elif task in SIZES:
        run_strips(prepared, config)
    else:
        raise ValueError(f"unknown warm-up task {task!r}; valid: {', '.join(TASKS)}")
    return time.perf_counter() - t0


def _run_task_from_dict(task: str, config: dict) -> float:
    return run_task(task, validate(config, "<warm-up>"))


def _start_worker() -> None:
    from ..process import prepare_kernels

    prepare_kernels()


def warm_up(configs: dict[str, PipelineConfig], *, jobs: int = 1, report=None) -> dict[tuple[str, str], float]:
    """Run every task of every config, on ``jobs`` processes (1: in this process); returns
    ``{(config label, task): seconds}``. ``report(label, task, seconds)`` is called as each
    task ends."""
    work = [(label, task) for task in TASKS for label in configs]
    done: dict[tuple[str, str], float] = {}
    if jobs <= 1:
        for label, task in work:
            done[label, task] = run_task(task, configs[label])
            if report:
                report(label, task, done[label, task])
        return done
    with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"), initializer=_start_worker) as pool:
        futures = {pool.submit(_run_task_from_dict, task, configs[label].as_dict()): (label, task)
                   for label, task in work}
        for future, key in futures.items():
            done[key] = future.result()
            if report:
                report(*key, done[key])
    return done


# --- the map stages compiled beside a first run ------------------------------------------------

_aside: list[subprocess.Popen] = []


def compile_aside(config: PipelineConfig | None) -> bool:
    """Start a helper process that compiles ``config``'s map refinements (the ``maps`` task)
    while this process goes on; False when there is nothing to do (no config, no map stage, or
    a helper already started). The helper writes nothing but the numba cache, and is stopped
    when this process exits."""
    if config is None or _aside or not any(not c.stage.traits.needs_cost for c in config.refinement):
        return False
    helper = subprocess.Popen([sys.executable, "-m", "stereocli.match.warmup", "maps"], stdin=subprocess.PIPE,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        helper.stdin.write(json.dumps(config.as_dict()).encode())
        helper.stdin.close()
    except OSError:
        pass
    _aside.append(helper)
    atexit.register(_stop_aside)
    return True


def _stop_aside() -> None:
    for helper in _aside:
        if helper.poll() is None:
            helper.terminate()


def _main() -> None:
    """``python -m stereocli.match.warmup TASK`` with the effective config as JSON on stdin."""
    _start_worker()
    config = json.loads(sys.stdin.read())
    _run_task_from_dict(sys.argv[1], config)


if __name__ == "__main__":
    _main()
