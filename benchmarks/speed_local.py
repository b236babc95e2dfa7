#!/usr/bin/env python3
"""Throughput of every local stage in MDE/s (million disparity evaluations per second).

All methods run on the same pair (Middlebury 2003 Teddy, 450×375, D = 64 by default) in the
same process, with OpenCV StereoBM measured in the same run as the yardstick (``ratio`` =
throughput / StereoBM's). Each method runs through :func:`stereocli.matching.pipeline.match_pair`
as ``[preprocess] → cost → [aggregation] → WTA`` (no refinement unless the row says so) on
the colour pair, except rows marked "grey" (the grey pair StereoBM also gets), once
to warm up (numba compilation, caches), then the best of ``--repeat`` runs is kept.
MDE/s = W·H·D / seconds / 10⁶.

SAD/STAD + WTA pipelines (and the realtime preset) run the fused cost + WTA kernel, which
never stores the cost volume (:func:`stereocli.matching.pipeline.fused_cost_wta`); the rows
marked "volume path" run the same pipeline with the fusion switched off, for comparison.

    python benchmarks/speed_local.py --threads 2
    python benchmarks/speed_local.py --threads 2 --only sad,realtime --repeat 10
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stereocli.io.images import read_image  # noqa: E402
from stereocli.matching import pipeline  # noqa: E402
from stereocli.matching.config import build_config, validate  # noqa: E402
from stereocli.matching.pipeline import match_pair  # noqa: E402
from stereocli.process import keep_freed_memory, prepare_kernels  # noqa: E402

keep_freed_memory()  # as the command line does: freed buffers stay in the process between pairs
prepare_kernels()  # as the command line does: idle kernel threads sleep, numba starts faster

DATA = REPO.parent / "shared" / "data"

# row label: (config dict or preset name, slow?) — slow rows run once after warm-up
COSTS = ["ad", "sd", "tad", "bt", "gradient", "color_gradient", "census", "rank", "ad_census", "ordinal",
         "sad", "ssd", "stad", "ncc", "zncc"]
AGGREGATIONS = {
    "box": ("ad", {"window": [9, 9]}),
    "shiftable": ("sd", {"window": [9, 9]}),
    "multiple_windows": ("ad", {"window": [7, 7], "windows": 9}),
    "variable_window": ("tad", {}),
    "cross": ("tad", {}),
    "adaptive_weights": ("color_gradient", {}),
    "segment_support": ("tad", {}),
    "fast_bilateral": ("tad", {}),
    "guided_filter": ("color_gradient", {}),
}
PREPROCESS = ["log", "mean_removal", "bilateral_subtraction", "xsobel", "histogram_matching"]


VOLUME_PATH = "volume path (fusion off)"


def rows() -> dict[str, object]:
    out: dict[str, object] = {}
    out["grey: realtime preset (mean removal, SAD 9×9, WTA, SMP, sub-pixel, texture)"] = "realtime"
    out["grey: SAD 9×9 (running sums) + WTA"] = {"cost": {"name": "sad", "window": [9, 9]}}
    out[f"grey: realtime preset, {VOLUME_PATH}"] = "realtime"
    out[f"grey: SAD 9×9 + WTA, {VOLUME_PATH}"] = {"cost": {"name": "sad", "window": [9, 9]}}
    out["grey: AD + box 9×9 + WTA"] = {"cost": {"name": "ad"}, "aggregation": [{"name": "box", "window": [9, 9]}]}
    out["realtime preset (colour)"] = "realtime"
    out["SAD 9×9 (running sums) + WTA"] = {"cost": {"name": "sad", "window": [9, 9]}}
    out["AD + box 9×9 + WTA"] = {"cost": {"name": "ad"}, "aggregation": [{"name": "box", "window": [9, 9]}]}
    for c in COSTS:
        out[f"cost {c} + WTA"] = {"cost": {"name": c}}
    for a, (c, params) in AGGREGATIONS.items():
        out[f"{c} + {a} + WTA"] = {"cost": {"name": c}, "aggregation": [{"name": a, **params}]}
    out["tad + fast_bilateral + locally_consistent + WTA"] = {
        "cost": {"name": "tad"}, "aggregation": [{"name": "fast_bilateral"}, {"name": "locally_consistent"}]}
    for p in PREPROCESS:
        out[f"preprocess {p} + SAD 9×9 + WTA"] = {"preprocess": [{"name": p}], "cost": {"name": "sad"}}
    return out


def make_config(spec, threads: int):
    if isinstance(spec, str):
        return build_config([spec], sets=[f"runtime.threads={threads}"])
    base = {"preprocess": [], "aggregation": [], "optimizer": {"name": "wta"}, "refinement": [],
            "runtime": {"threads": threads}}
    return validate({**base, **spec}, "<speed>")


def best_time(fn, repeat: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="middlebury2003/teddy")
    ap.add_argument("--ndisp", type=int, default=64)
    ap.add_argument("--threads", type=int, default=0, help="numba and OpenCV threads (0 = all cores)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default="", help="comma-separated substrings of row labels (case-insensitive)")
    args = ap.parse_args(argv)
    folder = DATA / args.scene
    left, right = read_image(folder / "im2.png"), read_image(folder / "im6.png")
    if args.threads:
        cv2.setNumThreads(args.threads)
    h, w = left.shape[:2]
    mde = w * h * args.ndisp / 1e6

    gl, gr = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    bm = cv2.StereoBM_create(numDisparities=args.ndisp, blockSize=9)
    t_bm = best_time(lambda: bm.compute(gl, gr), max(args.repeat, 10))
    bm_rate = mde / t_bm
    print(f"{args.scene} {w}×{h}, D = {args.ndisp}, threads = {args.threads or 'all'}; "
          f"best of {args.repeat} after a warm-up run\n")
    print("| method | seconds | MDE/s | × StereoBM |")
    print("|---|---|---|---|")
    print(f"| OpenCV StereoBM (block 9, grey, its default post-filters) | {t_bm:.4f} | {bm_rate:.0f} | 1.00 |",
          flush=True)
    for label, spec in rows().items():
        if args.only and not any(s.strip().lower() in label.lower() for s in args.only.split(",")):
            continue
        config = make_config(spec, args.threads)
        slow = any(a in label for a in ("adaptive_weights", "segment_support", "locally_consistent",
                                        "ordinal", "variable_window", "cross"))
        a, b = (gl, gr) if label.startswith("grey:") else (left, right)
        pipeline.FUSED = VOLUME_PATH not in label
        t = best_time(lambda: match_pair(a, b, config, ndisp=args.ndisp), 1 if slow else args.repeat)
        pipeline.FUSED = True
        print(f"| {label} | {t:.4f} | {mde / t:.0f} | {mde / t / bm_rate:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
