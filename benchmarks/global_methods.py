"""Accuracy and speed of the global / scanline optimizers on the Middlebury v2 scenes.

Runs every method (and OpenCV StereoSGBM in the same process, as the reference peer) on
Tsukuba, Venus, Teddy and Cones from ``../shared/data`` and prints a markdown table of
bad-pixel rates (non-occluded, error > 1 px, dense output), wall time and throughput
(MDE/s = W·H·D / seconds / 10⁶).

Masks are *derived* from the GT (z-buffer visibility, plus the right-view GT for Teddy and
Cones; see ``stereocli.evaluation.metrics.derive_nonocc_mask``), not the official v2 masks,
so numbers are close to but not identical with the published tables.

Usage::

    python benchmarks/global_methods.py                  # all methods, all scenes
    python benchmarks/global_methods.py --methods dp,bp --scenes tsukuba --repeat 3
    python benchmarks/global_methods.py --markdown out.md --json out.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stereocli.evaluation.metrics import derive_nonocc_mask, middlebury_stats  # noqa: E402
from stereocli.matching.config import build_config  # noqa: E402
from stereocli.matching.kernels.maps import fill_background  # noqa: E402
from stereocli.matching.pipeline import match_pair  # noqa: E402
from stereocli.process import keep_freed_memory, prepare_kernels  # noqa: E402

keep_freed_memory()  # as the command line does: freed buffers stay in the process between pairs
prepare_kernels()  # as the command line does: idle kernel threads sleep, numba starts faster

DATA = REPO.parent / "shared" / "data"

#: name -> (left, right, GT, right GT or None, GT scale, ndisp)
SCENES = {
    "tsukuba": ("middlebury2001/tsukuba/im3.png", "middlebury2001/tsukuba/im4.png", "middlebury2001/tsukuba/disp3.pgm",
                None, 16, 16),
    "venus": ("middlebury2001/venus/im2.png", "middlebury2001/venus/im6.png", "middlebury2001/venus/disp2.pgm",
              None, 8, 20),
    "teddy": ("middlebury2003/teddy/im2.png", "middlebury2003/teddy/im6.png", "middlebury2003/teddy/disp2.pgm",
              "middlebury2003/teddy/disp6.pgm", 4, 60),
    "cones": ("middlebury2003/cones/im2.png", "middlebury2003/cones/im6.png", "middlebury2003/cones/disp2.pgm",
              "middlebury2003/cones/disp6.pgm", 4, 60),
}

# Refinement chains. Labelling methods (dp, so, bp, gc) run without sub-pixel fitting: their
# integer labels are what the v2 bad>1 metric rewards, and parabolas through raw per-pixel
# costs mostly add noise.
_SUB = "refinement: [{name: subpixel}, {name: lr_check, max_diff: 1.0}, {name: median, size: 3}, {name: fill}]"
_INT = "refinement: [{name: lr_check, max_diff: 1.0}, {name: median, size: 3}, {name: fill}]"
_CENSUS_BOX = "cost: {name: census, window: [7, 9]}\naggregation: [{name: box, window: [5, 5]}]"

#: method -> full pipeline YAML (independent of the default preset) or a preset name.
#: Parameters were tuned once on these four scenes (see the notes in the README section).
METHODS: dict[str, str] = {
    "wta (census + box)": f"{_CENSUS_BOX}\noptimizer: {{name: wta}}\n{_SUB}",
    "dp": f"cost: {{name: bt, truncate: 20}}\naggregation: [{{name: box, window: [5, 5]}}]\n"
          f"optimizer: {{name: dp, occlusion: 0.3}}\n{_INT}",
    "so": f"{_CENSUS_BOX}\noptimizer: {{name: so, smoothness: 0.1}}\n{_INT}",
    "so + adaptive_weights": "cost: {name: census, window: [7, 9]}\naggregation: [{name: adaptive_weights}]\n"
                             f"optimizer: {{name: so, smoothness: 0.1}}\n{_SUB}",
    "bp": "cost: {name: bt, truncate: 15}\naggregation: []\n"
          f"optimizer: {{name: bp, smoothness: 0.5, truncate: 1.7}}\n{_INT}",
    "gc": "cost: {name: bt, truncate: 20}\naggregation: []\n"
          f"optimizer: {{name: gc, model: truncated_linear, smoothness: 0.25, truncate: 1.5}}\n{_INT}",
    "coop": f"{_CENSUS_BOX}\noptimizer: {{name: coop}}\n{_SUB}",
    "adcensus preset": "adcensus",
}
_TMP = tempfile.TemporaryDirectory(prefix="stereocli-bench-")


def load(name: str):
    left, right, gt, gt_right, scale, ndisp = SCENES[name]

    def read_gt(rel):
        g = cv2.imread(str(DATA / rel), cv2.IMREAD_UNCHANGED).astype(np.float32) / scale
        g[g == 0] = np.inf
        return g

    L = cv2.imread(str(DATA / left))[..., ::-1].copy()
    R = cv2.imread(str(DATA / right))[..., ::-1].copy()
    gt_l = read_gt(gt)
    mask = derive_nonocc_mask(gt_l, read_gt(gt_right) if gt_right else None)
    return L, R, gt_l, mask, ndisp


def _config(method: str):
    text = METHODS[method]
    if "\n" not in text:
        return build_config([text], [])
    path = Path(_TMP.name) / f"{abs(hash(method))}.yaml"
    path.write_text("preprocess: []\n" + text + "\n")
    return build_config([str(path)], [])


def opencv_sgbm(left: np.ndarray, right: np.ndarray, ndisp: int) -> np.ndarray:
    """OpenCV StereoSGBM (3-way, block 5, usual P1/P2), holes filled with the background."""
    nd16 = (ndisp + 15) // 16 * 16
    block = 5
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd16, blockSize=block,
                                 P1=8 * 3 * block * block, P2=32 * 3 * block * block,
                                 disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                                 speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    raw = sgbm.compute(np.ascontiguousarray(left[..., ::-1]), np.ascontiguousarray(right[..., ::-1]))
    disp = raw.astype(np.float32) / 16.0
    disp[raw < 0] = np.inf
    return fill_background(disp)


def run(methods: list[str], scenes: list[str], repeat: int) -> list[dict]:
    rows = []
    data = {s: load(s) for s in scenes}
    for method in ["opencv sgbm", *methods]:
        row = {"method": method, "bad": {}, "seconds": {}, "mdes": {}}
        for s in scenes:
            L, R, gt, mask, nd = data[s]
            times = []
            for _ in range(repeat + 1):  # the first run compiles / warms caches: not timed
                t0 = time.perf_counter()
                if method == "opencv sgbm":
                    disp = opencv_sgbm(L, R, nd)
                else:
                    disp = match_pair(L, R, _config(method), ndisp=nd).disparity
                times.append(time.perf_counter() - t0)
            best = min(times[1:] or times)
            row["bad"][s] = middlebury_stats(disp, gt, mask)["bad1.0"]
            row["seconds"][s] = best
            row["mdes"][s] = L.shape[0] * L.shape[1] * nd / best / 1e6
        rows.append(row)
        print(_line(row, scenes), flush=True)
    return rows


def _line(row: dict, scenes: list[str]) -> str:
    bad = " | ".join(f"{row['bad'][s]:.2f}" for s in scenes)
    secs = " | ".join(f"{row['seconds'][s]:.2f}" for s in scenes)
    mdes = sum(row["mdes"][s] for s in scenes) / len(scenes)
    return f"| {row['method']} | {bad} | {secs} | {mdes:.1f} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated subset of: " + ", ".join(METHODS))
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per scene after a warm-up (best is kept)")
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if not (DATA / "MANIFEST.md").is_file():
        sys.exit(f"{DATA}: shared data not found")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        sys.exit(f"unknown methods {unknown}; valid: {', '.join(METHODS)}")
    scenes = args.scenes.split(",")
    header = ("| method | " + " | ".join(f"{s} bad1" for s in scenes) + " | "
              + " | ".join(f"{s} s" for s in scenes) + " | mean MDE/s |")
    print("nonocc bad > 1 px (%), dense output, derived masks; wall seconds per pair; 2-core machine")
    print(header)
    print("|" + "---|" * (2 * len(scenes) + 2))
    rows = run(methods, scenes, args.repeat)
    if args.markdown:
        args.markdown.write_text("\n".join([header, "|" + "---|" * (2 * len(scenes) + 2),
                                            *(_line(r, scenes) for r in rows)]) + "\n")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
