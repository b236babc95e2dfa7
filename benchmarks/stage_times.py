#!/usr/bin/env python3
"""Where a preset's time goes: per-stage wall time on MiddEval3 trainingQ (or v2) pairs, against OpenCV
SGBM 3WAY on the same pair in the same process.

Each preset and OpenCV SGBM 3WAY run once to warm up (numba caches, allocations), then take
turns for ``--repeat`` rounds (as in ``accuracy.py``, with a short pause between calls); every
stage keeps its best time over the runs (``MatchResult.timings``, seconds per stage), the
total its best end-to-end time. ``×3WAY`` is the total over SGBM 3WAY's best time (same
disparity range, same thread count, the harness's recommended parameters).

    python benchmarks/stage_times.py                                   # default on 3 scenes
    python benchmarks/stage_times.py --presets default,fast --scenes Adirondack,Vintage --repeat 9

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise).
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from accuracy import DEFAULT_DATA, load_scenes, presets_and_3way, timed_in_turns  # noqa: E402
from stereocli.matching.config import build_config  # noqa: E402
from stereocli.process import keep_freed_memory, prepare_kernels  # noqa: E402
from stereocli.runtime import set_threads as set_kernel_threads  # noqa: E402

keep_freed_memory()  # as the command line does: freed buffers stay in the process between pairs
prepare_kernels()  # as the command line does: idle kernel threads sleep, numba starts faster


def stage_label(key: str) -> str:
    """'refinement.region_voting' -> 'region_voting' (the pipeline's timing keys)."""
    return key.split(".", 1)[-1]


def best_stage_times(scene, configs: dict, repeat: int) -> tuple[dict[str, dict[str, float]], float]:
    """``({preset: {stage: best seconds, ..., 'total': best seconds}}, SGBM 3WAY's best
    seconds)``, the presets and OpenCV taking turns."""
    best: dict[str, dict[str, float]] = {p: defaultdict(lambda: np.inf) for p in configs}
    def keep_stages(name, result, seconds) -> None:
        if name in configs:
            best[name]["total"] = min(best[name]["total"], seconds)
            for key, stage_seconds in result.timings.items():
                best[name][stage_label(key)] = min(best[name][stage_label(key)], stage_seconds)

    sgbm = timed_in_turns(presets_and_3way(scene, configs), repeat, keep_stages)["3way"][1]
    return best, sgbm


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="../shared/data folder")
    ap.add_argument("--presets", default="default", help="stereocli presets or YAML files, comma-separated")
    ap.add_argument("--datasets", default="mb2014", help="mb2014 and/or v2 (Middlebury 2001/2003)")
    ap.add_argument("--scenes", default="Adirondack,Teddy,Vintage", help="scene names (MiddEval3 trainingQ or v2)")
    ap.add_argument("--threads", type=int, default=2, help="threads for OpenCV and numba")
    ap.add_argument("--repeat", type=int, default=7, help="timed runs per preset (best kept per stage)")
    args = ap.parse_args(argv)

    if not (args.data / "MANIFEST.md").is_file():
        print(f"skipped: {args.data} not found (real-data benchmark)")
        return 0
    import numba

    cv2.setNumThreads(args.threads)
    numba.set_num_threads(args.threads)
    set_kernel_threads(args.threads)
    presets = [p for p in args.presets.split(",") if p]
    # The matcher sets its kernel threads from the config's runtime.threads on every call.
    configs = {p: build_config([p], [f"runtime.threads={args.threads}"]) for p in presets}
    scenes = load_scenes(args.data, args.datasets.split(","), set(filter(None, args.scenes.split(","))))
    print(f"{args.threads} threads, best of {args.repeat} per stage; ms per pair\n")
    for scene in scenes:
        best, sgbm = best_stage_times(scene, configs, args.repeat)
        h, w = scene.left.shape[:2]
        print(f"### {scene.name} ({w}×{h}, D = {scene.ndisp}); OpenCV SGBM 3WAY {sgbm * 1e3:.1f} ms\n")
        stages = [k for k in dict.fromkeys(k for p in presets for k in best[p]) if k != "total"]
        print("| preset | total | ×3WAY | " + " | ".join(stages) + " |")
        print("|---" * (len(stages) + 3) + "|")
        for p in presets:
            cells = [f"{best[p][k] * 1e3:.1f}" if np.isfinite(best[p][k]) else "–" for k in stages]
            print(f"| {p} | {best[p]['total'] * 1e3:.1f} | {best[p]['total'] / sgbm:.2f} | " + " | ".join(cells) + " |")
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
