#!/usr/bin/env python3
"""The cost of one call: ``stereocli match`` as a whole process against an OpenCV process.

The reference is a Python process that imports numpy and OpenCV, reads the same images, runs
StereoSGBM 3WAY (the parameters of ``accuracy.py``) over the same disparity range and writes
the PFM (little endian, bottom row first). Cases:

* ``pair``: one 640×480 pair (the centre of MiddEval3-Q Adirondack, 64 disparities);
* ``folder``: the 15 MiddEval3-Q scenes (ranges from each ``calib.txt``) in one process;
* ``import``: ``import stereocli`` in Python (the public functions load on first use), and the
  first use of ``stereocli.match``, over a bare interpreter's start (no data needed).

stereocli runs with its kernels compiled ahead of time (``pip install .``; in a checkout,
``python -m stereocli.runtime.aot``) and, as a third process, without them
(``STEREOCLI_AOT=0``: every kernel from numba's cache).

The processes take turns (A, B, C, A, B, C, ...) for ``--repeat`` rounds with warm numba caches
(one untimed run of each first); each keeps its best and median wall time, and the ratio is
stereocli's over OpenCV's.

``--first-run`` also times the first ``match`` of the pair with an empty numba cache
(``NUMBA_CACHE_DIR`` set to a fresh folder, so every kernel compiles), the compile notice
printed on stderr, and then the same command warm.

    python benchmarks/startup.py                    # both cases, 5 rounds
    python benchmarks/startup.py --cases pair --repeat 9 --first-run

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise). Run on an idle
machine: absolute times move with the load, the ratios much less.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "middlebury2014" / "trainingQ"

#: The OpenCV process: argv = pairs of (scene folder or "L,R,NDISP", output folder).
OPENCV_SCRIPT = r"""
import re, sys
from pathlib import Path
import cv2
import numpy as np

def ndisp_of(folder):
    text = (folder / "calib.txt").read_text()
    return int(re.search(r"ndisp\s*=\s*(\d+)", text).group(1))

args = sys.argv[1:]
for src, out in zip(args[::2], args[1::2]):
    if "," in src:
        left, right, ndisp = src.split(",")
        ndisp = int(ndisp)
    else:
        folder = Path(src)
        left, right, ndisp = folder / "im0.png", folder / "im1.png", ndisp_of(folder)
    im0, im1 = cv2.imread(str(left)), cv2.imread(str(right))
    num = int(np.ceil(ndisp / 16.0) * 16)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=3, P1=8 * 3 * 9, P2=32 * 3 * 9,
                                 disp12MaxDiff=1, preFilterCap=63, uniquenessRatio=10, speckleWindowSize=100,
                                 speckleRange=2, mode=cv2.StereoSGBM_MODE_SGBM_3WAY)
    raw = sgbm.compute(im0, im1)
    disp = raw.astype(np.float32) / 16.0
    disp[raw < 0] = np.inf
    Path(out).mkdir(parents=True, exist_ok=True)
    h, w = disp.shape
    pfm = b"Pf\n%d %d\n-1.0\n" % (w, h) + np.ascontiguousarray(disp[::-1]).astype("<f4").tobytes()
    (Path(out) / "disp0.pfm").write_bytes(pfm)
