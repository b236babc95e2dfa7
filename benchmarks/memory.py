"""Peak memory of the default matcher on a large pair (≈ 6 MP, ndisp ≥ 300).

A MiddEval3 trainingQ scene is upsampled 4× (cubic) to about full resolution and matched in a
child process with ``ndisp`` = 4 × the scene's ndisp (at least ``--min-ndisp``); the child's
peak resident set size (``ru_maxrss``) is reported next to the pipeline's own estimate
(``MatchResult.memory_estimate_gb``) and the number of row strips it planned.

    python benchmarks/memory.py [--scene Adirondack] [--memory-gb 8] [--set key=value ...]

Needs ``../shared/data`` beside the repository.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "middlebury2014" / "trainingQ"


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
    t0 = time.perf_counter()
    res = match_pair(left, right, config, min_disp=0, ndisp=ndisp)
    seconds = time.perf_counter() - t0
    h, w = left.shape[:2]
    print(json.dumps({
        "scene": args.scene, "width": w, "height": h, "megapixels": round(w * h / 1e6, 2), "ndisp": ndisp,
        "strips": res.strips, "estimate_gib": round(res.memory_estimate_gb, 2), "seconds": round(seconds, 1),
        "mde_per_s": round(w * h * ndisp / seconds / 1e6, 1),
    }))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="Adirondack")
    ap.add_argument("--factor", type=float, default=4.0)
    ap.add_argument("--min-ndisp", type=int, default=320)
    ap.add_argument("--memory-gb", type=float, default=8.0)
    ap.add_argument("--config", action="append", default=[])
    ap.add_argument("--set", action="append", default=[])
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
    info = json.loads(out.stdout.strip().splitlines()[-1])
    peak_gib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / 1024**3  # ru_maxrss is KiB on Linux
    info["peak_rss_gib"] = round(peak_gib, 2)
    print(json.dumps(info))
    for k, v in info.items():
        print(f"{k:>14}: {v}")


if __name__ == "__main__":
    main()
