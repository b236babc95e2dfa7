#!/usr/bin/env python3
"""How the time against OpenCV SGBM 3WAY changes with the size of the pair: MiddEval3 trainingQ
scenes enlarged 1×, 2× and 3× (cubic), with the disparity range scaled alike.

A user's photographs are larger than MiddEval3's quarter-resolution pairs, and their
disparity ranges wider. OpenCV SGBM's work grows with pixels × disparities; stereocli's
coarse-to-fine search looks at a window of hypotheses per pixel whose width does not grow with
the range, so the ratio falls as pairs grow. Enlarged Q pairs stand in for larger ones (the
texture is smoother than a real full-resolution pair's, which changes the scores, not the work).

Each preset and SGBM 3WAY run once to warm up, then take turns for ``--repeat`` rounds; each
keeps its best time, summed over the scenes of one size.

    python benchmarks/pair_size.py                                  # default and fast, 3 scenes
    python benchmarks/pair_size.py --presets default --scenes Adirondack --factors 1,2,3,4

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
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

keep_freed_memory()  # as the command line does
prepare_kernels()


def enlarged(scene, factor: int):
    """``scene`` with both views enlarged ``factor`` times (cubic) and its range scaled."""
    if factor == 1:
        return scene

    def grow(image: np.ndarray) -> np.ndarray:
        return cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)

    return replace(scene, left=grow(scene.left), right=grow(scene.right), ndisp=scene.ndisp * factor)


def best_times(scene, configs: dict, repeat: int) -> dict[str, float]:
    """``{preset or "3way": best seconds}``, the presets and OpenCV taking turns."""
    return {name: seconds for name, (_, seconds) in timed_in_turns(presets_and_3way(scene, configs), repeat).items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="../shared/data folder")
    ap.add_argument("--presets", default="default,fast", help="stereocli presets or YAML files, comma-separated")
    ap.add_argument("--scenes", default="Adirondack,Motorcycle,Vintage", help="MiddEval3 trainingQ scenes")
    ap.add_argument("--factors", default="1,2,3", help="enlargement factors, comma-separated")
    ap.add_argument("--threads", type=int, default=2, help="threads for OpenCV and stereocli")
    ap.add_argument("--repeat", type=int, default=3, help="timed rounds (best kept)")
    args = ap.parse_args(argv)
    if not (args.data / "MANIFEST.md").is_file():
        print(f"skipped: {args.data} not found (real-data benchmark)")
        return 0
    cv2.setNumThreads(args.threads)
    set_kernel_threads(args.threads)
    presets = [p for p in args.presets.split(",") if p]
    configs = {p: build_config([p], [f"runtime.threads={args.threads}"]) for p in presets}
    scenes = load_scenes(args.data, ["mb2014"], set(filter(None, args.scenes.split(","))))
    factors = [int(f) for f in args.factors.split(",") if f]
    print(f"{args.threads} threads, best of {args.repeat}; {', '.join(s.name for s in scenes)}; "
          "seconds summed over the scenes\n")
    print("| size | megapixels per pair | disparities | " + " | ".join(f"{p} s (×3WAY)" for p in presets)
          + " | SGBM 3WAY s |")
    print("|---" * (len(presets) + 4) + "|")
    for factor in factors:
        total = {name: 0.0 for name in [*presets, "3way"]}
        for scene in scenes:
            for name, seconds in best_times(enlarged(scene, factor), configs, args.repeat).items():
                total[name] += seconds
        mp = np.mean([s.left.shape[0] * s.left.shape[1] for s in scenes]) * factor * factor / 1e6
        lo, hi = min(s.ndisp for s in scenes) * factor, max(s.ndisp for s in scenes) * factor
        ndisp = f"{lo}–{hi}" if lo != hi else str(lo)
        cells = [f"{total[p]:.3f} ({total[p] / total['3way']:.2f})" for p in presets]
        print(f"| Q × {factor} | {mp:.2f} | {ndisp} | " + " | ".join(cells) + f" | {total['3way']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
