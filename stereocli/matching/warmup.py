"""Compile a matching config's kernels before its first real pair, on several cores at once.

Numba compiles each kernel the first time it runs and caches the machine code on disk (beside
the installed package, or in ``NUMBA_CACHE_DIR``); every later process loads it from there.
Compiling costs far more than loading, kernel by kernel on one core, so a first run is worth
spreading over the cores: ``stereocli warmup`` does it ahead (Docker images, CI caches), and
the command line does it when the first kernel of a run turns out not to be cached.

The warm-up runs the config's own pipeline on small synthetic pairs, so every kernel compiles
for exactly the argument types a real run gives it (RGB 8-bit input), in tasks that run in
separate processes and share the disk cache:

* ``volume_large``: the volume stages (cost, optimizer, volume refinements) of a 448×320 pair
  with 96 disparities, a volume large enough for the default SGM's coarse-to-fine search. It
  hands the search the pair's true half-resolution disparities in place of its coarse level
  (:func:`with_coarse_level`), so this task compiles the fine level only (and the image
  halving), at the same time as ``volume_small`` compiles the coarse level;
* ``maps_1`` and ``maps_2``: the map refinements (LR check, fill, median, votes, smoothing) on
  a synthetic disparity map, without running the volume stages; ``maps_1`` runs the first,
  third, fifth, ... of them, ``maps_2`` the others (so ``accurate``'s two slowest to compile,
  the geodesic vote and ``plane_smooth``, fall into different tasks);
* ``volume_small``: the volume stages of a 128×96 pair with 16 disparities: the full-range
  search of small problems, whose kernels are also the coarse level's.

Compiling the coarse and the fine level in two processes instead of one after the other
shortens the longest process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import IO, Callable, cast

import numpy as np

from .config import PipelineConfig, validate

#: Tasks, each with its share of the compile time (seconds of ``accurate``'s kernels on one core;
#: for spreading them over processes).
TASKS = {"volume_large": 9.5, "maps_2": 6.0, "volume_small": 5.6, "maps_1": 2.4}
#: The folder that holds this ``stereocli`` package, the warm-up processes' working directory:
#: ``python -m`` puts the working directory first on the module path, so a worker started from
#: a checkout would import the checkout's sources rather than the installed package, compile
#: their kernels into a cache of their own, and leave the run to compile its kernels again.
PACKAGE_ROOT = Path(__file__).resolve().parents[2]
#: (width, height, ndisp) of each task's synthetic pair.
SIZES = {"volume_large": (448, 320, 96), "maps_1": (128, 96, 16), "maps_2": (128, 96, 16),
         "volume_small": (128, 96, 16)}


def synthetic_pair(width: int, height: int, ndisp: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A textured RGB uint8 pair: a background plane at ``ndisp // 4`` px and a box in front
    at ``ndisp // 2`` px (occlusions beside it, so the LR check rejects some pixels)."""
    rng = np.random.default_rng(seed)
    back = rng.integers(0, 256, (height, width + ndisp, 3), dtype=np.uint8)
    front = rng.integers(0, 256, (height, width + ndisp, 3), dtype=np.uint8)
    d_back, d_front = ndisp // 4, ndisp // 2
    y0, y1, x0, x1 = _box(width, height)
    left = back[:, :width].copy()
    left[y0:y1, x0:x1] = front[y0:y1, x0:x1]
    right = back[:, d_back:d_back + width].copy()
    right[y0:y1, x0 - d_front:x1 - d_front] = front[y0:y1, x0:x1]
    return left, right


def _box(width: int, height: int) -> tuple[int, int, int, int]:
    """Rows ``[y0, y1)`` and columns ``[x0, x1)`` of :func:`synthetic_pair`'s box (left view)."""
    return height // 4, 3 * height // 4, width // 3, 2 * width // 3


