#!/usr/bin/env python3
"""``rectify --uncalibrated`` on real data: the targets, measured as the tests measure them.

1. Every Middlebury scene of ``../shared/data`` (15 MiddEval3-Q, Tsukuba, Venus, Teddy, Cones)
   with its right view warped by a known small homography (1° turn, 5 px lower, 1 % larger,
   a slight perspective): |y_left − y_right| of independent SIFT matches on the rectified pair
   (median, p90; also on the original pair, for reference; of the matches that fit a
   fundamental matrix of their own, and raw), the same of the ground truth's
   correspondences carried into the rectified pair, their smallest rectified disparity, and the
   default preset's nonocc bad 2.0 on the original pair and mapped back from the rectified one.
2. OpenCV's 13-pair chessboard folder as one rig (one pair of homographies): the median
   |y_left − y_right| of the boards' 9x6 corners found on each rectified pair.

    python benchmarks/rectify_uncalibrated.py [--json benchmarks/results/rectify_uncalibrated.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from stereocli.io.images import read_image  # noqa: E402
from stereocli.io.middlebury import read_calib_txt  # noqa: E402
from test_rectify_uncalibrated import _sift_dy, corner_dy_medians, warped_middlebury_case  # noqa: E402

DATA = REPO.parent / "shared" / "data"
#: The v2 scenes' ranges used by the SGM paper (16, 32, 64, 64).
V2 = {"middlebury2001/tsukuba": ("im3", "im4", 16), "middlebury2001/venus": ("im2", "im6", 32),
      "middlebury2003/teddy": ("im2", "im6", 64), "middlebury2003/cones": ("im2", "im6", 64)}


def scenes(data: Path) -> list[tuple[Path, str, str, int]]:
    out = []
    for folder in sorted((data / "middlebury2014" / "trainingQ").iterdir()):
        out.append((folder, "im0", "im1", 16 * -(-read_calib_txt(folder / "calib.txt").ndisp // 16)))
    out += [(data / scene, *names) for scene, names in V2.items()]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args()
    results: dict = {"middlebury": {}, "chessboard": {}}
    print("dy: |y_left - y_right| median/p90 (px) of SIFT matches that fit their own fundamental matrix;\n"
          "raw: of every ratio-tested mutual match (gross mismatches included)")
    print(f"{'scene':12} {'original dy':>12} {'raw':>11} {'rectified dy':>13} {'raw':>11} {'GT dy':>11} "
          f"{'GT min d':>9} {'bad2 orig':>10} {'bad2 mapped':>12} {'ratio':>6} {'seconds':>8}")
    for folder, left, right, ndisp in scenes(args.data):
        t0 = time.perf_counter()
        r = warped_middlebury_case(folder, left, right, ndisp)
        r["seconds"] = time.perf_counter() - t0
        originals = read_image(folder / f"{left}.png"), read_image(folder / f"{right}.png")
        before, raw = _sift_dy(*originals), _sift_dy(*originals, consistent=False)
        r["original_dy_median"], r["original_dy_p90"] = float(np.median(before)), float(np.percentile(before, 90))
        r["original_raw_dy_median"], r["original_raw_dy_p90"] = float(np.median(raw)), float(np.percentile(raw, 90))
        results["middlebury"][folder.name] = r
        print(f"{folder.name:12} {r['original_dy_median']:5.2f}/{r['original_dy_p90']:<6.2f} "
              f"{r['original_raw_dy_median']:5.2f}/{r['original_raw_dy_p90']:<5.2f} "
              f"{r['dy_median']:6.2f}/{r['dy_p90']:<6.2f} {r['raw_dy_median']:5.2f}/{r['raw_dy_p90']:<5.2f} "
              f"{r['gt_dy_median']:5.2f}/{r['gt_dy_p90']:<5.2f} "
              f"{r['gt_min_disparity']:9.2f} {r['bad2_original']:10.2f} "
              f"{r['bad2_mapped']:12.2f} {r['bad2_mapped'] / r['bad2_original']:6.2f} {r['seconds']:8.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rect"
        t0 = time.perf_counter()
        run = subprocess.run(["stereocli", "rectify", str(args.data / "calibration" / "opencv-chessboard"),
                              "--uncalibrated", "-o", str(out), "--format", "json"], capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        if run.returncode:
            sys.exit(run.stderr)
        report = json.loads(run.stdout)
        medians = corner_dy_medians(out)
    results["chessboard"] = {"seconds": seconds, "corner_dy_median": medians, "pairs": report["pairs"]}
    print(f"\nchessboard rig, one pair of homographies for {len(medians)} pairs ({seconds:.1f} s, whole command):")
    print(f"{'pair':6} {'corners |dy| median':>20} {'matches |dy| median / p90':>27}")
    for name, median in medians.items():
        pair = report["pairs"][name]
        shown = "no board" if median is None else f"{median:.2f}"
        print(f"{name:6} {shown:>20} {pair['dy_median']:>18.2f} / {pair['dy_p90']:.2f}")
    met = sum(m is not None and m <= 0.8 for m in medians.values())
    print(f"pairs with the corners' median |dy| <= 0.8 px: {met} of {len(medians)}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=float) + "\n")


if __name__ == "__main__":
    main()
