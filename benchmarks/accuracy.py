#!/usr/bin/env python3
"""Accuracy/speed harness: stereocli presets vs OpenCV (and optionally CNES Pandora), side by side.

Runs every method on every scene of ``../shared/data`` (MiddEval3 trainingQ, the Middlebury
2001/2003 scenes the presets were tuned on, and the validation scenes nothing was tuned on),
scores all of them with ``stereocli.evaluate`` and prints one Markdown summary table plus a
per-scene table per dataset; raw numbers go to JSON. ``--scoreboard`` also writes the committed
``benchmarks/results/scoreboard.json``, from which ``benchmarks/render_docs.py`` writes the
score tables of the README, ``docs/benchmarks.md`` and the presets' comments.

    python benchmarks/accuracy.py                          # default preset vs OpenCV, all scenes
    python benchmarks/accuracy.py --presets default,fast --scenes Adirondack,teddy
    python benchmarks/accuracy.py --datasets v2 --opencv 3way --threads 2 --repeat 3
    python benchmarks/accuracy.py --datasets validation --presets default,quality --opencv 3way
    python benchmarks/accuracy.py --pandora ~/venvs/pandora/bin/pandora

Scoring rules (stated again in the table header):
* MiddEval3 trainingQ: official rules, scored at Q against the Q GT with thresholds in
  full-resolution units (bad 2.0 = 0.5 px at Q, bad 4.0 = 1 px at Q), nonocc, invalid counted
  bad, weighted average (0.5 for PianoL, Playroom, Playtable, Shelves, Vintage).
* Middlebury 2001/2003: bad > 1.0 px, nonocc masks *derived* from the GT (MANIFEST rule),
  disparity ranges of the SGM paper (16, 32, 64, 64).
* Validation (Middlebury 2005 Books, Dolls, Laundry, Moebius, Reindeer at ThirdSize; Middlebury
  2001 barn1, barn2, bull, map, poster, sawtooth): v2 rules (bad > 1.0 px, nonocc masks derived
  from the GT and checked against the right view's GT, estimates clipped to [0, ndisp]), ndisp =
  the GT's largest disparity rounded up to a multiple of 16, plain mean of the scenes.
Timing: every method runs once to warm up (numba compilation, OpenCV allocations), then the
methods take turns for ``--repeat`` rounds (A, B, A, B, ...: a machine that slows down for a
while, as shared machines do, slows every method alike) and each keeps its
best run. Ratios to SGBM 3WAY are measured in the same process and rounds, so they survive a
noisy machine better than absolute seconds. (Pandora, a subprocess of seconds, runs once.)
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import shlex
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

from stereocli.config import preset_names  # noqa: E402
from stereocli.evaluation.api import EvalOptions, evaluate_pair, weighted_average  # noqa: E402
from stereocli.evaluation.datasets import load_scene  # noqa: E402
from stereocli.io.images import read_image  # noqa: E402
from stereocli.matching.config import build_config  # noqa: E402
from stereocli.matching.pipeline import match_pair  # noqa: E402
from stereocli.process import keep_freed_memory, prepare_kernels  # noqa: E402
from stereocli.runtime import set_threads as set_kernel_threads  # noqa: E402

sys.path.insert(0, str(REPO / "benchmarks"))
import scoreboard  # noqa: E402  (benchmarks/scoreboard.py)

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
#: Validation scenes (MANIFEST, "Validation scenes"; nothing was tuned on them): (folder, left,
#: right, GT scale). The 2005 GT holds full-resolution disparities at every size: / 3 at ThirdSize.
VALIDATION_SCENES = {
    **{name: (f"middlebury2005/{name}", "view1.png", "view5.png", 3.0)
       for name in ("Books", "Dolls", "Laundry", "Moebius", "Reindeer")},
    **{name: (f"middlebury2001/{name}", "im2.ppm", "im6.ppm", 8.0)
       for name in ("barn1", "barn2", "bull", "poster", "sawtooth")},
    "map": ("middlebury2001/map", "im0.pgm", "im1.pgm", 8.0),
}
DATASETS = ("mb2014", "v2", "validation")
OPENCV_METHODS = {"bm": "OpenCV BM", "sgbm": "OpenCV SGBM", "3way": "OpenCV SGBM 3WAY", "hh": "OpenCV SGBM HH"}


@dataclass
class Scene:
    name: str
    dataset: str  # "mb2014", "v2" or "validation"
    folder: Path
    left: np.ndarray
    right: np.ndarray
    ndisp: int
    truth: object = None  # the loaded ground truth (stereocli.evaluation.datasets.Scene), validation scenes


def ndisp_from_truth(gt: np.ndarray) -> int:
    """Disparities to search for a ground truth (H, W) float32 px (+inf unknown): its largest
    disparity, rounded up to a multiple of 16 that exceeds it (the range is [0, ndisp))."""
    return int(16 * np.ceil((np.floor(gt[np.isfinite(gt)].max()) + 1) / 16))


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
    if "validation" in datasets:
        for name, (sub, left, right, gt_scale) in VALIDATION_SCENES.items():
            if only and name not in only:
                continue
            folder = data / sub
            if folder.is_dir():
                # The v2 loader reads both layouts given the scale: the smallest disp<k> is the left
                # view's GT, a larger one the right view's, which the derived nonocc mask checks.
                truth = load_scene(folder, dataset="middlebury2001", gt_scale=gt_scale)
                scenes.append(Scene(name, "validation", folder, read_image(folder / left), read_image(folder / right),
                                    ndisp_from_truth(truth.gt), truth))
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
    elif scene.truth is not None:
        options = EvalOptions(ndisp=scene.ndisp)
        gt = scene.truth
    else:
        options = EvalOptions(ndisp=scene.ndisp)
        gt = load_scene(scene.folder)
    result = evaluate_pair(disp, gt, options=options, time=seconds, name=scene.name)
    return result


def validation_title(scenes: list[Scene]) -> str:
    ranges = ", ".join(f"{s.name} {s.ndisp}" for s in scenes if s.dataset == "validation")
    return ("Validation scenes, not tuned on (Middlebury 2005 ThirdSize, Middlebury 2001) — nonocc (masks derived "
            "from the GT, checked against the right view's GT), bad > 1.0 / 2.0 px, ndisp = GT max rounded up to "
            f"a multiple of 16 ({ranges}), mean of scenes")


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


def set_threads(threads: int) -> None:
    """OpenCV's, numba's and the kernel pool's threads."""
    import numba

    cv2.setNumThreads(threads)
    numba.set_num_threads(threads)
    set_kernel_threads(threads)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="../shared/data folder")
    ap.add_argument("--datasets", default=",".join(DATASETS),
                    help="comma-separated: mb2014 (MiddEval3 trainingQ), v2 (Middlebury 2001/2003), "
                         "validation (the scenes nothing was tuned on)")
    ap.add_argument("--scenes", default="", help="comma-separated scene subset")
    ap.add_argument("--presets", default="default", help="stereocli presets or YAML files, comma-separated")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="--set for every preset")
    ap.add_argument("--opencv", default="bm,sgbm,3way,hh", help="OpenCV methods: bm, sgbm, 3way, hh ('' for none)")
    ap.add_argument("--pandora", default=None, help="path to a `pandora` executable (own virtualenv)")
    ap.add_argument("--resolution", default="Q", choices=["Q"],
                    help="MiddEval3 resolution (only Q is in ../shared/data)")
    ap.add_argument("--threads", type=int, default=0, help="threads for OpenCV and numba (0 = all cores)")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs per method (best kept)")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "accuracy.json")
    ap.add_argument("--scoreboard", type=Path, nargs="?", const=scoreboard.PATH, default=None,
                    help="also put the scores into the committed scoreboard (default path: "
                         "benchmarks/results/scoreboard.json), replacing the methods and datasets measured")
    ap.add_argument("--keep-times", action="store_true",
                    help="with --scoreboard: keep the scoreboard's times (a run for scores on a busy machine)")
    args = ap.parse_args(argv)

    if not (args.data / "MANIFEST.md").is_file():
        print(f"skipped: {args.data} not found (real-data benchmark)")
        return 0
    if args.threads:
        set_threads(args.threads)
    only = set(filter(None, args.scenes.split(","))) or None
    datasets = [d for d in args.datasets.split(",") if d]
    unknown = sorted(set(datasets) - set(DATASETS))
    if unknown:
        ap.error(f"--datasets: unknown {', '.join(unknown)}; choose from {', '.join(DATASETS)}")
    presets = [p for p in args.presets.split(",") if p]
    if args.scoreboard and (only or args.sets or set(presets) - set(preset_names())):
        ap.error("--scoreboard records whole datasets of the bundled presets as they are: "
                 "not with --scenes, --set or a config file")
    scenes = load_scenes(args.data, datasets, only)
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
        in_turns = {name: (lambda fn=fn: fn(scene)) for name, fn in methods.items() if "Pandora" not in name}
        runs = timed_in_turns(in_turns, args.repeat)
        for name, fn in methods.items():
            disp, seconds = runs[name] if name in runs else timed(lambda: fn(scene), 1, warm=False)
            h, w = disp.shape
            res = score(scene, disp, seconds)
            results[(scene.name, name)] = {"scene": scene.name, "method": name, "dataset": scene.dataset,
                                           "seconds": seconds, "mde": w * h * scene.ndisp, "result": res}
            nonocc = res.metrics.get("nonocc") or {}
            print(f"# {scene.name:12s} {name:22s} bad1 {fmt(nonocc.get('bad1.0')):>6} "
                  f"bad2 {fmt(nonocc.get('bad2.0')):>6} {seconds * 1000:8.1f} ms", file=sys.stderr)

    method_names = list(methods)
    threads = args.threads or cv2.getNumThreads()
    titles = {"mb2014": "MiddEval3 trainingQ — nonocc, invalid counted bad, thresholds in full-resolution px "
                        "(bad 2.0 = 0.5 px at Q, bad 4.0 = 1 px at Q), weighted average",
              "v2": "Middlebury 2001/2003 — nonocc (masks derived from GT, not the official masks), "
                    "bad > 1.0 / 2.0 px, ndisp 16/32/64/64, average of scenes",
              "validation": validation_title(scenes)}
    out = []
    for dataset, title in titles.items():
        if not any(s.dataset == dataset for s in scenes):
            continue
        out.append(f"\n### {title}\n\n{threads} threads, best of {args.repeat} warm run(s).\n")
        header, rows = summary_rows(results, dataset, method_names, scenes, ref)
        out.append(markdown(header, rows))
        per_header = ["scene", "method", "bad1.0 %", "bad2.0 %", "bad4.0 %", "avgerr", "invalid %", "ms", "MDE/s",
                      "×3WAY"]
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
    if args.scoreboard:
        given = sys.argv[1:] if argv is None else argv
        command = "python benchmarks/accuracy.py " + " ".join(shlex.quote(a) for a in given)
        write_scoreboard(args.scoreboard, results, scenes, method_names, ref, titles, command=command.strip(),
                         threads=threads, repeat=args.repeat, keep_times=args.keep_times)
        print(f"# scoreboard: {args.scoreboard}", file=sys.stderr)
    return 0


