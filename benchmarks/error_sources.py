#!/usr/bin/env python3
"""Where a preset's MiddEval3-Q errors lie: its nonocc bad 2.0 split into three parts.

bad 2.0 at full resolution is an error of more than 0.5 px at Q. Each bad pixel falls in one part:

* ``edge``: within 3 px of a ground-truth depth step (the ground truth's range over a 7×7
  window exceeds 2 px at Q): foreground fattening and misplaced depth edges;
* ``subpixel``: elsewhere, an error of 0.5–1 px at Q (slopes and sub-pixel values);
* ``gross``: elsewhere, an error of more than 1 px at Q (textureless or repetitive surfaces,
  lighting changes).

The three parts add up to the scene's bad 2.0, which is the harness's number (same mask,
invalid pixels counted bad). Rows per scene and the weighted average (the official weights).

    python benchmarks/error_sources.py                     # default
    python benchmarks/error_sources.py --presets default,quality

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from accuracy import DEFAULT_DATA, load_scenes  # noqa: E402
from stereocli.evaluation.datasets import load_scene  # noqa: E402
from stereocli.matching.config import build_config  # noqa: E402
from stereocli.matching.pipeline import match_pair  # noqa: E402
from stereocli.process import prepare_kernels  # noqa: E402

prepare_kernels()

#: Half side of the window that finds depth steps (px at Q), and the step that counts (px at Q).
EDGE_RADIUS = 3
EDGE_STEP = 2.0
PARTS = ("bad2.0", "edge", "subpixel", "gross")


def error_parts(disparity: np.ndarray, gt: np.ndarray, scored: np.ndarray) -> dict[str, float]:
    """% of the ``scored`` pixels in each part (see the module docstring); all maps (H, W) at Q,
    ``disparity`` and ``gt`` float32 px with +inf unknown."""
    known = np.where(np.isfinite(gt), gt, 0.0).astype(np.float32)
    window = np.ones((2 * EDGE_RADIUS + 1, 2 * EDGE_RADIUS + 1), np.uint8)
    near_step = (cv2.dilate(known, window) - cv2.erode(known, window)) > EDGE_STEP
    error = np.where(np.isfinite(disparity), np.abs(disparity - known), np.inf)
    bad = scored & (error > 0.5)
    n = max(int(scored.sum()), 1)
    share = lambda mask: 100.0 * int(mask.sum()) / n  # noqa: E731
    return {"bad2.0": share(bad), "edge": share(bad & near_step),
            "subpixel": share(bad & ~near_step & (error <= 1.0)), "gross": share(bad & ~near_step & (error > 1.0))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--presets", default="default", help="presets or YAML files, comma-separated")
    ap.add_argument("--scenes", default="", help="comma-separated scene subset")
    args = ap.parse_args(argv)
    if not (args.data / "middlebury2014" / "trainingQ").is_dir():
        print(f"skipped: no MiddEval3 data under {args.data}")
        return 0
    scenes = load_scenes(args.data, ["mb2014"], set(args.scenes.split(",")) if args.scenes else None)
    print("| preset | scene | " + " | ".join(PARTS) + " |")
    print("|---|---|" + "---|" * len(PARTS))
    for preset in args.presets.split(","):
        config = build_config([preset], [])
        total = dict.fromkeys(PARTS, 0.0)
        weights = 0.0
        for scene in scenes:
            gt = load_scene(scene.folder, resolution="Q")
            disparity = match_pair(scene.left, scene.right, config, ndisp=scene.ndisp).disparity
            # Estimates are clipped to [0, ndisp] first, as the official evaluator does.
            disparity = np.where(np.isfinite(disparity), np.clip(disparity, 0, scene.ndisp), np.inf)
            scored = gt.masks["nonocc"] & np.isfinite(gt.gt)
            parts = error_parts(disparity, gt.gt, scored)
            print(f"| {preset} | {scene.name} | " + " | ".join(f"{parts[p]:.2f}" for p in PARTS) + " |")
            for p in PARTS:
                total[p] += gt.weight * parts[p]
            weights += gt.weight
        print(f"| {preset} | **weighted** | " + " | ".join(f"**{total[p] / weights:.2f}**" for p in PARTS) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
