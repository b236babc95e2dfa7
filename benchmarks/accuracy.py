#!/usr/bin/env python3
"""Accuracy/speed harness: stereocli presets vs OpenCV (and optionally CNES Pandora), side by side.

Runs every method on every scene of ``../shared/data`` (MiddEval3 trainingQ and the
Middlebury 2001/2003 scenes), scores all of them with ``stereocli.evaluate`` and prints one
Markdown summary table plus a per-scene table; raw numbers go to JSON.

    python benchmarks/accuracy.py                          # default preset vs OpenCV, all scenes
    python benchmarks/accuracy.py --presets default,fast --scenes Adirondack,teddy
    python benchmarks/accuracy.py --datasets v2 --opencv 3way --threads 2 --repeat 3
    python benchmarks/accuracy.py --pandora ~/venvs/pandora/bin/pandora

Scoring rules (stated again in the table header):
* MiddEval3 trainingQ: official rules, scored at Q against the Q GT with thresholds in
  full-resolution units (bad 2.0 = 0.5 px at Q, bad 4.0 = 1 px at Q), nonocc, invalid counted
  bad, weighted average (0.5 for PianoL, Playroom, Playtable, Shelves, Vintage).
* Middlebury 2001/2003: bad > 1.0 px, nonocc masks *derived* from the GT (MANIFEST rule),
  disparity ranges of the SGM paper (16, 32, 64, 64).
Timing: every method runs once to warm up (numba compilation, OpenCV allocations), then the
methods take turns for ``--repeat`` rounds (A, B, A, B, ...: a machine that slows down for a
while, as shared machines do, slows every method alike) and each keeps its
best run. Ratios to SGBM 3WAY are measured in the same process and rounds, so they survive a
noisy machine better than absolute seconds. (Pandora, a subprocess of seconds, runs once.)
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stereocli.matching.config import build_config  # noqa: E402
from stereocli.evaluation.api import EvalOptions, evaluate_pair, weighted_average  # noqa: E402
from stereocli.evaluation.datasets import load_scene  # noqa: E402
from stereocli.io.images import read_image  # noqa: E402
from stereocli.matching.kernels import set_threads as set_kernel_threads  # noqa: E402
from stereocli.matching.pipeline import match_pair  # noqa: E402
from stereocli.process import keep_freed_memory, prepare_kernels  # noqa: E402

keep_freed_memory()  # as the command line does: freed buffers stay in the process between pairs
prepare_kernels()  # as the command line does: idle kernel threads sleep, numba starts faster

DEFAULT_DATA = REPO.parent / "shared" / "data"
#: v2 scenes: (folder, left, right, ndisp) with the disparity ranges used by the SGM paper.
V2_SCENES = {
    "tsukuba": ("middlebury2001/tsukuba", "im3", "im4", 16),
    "venus": ("middlebury2001/venus", "im2", "im6", 32),
    "teddy": ("middlebury2003/teddy", "im2", "im6", 64),
    "cones": ("middlebury2003/cones", "im2", "im6", 64),
}
OPENCV_METHODS = {"bm": "OpenCV BM", "sgbm": "OpenCV SGBM", "3way": "OpenCV SGBM 3WAY", "hh": "OpenCV SGBM HH"}


@dataclass
class Scene:
    name: str
    dataset: str  # "mb2014" or "v2"
    folder: Path
    left: np.ndarray
    right: np.ndarray
    ndisp: int


def find_image(folder: Path, stem: str) -> Path:
    for suffix in (".png", ".ppm", ".pgm"):
        if (folder / f"{stem}{suffix}").is_file():
            return folder / f"{stem}{suffix}"
    raise FileNotFoundError(folder / stem)


def load_scenes(data: Path, datasets: list[str], only: set[str] | None) -> list[Scene]:
    from stereocli.io.middlebury import read_calib_txt

    scenes = []
    if "mb2014" in datasets:
        root = data / "middlebury2014" / "trainingQ"
        for folder in sorted(p for p in root.glob("*") if p.is_dir()):
            if only and folder.name not in only:
                continue
            calib = read_calib_txt(folder / "calib.txt")
            scenes.append(Scene(folder.name, "mb2014", folder, read_image(folder / "im0.png"),
                                read_image(folder / "im1.png"), calib.ndisp))
    if "v2" in datasets:
        for name, (sub, left, right, ndisp) in V2_SCENES.items():
            if only and name not in only:
                continue
            folder = data / sub
            if folder.is_dir():
                scenes.append(Scene(name, "v2", folder, read_image(find_image(folder, left)),
                                    read_image(find_image(folder, right)), ndisp))
    return scenes


# --- methods ---------------------------------------------------------------------------------


def opencv_matcher(mode: str, ndisp: int, channels: int):
    """OpenCV StereoBM / StereoSGBM with the commonly recommended parameters."""
    num = int(np.ceil(ndisp / 16.0) * 16)  # OpenCV needs a multiple of 16
    if mode == "bm":
        bm = cv2.StereoBM_create(numDisparities=num, blockSize=9)
        bm.setUniquenessRatio(10)
        bm.setSpeckleWindowSize(100)
        bm.setSpeckleRange(2)
        return bm, True
    block = 3 if mode != "hh" else 3
    sgbm_mode = {"sgbm": cv2.StereoSGBM_MODE_SGBM, "3way": cv2.StereoSGBM_MODE_SGBM_3WAY,
                 "hh": cv2.StereoSGBM_MODE_HH}[mode]
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num, blockSize=block,
                                 P1=8 * channels * block * block, P2=32 * channels * block * block,
                                 disp12MaxDiff=1, preFilterCap=63, uniquenessRatio=10,
                                 speckleWindowSize=100, speckleRange=2, mode=sgbm_mode)
    return sgbm, False


def run_opencv(mode: str, scene: Scene) -> np.ndarray:
    left, right = scene.left, scene.right
    matcher, needs_grey = opencv_matcher(mode, scene.ndisp, 1 if left.ndim == 2 else 3)
    if needs_grey and left.ndim == 3:
        left = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
        right = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    elif left.ndim == 3:
        left = cv2.cvtColor(left, cv2.COLOR_RGB2BGR)
        right = cv2.cvtColor(right, cv2.COLOR_RGB2BGR)
    raw = matcher.compute(left, right)
    # int16 x16 fixed point, invalid = (minDisparity - 1) * 16: convert to float px and +inf.
    disp = raw.astype(np.float32) / 16.0
    disp[raw < 0] = np.inf
    return disp


def run_pandora(executable: str, scene: Scene) -> np.ndarray:
    """CNES Pandora's census + SGM example pipeline (its disparity is x_right - x_left)."""
    work = Path(tempfile.mkdtemp(prefix="pandora-"))
    try:
        grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in (scene.left, scene.right)]
        cv2.imwrite(str(work / "left.tif"), grey[0].astype(np.float32))
        cv2.imwrite(str(work / "right.tif"), grey[1].astype(np.float32))
        config = {
            "input": {"left": {"img": str(work / "left.tif"), "disp": [-scene.ndisp, 0], "nodata": -9999},
                      "right": {"img": str(work / "right.tif"), "nodata": -9999}},
            "pipeline": {
                "matching_cost": {"matching_cost_method": "census", "window_size": 5, "subpix": 1},
                "optimization": {"optimization_method": "sgm", "overcounting": False,
                                 "penalty": {"P1": 8, "P2": 32, "p2_method": "constant",
                                             "penalty_method": "sgm_penalty"}},
                "disparity": {"disparity_method": "wta", "invalid_disparity": "NaN"},
                "refinement": {"refinement_method": "vfit"},
                "filter": {"filter_method": "median", "filter_size": 3},
                "validation": {"validation_method": "cross_checking_accurate"},
                "filter.after.validation": {"filter_method": "median", "filter_size": 3},
            },
        }
        (work / "config.json").write_text(json.dumps(config))
        subprocess.run([executable, str(work / "config.json"), str(work / "out")], check=True,
                       capture_output=True)
        found = list((work / "out").rglob("left_disparity.tif"))
        disp = -cv2.imread(str(found[0]), cv2.IMREAD_UNCHANGED).astype(np.float32)
        disp[~np.isfinite(disp)] = np.inf
        return disp
    finally:
        shutil.rmtree(work, ignore_errors=True)