def _true_disparity(width: int, height: int, ndisp: int) -> np.ndarray:
    """(height, width) float32: :func:`synthetic_pair`'s left disparities."""
    disp = np.full((height, width), float(ndisp // 4), np.float32)
    y0, y1, x0, x1 = _box(width, height)
    disp[y0:y1, x0:x1] = ndisp // 2
    return disp


def _synthetic_disparity(shape: tuple[int, int], ndisp: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    disp = (rng.random(shape) * (ndisp - 1)).astype(np.float32)
    disp[rng.random(shape) < 0.1] = np.inf
    return disp


def run_task(task: str, config: PipelineConfig) -> float:
    """Run one warm-up task (see the module docstring) in this process; returns its seconds."""
    from .kernels.images import half_resolution
    from .pipeline import StripResult, finish, prepare, run_strip, run_strips, strip_input

    if task not in TASKS:
        raise ValueError(f"unknown warm-up task {task!r}; valid: {', '.join(TASKS)}")
    t0 = time.perf_counter()
    width, height, ndisp = SIZES[task]
    left, right = synthetic_pair(width, height, ndisp)
    if task.startswith("maps"):
        # Volume refinements stay (they set what the map stages are given); the map stages
        # alternate between the two tasks.
        maps = [i for i, c in enumerate(config.refinement) if not c.stage.traits.needs_cost]
        skipped = set(maps[1::2] if task == "maps_1" else maps[0::2])
        config = replace(config, refinement=[c for i, c in enumerate(config.refinement) if i not in skipped])
    prepared = prepare(left, right, config, ndisp=ndisp)
    if task.startswith("maps"):
        state = prepared.state
        strip = StripResult(0, height, _synthetic_disparity(state.shape, ndisp, 1))
        if state.wants.right:
            strip.disparity_right = _synthetic_disparity(state.shape, ndisp, 2)
        if state.wants.integer_maps:
            strip.integer_disparity = np.floor(strip.disparity)
            if state.wants.right and strip.disparity_right is not None:
                strip.integer_disparity_right = np.floor(strip.disparity_right)
        finish(prepared, [strip], config)
    elif task == "volume_large":
        taken = []

        def true_coarse_level(*_) -> np.ndarray:
            taken.append(True)
            return _true_disparity(width, height, ndisp)[::2, ::2] / np.float32(2.0)

        sub = strip_input(prepared, 0, height)
        run_strip(sub, with_coarse_level(config, true_coarse_level), 0, height)
        if taken:
            # The search went coarse to fine: compile the image halving its coarse level starts
            # with, which the full-range search of volume_small never runs.
            half_resolution(sub.left)
    else:
        run_strips(prepared, config)
    return time.perf_counter() - t0


def with_coarse_level(config: PipelineConfig, coarse_level: Callable) -> PipelineConfig:
    """``config`` whose optimizer, if its traits say ``takes_coarse_level``, calls
    ``coarse_level(state, params, cost)`` instead of computing a coarse-to-fine search's coarse
    level (``config`` itself otherwise)."""
    call = config.optimizer
    if not call.stage.traits.takes_coarse_level:
        return config
    stage = replace(call.stage, func=partial(call.stage.func, coarse_level=coarse_level))
    return replace(config, optimizer=replace(call, stage=stage))


def plan(labels: list[str], jobs: int) -> list[list[tuple[str, str]]]:
    """``(label, task)`` lists, one per process: the longest tasks first, each to the least
    loaded process."""
    work = sorted(((label, task) for label in labels for task in TASKS), key=lambda lt: -TASKS[lt[1]])
    slots: list[list[tuple[str, str]]] = [[] for _ in range(max(1, jobs))]
    load = [0.0] * len(slots)
    for label, task in work:
        i = load.index(min(load))
        slots[i].append((label, task))
        load[i] += TASKS[task]
    return [s for s in slots if s]


def warm_up(configs: dict[str, PipelineConfig], *, jobs: int = 1, report=None) -> None:
    """Run every task of every config on ``jobs`` processes (1: in this process).
    ``report(label, task, seconds)`` is called as each task's process ends (in process
    order). Worker processes are stopped if this one is interrupted."""
    slots = plan(list(configs), jobs)
    if len(slots) == 1 and jobs <= 1:
        for label, task in slots[0]:
            seconds = run_task(task, configs[label])
            if report:
                report(label, task, seconds)
        return
    workers = []
    try:
        for slot in slots:
            payload = json.dumps([[label, task, configs[label].as_dict()] for label, task in slot])
            worker = subprocess.Popen([sys.executable, "-m", "stereocli.matching.warmup"], cwd=PACKAGE_ROOT,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                      text=True)
            workers.append(worker)
            stdin = cast(IO[str], worker.stdin)  # stdin=PIPE
            stdin.write(payload)
            stdin.close()
        for worker in workers:
            lines = cast(IO[str], worker.stdout).read().splitlines()  # stdout=PIPE
            if worker.wait() != 0:
                raise RuntimeError(f"a warm-up process failed (exit code {worker.returncode})")
            for line in lines:
                label, task, seconds = json.loads(line)
                if report:
                    report(label, task, seconds)
    finally:
        for worker in workers:
            if worker.poll() is None:
                worker.kill()
                worker.wait()


def warm_up_first_run(config: PipelineConfig | None) -> None:
    """Called when a run's first kernel has to compile: compile all of ``config`` on every core
    first (the run waits), so the run then loads its kernels from the cache. Any failure is
    left to the run itself, which compiles what it needs."""
    cores = os.cpu_count() or 1
    if config is None or cores < 2:
        return
    try:
        warm_up({"run": config}, jobs=min(cores, 2))
    except Exception:  # noqa: BLE001 - only a warm-up: the run compiles what it lacks itself
        pass


def tiny_match(config: PipelineConfig, *, channels: int, dtype: np.dtype, min_disp: int, ndisp: int, masks: bool,
               **flags):
    """:func:`~stereocli.matching.pipeline.match_pair` on a small random pair of this kind
    (channels, dtype, valid masks, wanted outputs) with at most 32 disparities."""
    from .pipeline import match_pair

    nd = max(1, min(int(ndisp), 32))
    h, w = 48, nd + 64
    info = np.iinfo(dtype) if np.issubdtype(dtype, np.integer) else None
    high = info.max if info else 255
    shape = (h, w, channels) if channels > 1 else (h, w)
    left = np.random.default_rng(0).integers(0, high, shape, endpoint=True).astype(dtype)
    right = np.roll(left, -max(0, min_disp) - nd // 2, axis=1)
    valid = np.ones((h, w), bool) if masks else None
    return match_pair(left, right, config, min_disp=int(min_disp), ndisp=nd, left_valid=valid, right_valid=valid,
                      **flags)


_WARMED: set = set()
_WARMED_LOCK = threading.Lock()


def warm_up_pair(config: PipelineConfig, left: np.ndarray, *, min_disp: int, ndisp: int, masks: bool,
                 **flags) -> None:
    """Once per process and kind of call, match a tiny pair first, so that the time of the first
    real pair (``time.txt``) holds matching, not loading (or compiling) the kernels. The tiny
    pair takes the code path of the real one (:func:`~stereocli.matching.config.small_twin`)."""
    from .config import small_twin

    twin = small_twin(config, left.shape[0], left.shape[1], ndisp)
    key = (repr(twin.as_dict()), left.ndim, left.dtype.str, masks, tuple(sorted(flags.items())))
    with _WARMED_LOCK:
        if key in _WARMED:
            return
        _WARMED.add(key)
    try:
        tiny_match(twin, channels=left.shape[2] if left.ndim == 3 else 1, dtype=left.dtype,
                   min_disp=min_disp, ndisp=ndisp, masks=masks, **flags)
    except Exception:  # noqa: BLE001 - only a warm-up: the real pair reports its own errors
        pass


def _main() -> None:
    """``python -m stereocli.matching.warmup``: runs the ``[label, task, config]`` list read as JSON
    on stdin; prints ``[label, task, seconds]`` per task. Leaves Ctrl-C to its parent (which
    stops it) and exits when the parent is gone."""
    from ..process import prepare_kernels, worker_signals

    worker_signals(os.getppid())
    prepare_kernels()
    for label, task, config in json.loads(sys.stdin.read()):
        seconds = run_task(task, validate(config, "<warm-up>"))
        print(json.dumps([label, task, round(seconds, 2)]), flush=True)


if __name__ == "__main__":
    _main()
