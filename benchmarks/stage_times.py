#!/usr/bin/env python3
"""Where a preset's time goes: per-stage wall time on MiddEval3 trainingQ (or v2) pairs, against OpenCV
SGBM 3WAY on the same pair in the same process.

Each preset runs once to warm up (numba caches, allocations), then ``--repeat`` times with the
presets interleaved; every stage keeps its best time over the runs (``MatchResult.timings``,
seconds per stage), the total its best end-to-end time. OpenCV runs after all stereocli runs
of a scene: its worker threads keep spinning for a while after a call and would slow the
next numba stage down. ``×3WAY`` is the total over SGBM 3WAY's best time (same disparity
range, same thread count, the harness's recommended parameters).

    python benchmarks/stage_times.py                                   # default on 3 scenes
    python benchmarks/stage_times.py --presets default,fast --scenes Adirondack,Vintage --repeat 9

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from accuracy import DEFAULT_DATA, load_scenes, run_opencv, timed  # noqa: E402
from stereocli.config import build_config  # noqa: E402
from stereocli.match.pipeline import match_pair  # noqa: E402


def stage_label(key: str) -> str:
    """'refinement.region_voting' -> 'region_voting' (the pipeline's timing keys)."""
    return key.split(".", 1)[-1]


def best_stage_times(scene, configs: dict, repeat: int) -> dict[str, dict[str, float]]:
    """{preset: {stage: best seconds, ..., 'total': best seconds}} with the presets interleaved."""
    best: dict[str, dict[str, float]] = {p: defaultdict(lambda: np.inf) for p in configs}
    for p, cfg in configs.items():  # warm-up
        match_pair(scene.left, scene.right, cfg, ndisp=scene.ndisp)
    for _ in range(repeat):
        for p, cfg in configs.items():
            t0 = time.perf_counter()
            result = match_pair(scene.left, scene.right, cfg, ndisp=scene.ndisp)
            total = time.perf_counter() - t0
            best[p]["total"] = min(best[p]["total"], total)
            for key, seconds in result.timings.items():
                best[p][stage_label(key)] = min(best[p][stage_label(key)], seconds)
    return best


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
    presets = [p for p in args.presets.split(",") if p]
    configs = {p: build_config([p], []) for p in presets}
    scenes = load_scenes(args.data, args.datasets.split(","), set(filter(None, args.scenes.split(","))))
    print(f"{args.threads} threads, best of {args.repeat} per stage; ms per pair\n")
    for scene in scenes:
        best = best_stage_times(scene, configs, args.repeat)
        _, sgbm = timed(lambda: run_opencv("3way", scene), args.repeat, True)
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
