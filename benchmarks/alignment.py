#!/usr/bin/env python
"""Row-alignment check of a pair's survey: false alarms on rectified pairs, detections of
misaligned ones, and its time.

The pairs: the 15 MiddEval3-Q and 4 Middlebury 2001/2003 scenes of ``../shared/data`` and the
13 pairs of the OpenCV chessboard rig after ``stereocli calibrate`` and ``stereocli rectify``
(when the set is there). Each pair is measured as it is (the largest fitted vertical offset
where the plane holds matches; above 2 px is a false alarm), then with its right view moved
6 px down, 3 px down and rotated by 1° about the image centre (each flagged or not). The time
is the survey's sparse matching and alignment fit, best of ``--repeat``, summed over the pairs.

    python benchmarks/alignment.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from accuracy import DEFAULT_DATA, load_scenes  # noqa: E402
from stereocli.features.alignment import row_alignment  # noqa: E402
from stereocli.features.points import match_points  # noqa: E402
from stereocli.io.images import read_image  # noqa: E402

#: Misalignments applied to the right view: name -> (shift down in px, rotation in degrees).
MISALIGNMENTS = {"6 px lower": (6.0, 0.0), "3 px lower": (3.0, 0.0), "1° rotation": (0.0, 1.0)}


def misaligned(right: np.ndarray, shift: float, degrees: float) -> np.ndarray:
    """The right view moved ``shift`` px down and rotated by ``degrees`` about its centre."""
    h, w = right.shape[:2]
    warp = cv2.getRotationMatrix2D((w / 2, h / 2), degrees, 1.0)
    warp[1, 2] += shift
    return cv2.warpAffine(right, warp, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def chessboard_pairs(data: Path, work: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The OpenCV chessboard rig's pairs, calibrated and rectified by the command line."""
    folder = data / "calibration" / "opencv-chessboard"
    if not folder.is_dir():
        return []
    cli = [sys.executable, "-m", "stereocli"]
    subprocess.run([*cli, "calibrate", str(folder), "-o", str(work / "rig.yml"), "--pattern", "9x6", "-q"], check=True)
    subprocess.run([*cli, "rectify", str(folder), "--calib", str(work / "rig.yml"), "-o", str(work / "rect"), "-q"],
                   check=True)
    pairs = []
    for pair in sorted(p for p in (work / "rect").iterdir() if p.is_dir()):
        pairs.append((f"chessboard {pair.name}", read_image(pair / "im0.png"), read_image(pair / "im1.png")))
    return pairs


def survey_seconds(left: np.ndarray, right: np.ndarray, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        row_alignment(match_points(left, right))
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="../shared/data folder")
    ap.add_argument("--repeat", type=int, default=3, help="timed surveys per pair (best kept)")
    args = ap.parse_args()
    if not (args.data / "MANIFEST.md").is_file():
        print(f"skipped: {args.data} not found (real-data benchmark)")
        return 0
    pairs = [(s.name, s.left, s.right) for s in load_scenes(args.data, ["mb2014", "v2"], None)]
    with tempfile.TemporaryDirectory() as tmp:
        pairs += chessboard_pairs(args.data, Path(tmp))
    largest, alarms, seconds = 0.0, 0, 0.0
    flagged = dict.fromkeys(MISALIGNMENTS, 0)
    for _name, left, right in pairs:
        measured = row_alignment(match_points(left, right))
        largest = max(largest, measured.max_offset or 0.0)
        alarms += not measured.aligned
        for case, (shift, degrees) in MISALIGNMENTS.items():
            flagged[case] += not row_alignment(match_points(left, misaligned(right, shift, degrees))).aligned
        seconds += survey_seconds(left, right, args.repeat)
    n = len(pairs)
    print(f"{n} pairs; as they are: largest offset {largest:.2f} px, {alarms} false alarms; "
          + ", ".join(f"{case}: flagged in {count} of {n}" for case, count in flagged.items())
          + f"; survey {seconds * 1e3:.0f} ms in all (best of {args.repeat})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
