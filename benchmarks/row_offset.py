#!/usr/bin/env python3
"""How much the rows of the MiddEval3-Q pairs are off, and what ``row_align`` recovers.

For every scene: the plane ``row_align`` fits (offset at the centre, change across the width
and the height, tracks used; "—" when the pair is left as it is, with the reason), then the
nonocc bad 2.0 (official rules) of a preset

* without ``row_align`` (the pair as it is),
* with the right view moved by hand a quarter pixel up or down (each of ``--shifts``, cubic
  interpolation, no ``row_align``): how sensitive the scene is to its rows,
* with ``row_align``,

and the weighted averages (the official weights). The last column is the stage's time per
pair. Timings are for orientation only: ``accuracy.py`` measures presets against OpenCV.

    python benchmarks/row_offset.py                     # default
    python benchmarks/row_offset.py --preset quality --shifts -0.25,0.25

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from accuracy import DEFAULT_DATA, load_scenes, score  # noqa: E402
from stereocli.evaluation.api import weighted_average  # noqa: E402
from stereocli.matching.config import build_config  # noqa: E402
from stereocli.matching.pipeline import match_pair  # noqa: E402
from stereocli.process import prepare_kernels  # noqa: E402

prepare_kernels()


def shifted_down(image: np.ndarray, pixels: float) -> np.ndarray:
    """``image`` moved ``pixels`` down (content of row y appears at row y + pixels), cubic."""
    h, w = image.shape[:2]
    move = np.float32([[1, 0, 0], [0, 1, pixels]])
    return cv2.warpAffine(image, move, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="../shared/data folder")
    ap.add_argument("--preset", default="default", help="stereocli preset or YAML file (with row_align)")
    ap.add_argument("--shifts", default="-0.25,0.25", help="hand shifts of the right view, px (down > 0)")
    ap.add_argument("--threads", type=int, default=2, help="threads for numba and OpenCV")
    args = ap.parse_args()
    data = Path(args.data)
    if not (data / "middlebury2014").is_dir():
        print(f"skipped: no MiddEval3 data under {data}")
        return 0
    cv2.setNumThreads(args.threads)
    sets = [f"runtime.threads={args.threads}"]
    with_align = build_config([args.preset], sets)
    if not any(c.stage.name == "row_align" for c in with_align.preprocess):
        print(f"{args.preset} has no row_align stage; pass a preset or YAML file that does")
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        bare = Path(tmp) / "no_row_align.yaml"
        others = [f"{{name: {c.stage.name}}}" for c in with_align.preprocess if c.stage.name != "row_align"]
        bare.write_text(f"preprocess: [{', '.join(others)}]\n")
        without = build_config([args.preset, str(bare)], sets)
    shifts = [float(s) for s in args.shifts.split(",") if s.strip()]
    scenes = load_scenes(data, ["mb2014"], None)
    columns = ["as it is", *(f"moved {s:+g} px" for s in shifts), "row_align"]
    results: dict[str, list] = {c: [] for c in columns}
    print(f"### {args.preset}: MiddEval3-Q nonocc bad 2.0 %\n")
    print("| scene | fitted offset / across W / across H, px (tracks) | " + " | ".join(columns) + " | row_align ms |")
    print("|---|---|" + "---|" * (len(columns) + 1))
    for scene in scenes:
        runs = {"as it is": (scene.right, without)}
        runs.update({f"moved {s:+g} px": (shifted_down(scene.right, s), without) for s in shifts})
        runs["row_align"] = (scene.right, with_align)
        cells, note, stage_ms = [], {}, 0.0
        for column, (right, config) in runs.items():
            result = match_pair(scene.left, right, config, ndisp=scene.ndisp)
            scored = score(scene, result.disparity, 0.0)
            results[column].append(scored)
            cells.append(f"{scored.metrics['nonocc']['bad2.0']:.2f}")
            if column == "row_align":
                note, stage_ms = result.notes["row_align"], 1e3 * result.timings["preprocess.row_align"]
        fit = (f"{note['offset_px']:+.2f} / {note['tilt_x_px']:+.2f} / {note['tilt_y_px']:+.2f} ({note['tracks']})"
               if note.get("applied") else f"— ({note.get('reason')})")
        print(f"| {scene.name} | {fit} | " + " | ".join(cells) + f" | {stage_ms:.1f} |")
    averages = [weighted_average(results[c])["nonocc"] for c in columns]
    print("| **weighted** | | " + " | ".join(f"**{a['bad2.0']:.2f}** / {a['bad4.0']:.2f}" for a in averages) + " | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