def timed(fn, repeat: int, warm: bool) -> tuple[np.ndarray, float]:
    if warm:
        fn()
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


#: Pause between two timed calls of different methods. The previous method's worker threads
#: keep spinning for a few ms after a call (numba's OpenMP team, OpenCV's pool): measured here,
#: OpenCV right after stereocli ran 40 % slower with no pause, 20 % with 5 ms, 1-2 % with 10 ms;
#: stereocli right after OpenCV 2-3 % slower with 10 ms. Longer idles let the cores clock down
#: (5 % slower with 30 ms).
TURN_GAP_S = 0.01


def presets_and_3way(scene: Scene, configs: dict) -> dict:
    """``{preset: run, "3way": run}`` for :func:`timed_in_turns`: each validated config of
    ``configs`` matching ``scene``, and OpenCV SGBM 3WAY on it."""
    runs = {name: (lambda cfg=cfg: match_pair(scene.left, scene.right, cfg, ndisp=scene.ndisp))
            for name, cfg in configs.items()}
    runs["3way"] = lambda: run_opencv("3way", scene)
    return runs


def timed_in_turns(fns: dict, repeat: int, each=None) -> dict[str, tuple[np.ndarray, float]]:
    """Each function warmed up once, then all of them in turns for ``repeat`` rounds; returns
    ``{name: (last output, best seconds)}``. Each round starts one function later than the
    previous one, so no function always runs right after the same other one (whose worker
    threads may still be spinning). ``each(name, output, seconds)``, if given, sees every
    timed call (e.g. to keep the best of a result's own timings)."""
    outs = {name: fn() for name, fn in fns.items()}
    best = dict.fromkeys(fns, np.inf)
    names = list(fns)
    for round_ in range(repeat):
        start = round_ % len(names)
        for name in names[start:] + names[:start]:
            fn = fns[name]
            time.sleep(TURN_GAP_S)
            t0 = time.perf_counter()
            outs[name] = fn()
            seconds = time.perf_counter() - t0
            best[name] = min(best[name], seconds)
            if each is not None:
                each(name, outs[name], seconds)
    return {name: (outs[name], best[name]) for name in fns}


