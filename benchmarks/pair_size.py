#!/usr/bin/env python3
"""Memory and time against OpenCV SGBM 3WAY as pairs grow, one whole process per run.

A Middlebury 2005 scene (a validation scene: ThirdSize views enlarged 3× stand in for its full
size, about 1.4 MP with about 230 disparities) is enlarged 1×, 2× and 3× (cubic), its ground
truth and disparity range scaled alike, and written as PNG files. Each size is then matched by

* ``stereocli match LEFT RIGHT -o OUT --ndisp D`` (the default preset unless ``--preset``), and
* a Python process that reads the PNG files with OpenCV, runs SGBM 3WAY with the settings of
  ``docs/benchmarks.md`` and writes the disparity as a PFM file,

taking turns for ``--repeat`` rounds. Each process reports its own peak resident set size as it
exits (``VmHWM`` in ``/proc/self/status``: ``ru_maxrss`` would count the resident memory of the
process that started it, which the kernel carries over the exec); wall time is measured from
outside. Each keeps its best time and its largest peak. The table gives the ratios to OpenCV's,
the planner's estimate of the peak (``params.json``'s ``memory_estimate_gb``) over the measured
peak, and bad 2 px (all pixels with ground truth) of both maps.

    python benchmarks/pair_size.py                                   # Books, 1x 2x 3x, default preset
    python benchmarks/pair_size.py --scene Dolls --factors 1,2 --repeat 3
    python benchmarks/pair_size.py --set runtime.memory_gb=1 --factors 3   # a 1 GiB budget

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
GIB = 1024.0**3

#: Written first into both processes: at exit, the process's peak RSS (KiB) goes to the file named
#: by its first argument, which is then removed from ``sys.argv``.
PEAK_PRELUDE = r"""
import atexit, sys
def _write_peak(path=sys.argv.pop(1)):
    with open("/proc/self/status") as status:
        peak = status.read().split("VmHWM:")[1].split()[0]
    with open(path, "w") as out:
        out.write(peak)
atexit.register(_write_peak)
"""

#: The stereocli process: ``stereocli`` with the arguments after the peak file.
STEREOCLI_SCRIPT = PEAK_PRELUDE + r"""
import runpy
sys.argv[0] = "stereocli"
runpy.run_module("stereocli", run_name="__main__")
"""

#: The OpenCV process: the settings of benchmarks/accuracy.py's ``opencv_matcher("3way", ...)``.
OPENCV_SCRIPT = PEAK_PRELUDE + r"""
import cv2
import numpy as np
left_path, right_path, ndisp, out, threads = sys.argv[1:6]
cv2.setNumThreads(int(threads))
left, right = cv2.imread(left_path, cv2.IMREAD_COLOR), cv2.imread(right_path, cv2.IMREAD_COLOR)
num = int(np.ceil(int(ndisp) / 16.0) * 16)
block = 3
sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=block, P1=8 * 3 * block * block,
                             P2=32 * 3 * block * block, disp12MaxDiff=1, preFilterCap=63, uniquenessRatio=10,
                             speckleWindowSize=100, speckleRange=2, mode=cv2.StereoSGBM_MODE_SGBM_3WAY)
raw = sgbm.compute(left, right)
disparity = raw.astype(np.float32) / 16.0
disparity[raw < 0] = np.inf
h, w = disparity.shape
with open(out, "wb") as f:
    f.write(b"Pf\n%d %d\n-1.0\n" % (w, h))
    f.write(np.ascontiguousarray(disparity[::-1]).astype("<f4").tobytes())