"""


#: The command that runs stereocli (``--command`` sets it, e.g. to compare two checkouts).
COMMAND: list[str] = []


def stereocli_command() -> list[str]:
    """The console script installed beside this interpreter, as a venv's ``bin/`` holds it.

    Not the first ``stereocli`` on PATH: a version manager's shim there (pyenv's is a shell
    script that runs ``pyenv exec``) adds about 60 ms to every process, while the OpenCV
    process starts this interpreter directly."""
    if COMMAND:
        return list(COMMAND)
    beside = Path(sys.executable).parent / "stereocli"
    if beside.is_file():
        return [str(beside)]
    exe = shutil.which("stereocli")
    return [exe] if exe else [sys.executable, "-m", "stereocli"]


def make_pair(root: Path) -> tuple[Path, Path]:
    """The 640×480 centre of Adirondack (Q), written as two PNGs."""
    import cv2

    pair = root / "pair"
    pair.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in ("im0", "im1"):
        image = cv2.imread(str(DATA / "Adirondack" / f"{name}.png"))
        path = pair / f"{name}.png"
        cv2.imwrite(str(path), image[8:488, 39:679])
        paths.append(path)
    return paths[0], paths[1]


def cases(root: Path, wanted: list[str]) -> dict[str, tuple[list[str], list[str]]]:
    """``{case: (stereocli argv, OpenCV argv)}``."""
    out = {}
    cli = stereocli_command()
    if "pair" in wanted:
        left, right = make_pair(root)
        out["pair"] = (cli + ["match", str(left), str(right), "-o", str(root / "cli-pair"), "--ndisp", "64",
                              "--overwrite", "-q"],
                       [sys.executable, "-c", OPENCV_SCRIPT, f"{left},{right},64", str(root / "cv-pair")])
    if "folder" in wanted:
        scenes = sorted(p for p in DATA.iterdir() if p.is_dir())
        cv_args = []
        for s in scenes:
            cv_args += [str(s), str(root / "cv-folder" / s.name)]
        out["folder"] = (cli + ["match", str(DATA), "-o", str(root / "cli-folder"), "--overwrite", "-q"],
                         [sys.executable, "-c", OPENCV_SCRIPT, *cv_args])
    return out


def wall(argv: list[str], env: dict | None = None) -> tuple[float, str]:
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv[:3])} ... failed ({done.returncode}):\n{done.stderr}")
    return seconds, done.stderr


#: Environment of stereocli's JIT-only process: the kernels compiled ahead of time left unused.
JIT_ONLY = {"STEREOCLI_AOT": "0"}


def in_turns(runs: dict[str, tuple[list[str], dict | None]], repeat: int) -> dict[str, list[float]]:
    for argv, env in runs.values():  # warm-up: caches, page cache
        wall(argv, env)
    times = {name: [] for name in runs}
    for _ in range(repeat):
        for name, (argv, env) in runs.items():
            times[name].append(wall(argv, env)[0])
    return times


def first_run(root: Path, left: Path, right: Path) -> None:
    argv = stereocli_command() + ["match", str(left), str(right), "-o", str(root / "first"), "--ndisp", "64",
                                  "--overwrite"]
    for label, extra in (("", {}), (" without the ahead-of-time kernels (STEREOCLI_AOT=0)", JIT_ONLY)):
        cache = Path(tempfile.mkdtemp(prefix="numba-cache-", dir=root))
        env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), **extra)
        cold, err = wall(argv, env)
        warm, _ = wall(argv, env)
        notice = [line for line in err.splitlines() if "compil" in line.lower()]
        print(f"\nfirst run{label} (empty numba cache): {cold:.1f} s; the next run {warm:.2f} s")
        for line in notice:
            print(f"  stderr: {line}")


def import_cost(repeat: int) -> None:
    """Best wall time of ``import stereocli`` (and of reaching ``stereocli.match``) in a fresh
    interpreter, over that of a bare interpreter, from outside the checkout's working folder."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    runs = {"bare": "pass", "import stereocli": "import stereocli",
            "then stereocli.match": "import stereocli; stereocli.match"}
    best = {}
    for name, code in runs.items():
        argv = [sys.executable, "-c", code]
        wall(argv, env)
        best[name] = min(wall(argv, env)[0] for _ in range(max(1, repeat)))
    for name in ("import stereocli", "then stereocli.match"):
        print(f"{name:20} {1000 * (best[name] - best['bare']):7.1f} ms over a bare interpreter")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="import,pair,folder", help="comma-separated: import, pair, folder")
    ap.add_argument("--repeat", type=int, default=5, help="rounds of alternating runs")
    ap.add_argument("--first-run", action="store_true", help="also time a match with an empty numba cache")
    ap.add_argument("--command", default="",
                    help="how to run stereocli (default: the console script beside this Python)")
    args = ap.parse_args()
    COMMAND[:] = args.command.split()
    wanted = [c.strip() for c in args.cases.split(",") if c.strip()]
    if "import" in wanted:
        import_cost(args.repeat)
        wanted.remove("import")
        if not wanted:
            return
    if not (DATA / "Adirondack").is_dir():
        print(f"skipped: {DATA} not found")
        return
    root = Path(tempfile.mkdtemp(prefix="stereocli-startup-"))
    try:
        print(f"{'case':8} {'process':10} {'best s':>8} {'median s':>9} {'× OpenCV (best)':>16} {'(median)':>9}")
        for case, (cli, cv) in cases(root, wanted).items():
            t = in_turns({"stereocli": (cli, None), "opencv": (cv, None),
                          "JIT only": (cli, dict(os.environ, **JIT_ONLY))}, args.repeat)
            best = {k: min(v) for k, v in t.items()}
            med = {k: statistics.median(v) for k, v in t.items()}
            for name in ("opencv", "stereocli", "JIT only"):
                ratio = ("" if name == "opencv" else
                         f"{best[name] / best['opencv']:16.2f} {med[name] / med['opencv']:9.2f}")
                print(f"{case:8} {name:10} {best[name]:8.3f} {med[name]:9.3f} {ratio}")
        if args.first_run:
            first_run(root, *make_pair(root))
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