# --- scoring and tables -------------------------------------------------------------------------


def score(scene: Scene, disp: np.ndarray, seconds: float) -> dict:
    if scene.dataset == "mb2014":
        options = EvalOptions(resolution="Q", threshold_units="full")
        gt = load_scene(scene.folder, resolution="Q")
    else:
        options = EvalOptions(ndisp=scene.ndisp)
        gt = load_scene(scene.folder)
    result = evaluate_pair(disp, gt, options=options, time=seconds, name=scene.name)
    return result


def fmt(v, digits=2) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def summary_rows(results: dict, dataset: str, methods: list[str], scenes: list[Scene], ref: str | None):
    rows = []
    keys = ["bad1.0", "bad2.0", "bad4.0"] if dataset == "mb2014" else ["bad1.0", "bad2.0"]
    for m in methods:
        res = [results[(s.name, m)] for s in scenes if s.dataset == dataset and (s.name, m) in results]
        if not res:
            continue
        avg = weighted_average([r["result"] for r in res])
        nonocc = avg.get("nonocc") or {}
        secs = sum(r["seconds"] for r in res)
        mde = sum(r["mde"] for r in res) / 1e6
        ratio = None
        if ref and all((r["scene"], ref) in results for r in res):
            ratio = secs / sum(results[(r["scene"], ref)]["seconds"] for r in res)
        rows.append([m] + [fmt(nonocc.get(k)) for k in keys] + [fmt(nonocc.get("avgerr")), fmt(nonocc.get("invalid")),
                                                                  fmt(secs, 3), fmt(mde / secs, 1), fmt(ratio)])
    header = ["method"] + [f"{k} %" for k in keys] + ["avgerr px", "invalid %", "time s (sum)", "MDE/s", "time ×3WAY"]
    return header, rows


