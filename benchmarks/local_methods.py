#!/usr/bin/env python3
"""Accuracy of the local aggregation methods on the Middlebury 2001/2003 scenes.

Every method runs as  cost → aggregation → WTA → sub-pixel (parabola) → LR check (on the integer
WTA winners, exact agreement, as Rhemann et al. 2011 / Hosni et al. 2013) → hole
filling (region voting, then 16-direction proper interpolation: the ADCensus outlier handling of
Mei et al. 2011) → median 3×3 → ``plane_smooth`` (gated, colour-weighted line fits: a second
sub-pixel step that removes the pixel locking of the parabola fit), dense output, through
:func:`stereocli.matching.pipeline.match_pair`, and is scored with bad > 1.0 px over non-occluded
pixels. One chain (:data:`REFINEMENT`) for every method and scene. The official v2 region
masks are not in ``../shared/data``: the nonocc masks are *derived* from the GT (z-buffer
visibility, cross-checked with ``disp6`` for Teddy/Cones;
``stereocli.evaluation.datasets.load_middlebury_v2``), so numbers are close to, not identical
with, the published v2 table. ``guided_filter`` runs with ``right_view: guided`` (the
right-view map for the LR check is filtered with the right image as guide, as in
Rhemann/Hosni et al.); the other aggregations are symmetric in the two views or read the right
view from the volume.

    python benchmarks/local_methods.py                       # all methods, all four scenes
    python benchmarks/local_methods.py --methods guided_filter,adaptive_weights --threads 2
    python benchmarks/local_methods.py --ranges 16,20,60,60  # the scenes' own ndisp
    python benchmarks/local_methods.py --breakdown           # also: near depth edges / elsewhere

``--breakdown`` splits each score into pixels near depth discontinuities and the rest, with a
*derived* disc mask built like the v2 one (Scharstein & Szeliski 2002, §5.1: GT jumps of more
than 2 px between 4-neighbours, dilated by a 9×9 window), intersected with nonocc.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stereocli.evaluation.datasets import load_middlebury_v2  # noqa: E402
from stereocli.evaluation.metrics import middlebury_stats  # noqa: E402
from stereocli.io.images import read_image  # noqa: E402
from stereocli.matching.config import validate  # noqa: E402
from stereocli.matching.pipeline import match_pair  # noqa: E402
from stereocli.process import keep_freed_memory, prepare_kernels  # noqa: E402

keep_freed_memory()  # as the command line does: freed buffers stay in the process between pairs
prepare_kernels()  # as the command line does: idle kernel threads sleep, numba starts faster

DATA = REPO.parent / "shared" / "data"
SCENES = {  # name: (folder, left, right)
    "Tsukuba": ("middlebury2001/tsukuba", "im3.png", "im4.png"),
    "Venus": ("middlebury2001/venus", "im2.png", "im6.png"),
    "Teddy": ("middlebury2003/teddy", "im2.png", "im6.png"),
    "Cones": ("middlebury2003/cones", "im2.png", "im6.png"),
}
#: method: (cost stage, aggregation stages, published nonocc bad1.0 for reference or None)
METHODS = {
    "box (SAD 9×9)": ({"name": "ad"}, [{"name": "box", "window": [9, 9]}], None),
    "shiftable (SSD + min filter 21×21)": ({"name": "sd"}, [{"name": "shiftable", "window": [21, 21]}],
                                      (5.23, 3.74, 16.5, 10.6)),
    "multiple_windows (9)": ({"name": "ad"}, [{"name": "multiple_windows", "window": [7, 7], "windows": 9}], None),
    "variable_window": ({"name": "tad", "truncate": 30}, [{"name": "variable_window"}], None),
    "cross": ({"name": "tad", "truncate": 30}, [{"name": "cross"}], None),
    # The cost of Julià & Monasse's IPOL implementation of Yoon–Kweon (2015): colour AD truncated
    # at 30 mixed with the x-gradient (α 0.9, τ_g 2), i.e. Hosni et al.'s cost with a wider colour
    # truncation; the paper's plain truncated AD scores 3.96 on Tsukuba through this chain.
    "adaptive_weights": ({"name": "color_gradient", "tau_color": 30}, [{"name": "adaptive_weights"}],
                         (1.38, 0.71, 7.88, 3.97)),
    "segment_support": ({"name": "tad", "truncate": 40 / 3}, [{"name": "segment_support"}], None),
    "fast_bilateral": ({"name": "tad", "truncate": 40 / 3}, [{"name": "fast_bilateral"}], None),
    "locally_consistent (on FBS)": ({"name": "tad", "truncate": 40 / 3},
                                    [{"name": "fast_bilateral"}, {"name": "locally_consistent"}], None),
    "guided_filter": ({"name": "color_gradient"}, [{"name": "guided_filter", "right_view": "guided"}],
                      (1.51, 0.20, 6.16, 2.71)),
}
#: WTA → sub-pixel → LR check → hole filling (→ median → sub-pixel smoothing).
#: ``subpixel`` needs the cost volume, so the pipeline runs it before the map stages; the LR
#: check still decides on the integer WTA winners (``compare: integer``, kept by the pipeline
#: before the sub-pixel fit), and on integers the papers' test is exact agreement (max_diff 0):
#: after both sub-pixel fits, winners 1–2 px apart can pass a 1 px test.
REFINEMENT = [
    {"name": "subpixel", "method": "parabola"},
    {"name": "lr_check", "max_diff": 0.0, "compare": "integer"},
    {"name": "region_voting"},  # holes inside colour regions take the region's dominant disparity
    {"name": "proper_interpolation"},  # the rest: background for occlusions, closest colour for mismatches
    {"name": "median", "size": 3},
    {"name": "plane_smooth"},  # registry defaults (radius 10, gate 1 px, colour range 20)
]
#: Stages that make values non-integer; ``--no-subpixel`` leaves them out.
SUBPIXEL_STAGES = ("subpixel", "plane_smooth")


def derive_disc_mask(gt: np.ndarray, nonocc: np.ndarray, gap: float = 2.0, width: int = 9) -> np.ndarray:
    """(H, W) bool: nonocc pixels within ``width // 2`` px of a GT jump larger than ``gap`` px.

    ``gt`` is (H, W) float32 px with +inf unknown (unknown pixels never make a jump).
    """
    import cv2

    g = np.where(np.isfinite(gt), gt, np.nan)
    jump = np.zeros(gt.shape, bool)
    with np.errstate(invalid="ignore"):
        jx = np.abs(np.diff(g, axis=1)) > gap  # NaN compares False: unknown GT is no jump
        jy = np.abs(np.diff(g, axis=0)) > gap
    jump[:, 1:] |= jx
    jump[:, :-1] |= jx
    jump[1:] |= jy
    jump[:-1] |= jy
    near = cv2.dilate(jump.astype(np.uint8), np.ones((width, width), np.uint8)).astype(bool)
    return near & nonocc


def config_for(method: str, threads: int, subpixel: bool = True):
    cost, aggregation, _ = METHODS[method]
    refinement = [stage for stage in REFINEMENT if subpixel or stage["name"] not in SUBPIXEL_STAGES]
    return validate({"preprocess": [], "cost": cost, "aggregation": aggregation, "optimizer": {"name": "wta"},
                     "refinement": refinement, "runtime": {"threads": threads}}, f"<{method}>")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--methods", default="", help="comma-separated substrings of method names (default: all)")
    ap.add_argument("--ranges", default="16,32,64,64",
                    help="ndisp for Tsukuba,Venus,Teddy,Cones (SGM paper: 16,32,64,64)")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--no-subpixel", action="store_true",
                    help="integer disparities: no subpixel, no plane_smooth (Tsukuba's GT is integer)")
    ap.add_argument("--breakdown", action="store_true",
                    help="print each score as total (near depth edges / elsewhere), derived disc mask")
    args = ap.parse_args(argv)
    if not (args.data / "MANIFEST.md").is_file():
        print(f"no data at {args.data}", file=sys.stderr)
        return 1
    ranges = [int(v) for v in args.ranges.split(",")]
    wanted = [m for m in METHODS if not args.methods or any(s.strip() in m for s in args.methods.split(","))]
    scenes = []
    for (name, (folder, left, right)), nd in zip(SCENES.items(), ranges):
        sc = load_middlebury_v2(args.data / folder)
        scenes.append((name, read_image(args.data / folder / left), read_image(args.data / folder / right), sc, nd))

    print("| method | " + " | ".join(s[0] for s in scenes) + " | avg | published | s/pair (max) |")
    print("|---|" + "---|" * (len(scenes) + 3))
    for method in wanted:
        config = config_for(method, args.threads, not args.no_subpixel)
        row, secs, parts = [], [], []
        for _name, left, right, sc, nd in scenes:
            t0 = time.perf_counter()
            res = match_pair(left, right, config, ndisp=nd)
            secs.append(time.perf_counter() - t0)
            d = res.disparity
            est = np.where(np.isfinite(d), np.clip(d, 0, nd), np.inf).astype(np.float32)  # v2 range
            row.append(middlebury_stats(est, sc.gt, sc.masks["nonocc"], thresholds=(1.0,))["bad1.0"])
            if args.breakdown:
                disc = derive_disc_mask(sc.gt, sc.masks["nonocc"])
                parts.append(tuple(middlebury_stats(est, sc.gt, m, thresholds=(1.0,))["bad1.0"]
                                   for m in (disc, sc.masks["nonocc"] & ~disc)))
        pub = METHODS[method][2]
        pub_txt = "/".join(f"{v:g}" for v in pub) if pub else "–"
        cells = [f"{v:.2f}" for v in row]
        if args.breakdown:
            cells = [f"{c} ({a:.1f}/{b:.2f})" for c, (a, b) in zip(cells, parts)]
        print(f"| {method} | " + " | ".join(cells) + f" | {np.mean(row):.2f} | {pub_txt} | {max(secs):.2f} |",
              flush=True)
    print("\nnonocc bad > 1.0 px (%), dense maps (sub-pixel " + ("off" if args.no_subpixel else "on") + "); "
          "nonocc masks derived from the GT (not the official v2 masks); "
          f"ndisp {args.ranges}; "
          + ("cells: total (near depth edges / elsewhere, derived disc mask); " if args.breakdown else "")
          + "first run of each method includes numba compilation when the cache is cold.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
