"""Peak memory of the default matcher on a large pair (≈ 6 MP, ndisp ≥ 300).

A MiddEval3 trainingQ scene is upsampled 4× (cubic) to about full resolution and matched in a
child process with ``ndisp`` = 4 × the scene's ndisp (at least ``--min-ndisp``); the child's
peak resident set size (``VmHWM``, its own) is reported next to the pipeline's own estimate
(``MatchResult.memory_estimate_gb``) and the number of row strips it planned.

With ``--profile`` the child also samples its RSS every 2 ms and prints where the peak sits: the
RSS at the start and end of each phase (preparing the pair, each strip's levels of the search,
each map stage) and the highest sample while it ran.

    python benchmarks/memory.py [--scene Adirondack] [--memory-gb 8] [--set key=value ...] [--profile]

Needs ``../shared/data`` beside the repository.
"""

from __future__ import annotations

import argparse
import functools
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "middlebury2014" / "trainingQ"


def resident_mib() -> float:
    """This process's resident set size now, MiB (Linux)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096 / 2**20


def peak_gib() -> float:
    """This process's own peak resident set size, GiB (``VmHWM``; ``ru_maxrss`` of a child would
    count its parent's resident memory at the moment it started)."""
    with open("/proc/self/status") as status:
        return int(status.read().split("VmHWM:")[1].split()[0]) / 2**20


class PhaseProfile:
    """RSS sampled every 2 ms by a thread, and the start and end of the phases it wraps."""

    def __init__(self) -> None:
        self.samples: list[tuple[float, float]] = []
        self.events: list[tuple[float, str, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.perf_counter(), resident_mib()))
            time.sleep(0.002)

    def wrap(self, module, name: str, label: str, label_arg: int | None = None) -> None:
        """Replace ``module.name`` by a function that records its start and end (named ``label``,
        or by its positional argument ``label_arg``)."""
        func = getattr(module, name)

        @functools.wraps(func)
        def recorded(*a, **k):
            what = label if label_arg is None else str(a[label_arg])
            self.events.append((time.perf_counter(), f"{what} start", resident_mib()))
            try:
                return func(*a, **k)
            finally:
                self.events.append((time.perf_counter(), f"{what} end", resident_mib()))

        setattr(module, name, recorded)

    def __enter__(self) -> PhaseProfile:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def table(self) -> str:
        """One row per event: RSS then, and the highest sample until the next event (MiB)."""
        lines = ["| s | event | RSS MiB | peak until the next event MiB |", "|---|---|---|---|"]
        t0 = self.events[0][0] if self.events else 0.0
        for i, (t, what, rss) in enumerate(self.events):
            until = self.events[i + 1][0] if i + 1 < len(self.events) else float("inf")
            peak = max([m for ts, m in self.samples if t <= ts <= until] or [rss])
            lines.append(f"| {t - t0:.3f} | {what} | {rss:.0f} | {peak:.0f} |")
        return "\n".join(lines)


def profiled() -> PhaseProfile:
    """A :class:`PhaseProfile` wrapping the pipeline's phases."""
    from stereocli.matching import pipeline
    from stereocli.matching.kernels import sgm_window
    from stereocli.matching.optimize import sgm

    profile = PhaseProfile()
    profile.wrap(pipeline, "prepare", "prepare (views, preprocess, plan)")
    profile.wrap(pipeline, "run_strip", "strip")
    profile.wrap(sgm, "coarse_disparity", "coarser level")
    profile.wrap(sgm_window, "window_runs", "window runs")
    profile.wrap(sgm_window, "sgm_window", "windowed SGM")
    profile.wrap(pipeline, "find_unmatched", "unmatched pixels")
    profile.wrap(pipeline, "_timed", "stage", label_arg=1)  # (timings, "refinement.median", ...)
    return profile


def child(args: argparse.Namespace) -> None:
    sys.path.insert(0, str(REPO))
    import cv2

    from stereocli.io.images import read_image
    from stereocli.io.middlebury import read_calib_txt
    from stereocli.matching.config import build_config
    from stereocli.matching.pipeline import match_pair
    from stereocli.process import keep_freed_memory

    keep_freed_memory()  # as the command line does

    folder = DATA / args.scene
    ndisp = max(4 * read_calib_txt(folder / "calib.txt").ndisp, args.min_ndisp)
    left, right = (read_image(folder / n) for n in ("im0.png", "im1.png"))
    up = lambda im: cv2.resize(im, None, fx=args.factor, fy=args.factor, interpolation=cv2.INTER_CUBIC)  # noqa: E731
    left, right = up(left), up(right)
    config = build_config(args.config, [f"runtime.memory_gb={args.memory_gb}", *args.set])
    profile = profiled() if args.profile else None
    t0 = time.perf_counter()
    if profile is not None:
        with profile:
            res = pipeline_match(left, right, config, ndisp)
    else:
        res = match_pair(left, right, config, min_disp=0, ndisp=ndisp)
    seconds = time.perf_counter() - t0
    h, w = left.shape[:2]
    if profile is not None:
        print(profile.table(), file=sys.stderr)
    print(json.dumps({
        "scene": args.scene, "width": w, "height": h, "megapixels": round(w * h / 1e6, 2), "ndisp": ndisp,
        "strips": res.strips, "estimate_gib": round(res.memory_estimate_gb, 2), "seconds": round(seconds, 1),
        "mde_per_s": round(w * h * ndisp / seconds / 1e6, 1), "peak_rss_gib": round(peak_gib(), 2),
    }))


def pipeline_match(left, right, config, ndisp: int):
    """:func:`match_pair` looked up when called (so the profile's wrappers are the ones called)."""
    from stereocli.matching import pipeline

    return pipeline.match_pair(left, right, config, min_disp=0, ndisp=ndisp)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="Adirondack")
    ap.add_argument("--factor", type=float, default=4.0)
    ap.add_argument("--min-ndisp", type=int, default=320)
    ap.add_argument("--memory-gb", type=float, default=8.0)
    ap.add_argument("--config", action="append", default=[])
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--profile", action="store_true", help="print the RSS of each phase (stderr)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    if not (DATA / args.scene).is_dir():
        sys.exit(f"{DATA / args.scene}: not found (needs ../shared/data)")
    cmd = [sys.executable, __file__, "--child", *sys.argv[1:]]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(out.stderr.strip().splitlines()[-1] if out.stderr.strip() else f"child failed ({out.returncode})")
    if args.profile:
        print(out.stderr)
    info = json.loads(out.stdout.strip().splitlines()[-1])
    print(json.dumps(info))
    for k, v in info.items():
        print(f"{k:>14}: {v}")


if __name__ == "__main__":
    main()