def markdown(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="../shared/data folder")
    ap.add_argument("--datasets", default="mb2014,v2", help="mb2014 and/or v2")
    ap.add_argument("--scenes", default="", help="comma-separated scene subset")
    ap.add_argument("--presets", default="default", help="stereocli presets or YAML files, comma-separated")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="--set for every preset")
    ap.add_argument("--opencv", default="bm,sgbm,3way,hh", help="OpenCV methods: bm, sgbm, 3way, hh ('' for none)")
    ap.add_argument("--pandora", default=None, help="path to a `pandora` executable (own virtualenv)")
    ap.add_argument("--resolution", default="Q", choices=["Q"], help="MiddEval3 resolution (only Q is in ../shared/data)")
    ap.add_argument("--threads", type=int, default=0, help="threads for OpenCV and numba (0 = all cores)")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per method (best kept)")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "accuracy.json")
    args = ap.parse_args(argv)

    if not (args.data / "MANIFEST.md").is_file():
        print(f"skipped: {args.data} not found (real-data benchmark)")
        return 0
    if args.threads:
        import numba

        cv2.setNumThreads(args.threads)
        numba.set_num_threads(args.threads)
        set_kernel_threads(args.threads)
    only = set(filter(None, args.scenes.split(","))) or None
    scenes = load_scenes(args.data, args.datasets.split(","), only)
    presets = [p for p in args.presets.split(",") if p]
    # The matcher sets its kernel threads from the config's runtime.threads on every call.
    sets = [*args.sets, f"runtime.threads={args.threads}"] if args.threads else args.sets
    configs = {p: build_config([p], sets) for p in presets}
    methods: dict[str, callable] = {}
    for p, cfg in configs.items():
        methods[f"stereocli {p}"] = lambda s, cfg=cfg: match_pair(s.left, s.right, cfg, ndisp=s.ndisp).disparity
    for m in filter(None, args.opencv.split(",")):
        methods[OPENCV_METHODS[m]] = lambda s, m=m: run_opencv(m, s)
    if args.pandora:
        methods["Pandora census+SGM"] = lambda s: run_pandora(args.pandora, s)
    ref = OPENCV_METHODS["3way"] if "3way" in args.opencv.split(",") else None

    results: dict = {}
    for scene in scenes:
        runs = timed_in_turns({name: (lambda fn=fn: fn(scene)) for name, fn in methods.items() if "Pandora" not in name},
                              args.repeat)
        for name, fn in methods.items():
            disp, seconds = runs[name] if name in runs else timed(lambda: fn(scene), 1, warm=False)
            h, w = disp.shape
            res = score(scene, disp, seconds)
            results[(scene.name, name)] = {"scene": scene.name, "method": name, "dataset": scene.dataset,
                                           "seconds": seconds, "mde": w * h * scene.ndisp, "result": res}
            nonocc = res.metrics.get("nonocc") or {}
            print(f"# {scene.name:12s} {name:22s} bad1 {fmt(nonocc.get('bad1.0')):>6} bad2 {fmt(nonocc.get('bad2.0')):>6} "
                  f"{seconds * 1000:8.1f} ms", file=sys.stderr)

    method_names = list(methods)
    threads = args.threads or cv2.getNumThreads()
    out = []
    for dataset, title in (("mb2014", "MiddEval3 trainingQ — nonocc, invalid counted bad, thresholds in "
                                      "full-resolution px (bad 2.0 = 0.5 px at Q, bad 4.0 = 1 px at Q), weighted average"),
                           ("v2", "Middlebury 2001/2003 — nonocc (masks derived from GT, not the official masks), "
                                  "bad > 1.0 / 2.0 px, ndisp 16/32/64/64, average of scenes")):
        if not any(s.dataset == dataset for s in scenes):
            continue
        out.append(f"\n### {title}\n\n{threads} threads, best of {args.repeat} warm run(s).\n")
        header, rows = summary_rows(results, dataset, method_names, scenes, ref)
        out.append(markdown(header, rows))
        per_header = ["scene", "method", "bad1.0 %", "bad2.0 %", "bad4.0 %", "avgerr", "invalid %", "ms", "MDE/s", "×3WAY"]
        per_rows = []
        for s in (s for s in scenes if s.dataset == dataset):
            for m in method_names:
                r = results[(s.name, m)]
                nonocc = r["result"].metrics.get("nonocc") or {}
                ratio = r["seconds"] / results[(s.name, ref)]["seconds"] if ref else None
                per_rows.append([s.name, m, fmt(nonocc.get("bad1.0")), fmt(nonocc.get("bad2.0")),
                                 fmt(nonocc.get("bad4.0")), fmt(nonocc.get("avgerr")), fmt(nonocc.get("invalid")),
                                 fmt(r["seconds"] * 1000, 1), fmt(r["mde"] / r["seconds"] / 1e6, 1), fmt(ratio)])
        out.append("\n<details><summary>per scene</summary>\n\n" + markdown(per_header, per_rows) + "\n\n</details>")
    text = "\n".join(out)
    print(text)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    raw = [{k: v for k, v in r.items() if k != "result"} | {"scores": r["result"].as_dict()} for r in results.values()]
    args.json.write_text(json.dumps({"threads": threads, "repeat": args.repeat, "results": raw}, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