"""


def run_measured(cmd: list[str], env: dict, peak_file: Path) -> tuple[float, float]:
    """Run ``cmd`` (a script with :data:`PEAK_PRELUDE`; ``peak_file`` its first argument); return
    ``(wall seconds, peak RSS GiB)`` of that process alone."""
    t0 = time.perf_counter()
    out = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - t0
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd[:4])}...: exit {out.returncode}: {out.stderr.strip()[-400:]}")
    return seconds, int(peak_file.read_text()) * 1024 / GIB


def bad(disparity: np.ndarray, truth: np.ndarray, threshold: float = 2.0) -> float:
    """Percentage of pixels with ground truth whose error exceeds ``threshold`` px (invalid counts as bad)."""
    known = np.isfinite(truth)
    error = np.abs(np.where(np.isfinite(disparity), disparity, np.inf) - truth)
    return float(100.0 * np.mean(error[known] > threshold))


def load_scene(data: Path, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left, right (BGR uint8, ThirdSize enlarged 3×) and the left ground truth in px (+inf unknown)."""
    folder = data / "middlebury2005" / name
    left, right = (cv2.imread(str(folder / f), cv2.IMREAD_COLOR) for f in ("view1.png", "view5.png"))
    raw = cv2.imread(str(folder / "disp1.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
    truth = np.where(raw > 0, raw / 3.0, np.inf).astype(np.float32)  # value / 3 at ThirdSize
    return left, right, truth


def enlarge(image: np.ndarray, factor: int, nearest: bool = False) -> np.ndarray:
    if factor == 1:
        return image
    mode = cv2.INTER_NEAREST if nearest else cv2.INTER_CUBIC
    return cv2.resize(image, None, fx=factor, fy=factor, interpolation=mode)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="../shared/data folder")
    ap.add_argument("--scene", default="Books", help="Middlebury 2005 scene (Books, Dolls, Laundry, Moebius, Reindeer)")
    ap.add_argument("--factors", default="1,2,3", help="enlargements of the full-size pair, comma-separated")
    ap.add_argument("--preset", default="default", help="stereocli preset")
    ap.add_argument("--set", action="append", default=[], help="stereocli --set KEY=VALUE (repeatable)")
    ap.add_argument("--threads", type=int, default=2, help="threads for OpenCV and stereocli")
    ap.add_argument("--repeat", type=int, default=2, help="rounds, the two processes taking turns")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows as JSON here")
    args = ap.parse_args(argv)
    if not (args.data / "middlebury2005" / args.scene).is_dir():
        print(f"skipped: {args.data / 'middlebury2005' / args.scene} not found (real-data benchmark)")
        return 0
    base_left, base_right, base_truth = load_scene(args.data, args.scene)
    base_left, base_right = enlarge(base_left, 3), enlarge(base_right, 3)
    base_truth = enlarge(base_truth, 3, nearest=True) * 3
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    sets = [f"runtime.threads={args.threads}", *args.set]
    rows = []
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), "unknown CPU") if Path("/proc/cpuinfo").is_file() else "unknown CPU"
    print(f"{args.scene} (Middlebury 2005, ThirdSize x3 = full size), {args.preset} preset, {args.threads} threads, "
          f"{os.cpu_count()} cores ({cpu}); best time and largest peak of {args.repeat} turns\n")
    print("| pair | stereocli s, GiB | SGBM 3WAY s, GiB | memory | time | estimate / peak | bad2 stereocli / 3WAY |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="pair_size_") as tmp:
        for factor in (int(f) for f in args.factors.split(",") if f):
            left, right = enlarge(base_left, factor), enlarge(base_right, factor)
            truth = enlarge(base_truth, factor, nearest=True) * factor
            ndisp = int(np.ceil(np.nanmax(np.where(np.isfinite(truth), truth, np.nan)) * 1.05 / 16) * 16)
            folder = Path(tmp) / f"x{factor}"
            folder.mkdir()
            paths = [str(folder / "left.png"), str(folder / "right.png")]
            cv2.imwrite(paths[0], left)
            cv2.imwrite(paths[1], right)
            peak_file = folder / "peak_kib"
            ours_cmd = [sys.executable, "-c", STEREOCLI_SCRIPT, str(peak_file), "match", *paths, "-o",
                        str(folder / "out"), "--ndisp", str(ndisp), "--overwrite",
                        *(["--config", args.preset] if args.preset != "default" else []),
                        *(a for s in sets for a in ("--set", s))]
            cv_out = str(folder / "opencv.pfm")
            cv_cmd = [sys.executable, "-c", OPENCV_SCRIPT, str(peak_file), *paths, str(ndisp), cv_out,
                      str(args.threads)]
            best = {"ours": (np.inf, 0.0), "opencv": (np.inf, 0.0)}
            for round_ in range(args.repeat):
                order = [("ours", ours_cmd), ("opencv", cv_cmd)]
                for name, cmd in order if round_ % 2 == 0 else order[::-1]:
                    seconds, peak = run_measured(cmd, env, peak_file)
                    best[name] = (min(best[name][0], seconds), max(best[name][1], peak))
            sys.path.insert(0, str(REPO))
            from stereocli.io.pfm import read_pfm

            ours_dir = next(p.parent for p in (folder / "out").glob("*/params.json"))
            params = json.loads((ours_dir / "params.json").read_text())
            ours_bad, cv_bad = bad(read_pfm(ours_dir / "disp0.pfm"), truth), bad(read_pfm(cv_out), truth)
            (t_ours, m_ours), (t_cv, m_cv) = best["ours"], best["opencv"]
            estimate = float(params["memory_estimate_gb"])
            h, w = truth.shape
            row = {"factor": factor, "width": w, "height": h, "megapixels": round(w * h / 1e6, 2), "ndisp": ndisp,
                   "seconds": round(t_ours, 3), "peak_gib": round(m_ours, 3), "opencv_seconds": round(t_cv, 3),
                   "opencv_peak_gib": round(m_cv, 3), "estimate_gib": estimate, "strips": params.get("strips"),
                   "bad2": round(ours_bad, 2), "opencv_bad2": round(cv_bad, 2)}
            rows.append(row)
            print(f"| {row['megapixels']:.1f} MP, D {ndisp} | {t_ours:.2f} s, {m_ours:.2f} | {t_cv:.2f} s, {m_cv:.2f} "
                  f"| {m_ours / m_cv:.2f}× | {t_ours / t_cv:.2f}× | {estimate:.2f} / {m_ours:.2f} = "
                  f"{estimate / m_ours:.2f} ({row['strips']} strips) | {ours_bad:.1f} / {cv_bad:.1f} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"scene": args.scene, "preset": args.preset, "sets": sets, "cpu": cpu,
                                         "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
