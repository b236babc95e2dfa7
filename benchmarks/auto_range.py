#!/usr/bin/env python3
"""Automatic disparity range: coverage, accuracy and batch time against the known range.

Every scene of ``../shared/data`` (15 MiddEval3-Q, Tsukuba, Venus, Teddy, Cones) is laid out
twice in a temporary folder: with a ``calib.txt`` giving the known ``ndisp`` (the MiddEval3
one, or the SGM paper's 16/32/64/64 for the v2 scenes) and without one, so ``stereocli match``
estimates each range. Both folders are matched as whole ``stereocli match`` processes with the
default preset, taking turns for ``--repeat`` rounds (best kept), and scored with the official
rules (MiddEval3: nonocc bad 2.0 in full-resolution px; v2: nonocc bad 2.0 on derived masks).

    python benchmarks/auto_range.py [--repeat 3] [--json benchmarks/results/auto_range.json]

Prints, per scene: the ground truth's span, the estimated range, the share of finite GT
disparities it covers, ``ndisp / (2 × span + 32)``, bad 2.0 with the known and the estimated
range; then the averages and the batch-time ratio.
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
sys.path.insert(0, str(REPO / "benchmarks"))

from accuracy import DEFAULT_DATA, load_scenes, score  # noqa: E402
from stereocli.evaluation.datasets import load_scene  # noqa: E402
from stereocli.io.pfm import read_pfm  # noqa: E402


def lay_out(scenes, root: Path) -> tuple[Path, Path]:
    """``root/known/<scene>`` with a calib.txt giving ndisp, ``root/auto/<scene>`` without."""
    import cv2

    for scene in scenes:
        for kind in ("known", "auto"):
            folder = root / kind / scene.name
            folder.mkdir(parents=True)
            for stem, image in (("im0", scene.left), ("im1", scene.right)):
                cv2.imwrite(str(folder / f"{stem}.png"),
                            cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image)
        (root / "known" / scene.name / "calib.txt").write_text(f"cam0=[1 0 0; 0 1 0; 0 0 1]\nndisp={scene.ndisp}\n")
    return root / "known", root / "auto"


def run_match(folder: Path, out: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run(["stereocli", "match", str(folder), "-o", str(out), "--overwrite", "-q"], check=True)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "auto_range.json")
    args = ap.parse_args()
    if not (args.data / "MANIFEST.md").is_file():
        print(f"skipped: {args.data} not found (real-data benchmark)")
        return 0
    scenes = load_scenes(args.data, ["mb2014", "v2"], None)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        known, auto = lay_out(scenes, root)
        run_match(known, root / "out_known")  # warm-up: compiled kernels loaded from the cache
        times = {"known": [], "auto": []}
        for _ in range(args.repeat):
            times["known"].append(run_match(known, root / "out_known"))
            times["auto"].append(run_match(auto, root / "out_auto"))
        rows = []
        for scene in scenes:
            gt = load_scene(scene.folder).gt
            finite = gt[np.isfinite(gt)]
            params = json.loads((root / "out_auto" / scene.name / "params.json").read_text())
            lo, nd = params["min_disp"], params["ndisp"]
            span = float(finite.max() - finite.min())
            cover = float(np.mean((finite >= lo) & (finite <= lo + nd - 1)))
            bad = {}
            for kind in ("known", "auto"):
                disp = read_pfm(root / f"out_{kind}" / scene.name / "disp0.pfm")
                bad[kind] = score(scene, disp, 0.0).metrics["nonocc"]["bad2.0"]
            rows.append({"scene": scene.name, "gt": [float(finite.min()), float(finite.max())],
                         "range": [lo, lo + nd - 1], "ndisp": nd, "cover": 100 * cover,
                         "ndisp_ratio": nd / (2 * span + 32),
                         "bad2_known": bad["known"], "bad2_auto": bad["auto"],
                         "alignment": params["alignment"]["max_offset"]})
    print("| scene | GT range px | estimated range | covered % | ndisp / (2·span+32) | bad2.0 known | bad2.0 estimated "
          "| max vertical disparity px |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['gt'][0]:.1f}–{r['gt'][1]:.1f} | {r['range'][0]}–{r['range'][1]} "
              f"| {r['cover']:.2f} | {r['ndisp_ratio']:.2f} | {r['bad2_known']:.2f} | {r['bad2_auto']:.2f} "
              f"| {r['alignment']:.2f} |")
    known_t, auto_t = min(times["known"]), min(times["auto"])
    summary = {
        "min_cover": min(r["cover"] for r in rows), "max_ndisp_ratio": max(r["ndisp_ratio"] for r in rows),
        "mean_bad2_known": float(np.mean([r["bad2_known"] for r in rows])),
        "mean_bad2_auto": float(np.mean([r["bad2_auto"] for r in rows])),
        "batch_seconds_known": known_t, "batch_seconds_auto": auto_t, "time_ratio": auto_t / known_t,
    }
    print(f"\nlowest coverage {summary['min_cover']:.2f} % (target ≥ 99.5); largest ndisp / (2·span+32) "
          f"{summary['max_ndisp_ratio']:.2f} (target ≤ 1); mean bad2.0 {summary['mean_bad2_known']:.2f} known, "
          f"{summary['mean_bad2_auto']:.2f} estimated (target ≤ +1.0); batch {known_t:.2f} s known, {auto_t:.2f} s "
          f"estimated: ×{summary['time_ratio']:.2f} (target ≤ 1.25; best of {args.repeat}, whole processes)")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"scenes": rows, "summary": summary, "times": times}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