SCORE_KEYS = ("bad1.0", "bad2.0", "bad4.0", "avgerr", "invalid")


def write_scoreboard(path: Path, results: dict, scenes: list[Scene], methods: list[str], ref: str | None,
                     titles: dict[str, str], *, command: str, threads: int, repeat: int, keep_times: bool) -> None:
    """Put this run's scores (and times, unless ``keep_times``) into the scoreboard at ``path``."""
    import numba

    board = scoreboard.load(path)
    versions = {"python": platform.python_version(), "numpy": np.__version__, "numba": numba.__version__,
                "opencv": cv2.__version__}
    note = "its times are not used (--keep-times: a busy machine)" if keep_times else ""
    run_id = scoreboard.new_run(board, command=command, threads=threads, repeat=repeat, versions=versions,
                                date=datetime.date.today().isoformat(), note=note)
    for dataset in titles:
        in_set = [s for s in scenes if s.dataset == dataset]
        if not in_set:
            continue
        weights = {s.name: results[(s.name, methods[0])]["result"].weight for s in in_set}
        board["datasets"][dataset] = {"title": titles[dataset],
                                      "scenes": {s.name: {"weight": weights[s.name], "ndisp": s.ndisp} for s in in_set}}
        for method in methods:
            runs = [results[(s.name, method)] for s in in_set]
            nonocc = weighted_average([r["result"] for r in runs]).get("nonocc") or {}
            per_scene = {}
            for s, r in zip(in_set, runs):
                values = r["result"].metrics.get("nonocc") or {}
                per_scene[s.name] = {k: values.get(k) for k in SCORE_KEYS}
                per_scene[s.name]["seconds"] = r["seconds"]
                per_scene[s.name]["x3way"] = r["seconds"] / results[(s.name, ref)]["seconds"] if ref else None
            seconds = sum(r["seconds"] for r in runs)
            totals = {"seconds": seconds, "mde_per_s": sum(r["mde"] for r in runs) / 1e6 / seconds,
                      "x3way": seconds / sum(results[(s.name, ref)]["seconds"] for s in in_set) if ref else None}
            scoreboard.record(board, method, dataset, run_id=run_id, average={k: nonocc.get(k) for k in SCORE_KEYS},
                              scenes=per_scene, time=totals, in_turns="Pandora" not in method, keep_times=keep_times)
    scoreboard.save(board, path)


if __name__ == "__main__":
    sys.exit(main())
