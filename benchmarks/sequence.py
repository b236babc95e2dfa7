#!/usr/bin/env python3
"""Stereo sequences: flicker, accuracy and frames per second, ``temporal="on"`` against ``"off"``.

Sequences (``stereocli.synth.sequences``), each filmed by a static rig with sensor noise of
sigma = 3 grey levels, ground truth per frame:

* ``still`` — the synthetic ``planes`` scene holding still;
* ``moving`` — the same scene with a textured disc moving in front of it;
* ``pan`` — the scene panning 1 px per frame;
* ``<Scene>+disc`` — with ``../shared/data`` present, a real scene with the moving disc pasted over
  it (nearer than the whole scene, so its occlusion is exact): the Middlebury 2014 (Q) scenes
  :data:`SHARED_SCENES` and the Middlebury 2005 (third size) validation scene :data:`VALIDATION_SCENES`.

Each sequence is matched by :class:`stereocli.sequence.SequenceMatcher` with the default preset
and the range the first frame's survey estimates, ``temporal="on"`` and ``"off"`` taking turns for
``--repeat`` rounds (the best time kept; the maps do not depend on the round). Reported:

* flicker: share of static pixels (ground truth unchanged between two frames, not on the moving
  object in either) whose disparity changes by more than 0.5 px from one frame to the next;
* bad 1: share of pixels with ground truth whose disparity is off by more than 1 px (or
  invalid), over the whole image and on the moving object, averaged over the frames;
* fps: frames per second of the whole sequence (the first frame's survey included).

    python benchmarks/sequence.py [--frames 30] [--width 640 --height 480] [--repeat 2] [--refresh-every 3]
                                  [--only NAME ...] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stereocli.sequence import SequenceMatcher  # noqa: E402
from stereocli.synth.sequences import SyntheticSequence, make_sequence, sequence_from_pair  # noqa: E402

DEFAULT_DATA = REPO.parent / "shared" / "data"
#: The Middlebury 2014 (trainingQ) scenes the shared-data rows paste the moving disc over.
SHARED_SCENES = ("Adirondack", "Motorcycle", "Piano", "Playtable")
#: Middlebury 2005 (third size) scenes, a held-out check: the reuse was not tuned on them.
VALIDATION_SCENES = ("Books",)


def flicker(maps: list[np.ndarray], seq: SyntheticSequence) -> float:
    """Share of static pixels changing by more than 0.5 px between consecutive frames (invalid
    against valid counts as a change; both invalid does not)."""
    changed = total = 0
    for i in range(1, len(maps)):
        gt0, gt1 = seq.disparity[i - 1], seq.disparity[i]
        same = np.where(np.isfinite(gt0) & np.isfinite(gt1), np.abs(gt1 - gt0) < 0.1,
                        ~np.isfinite(gt0) & ~np.isfinite(gt1))
        static = same & ~seq.moving[i - 1] & ~seq.moving[i]
        a, b = maps[i - 1][static], maps[i][static]
        both_invalid = ~np.isfinite(a) & ~np.isfinite(b)
        moved = ~(np.abs(b - a) <= 0.5) & ~both_invalid
        changed += int(np.count_nonzero(moved))
        total += int(static.sum())
    return changed / max(total, 1)


def bad1(maps: list[np.ndarray], seq: SyntheticSequence, on_object: bool = False) -> float:
    """Mean over frames of the share of pixels with ground truth (on the moving object only, with
    ``on_object``) off by more than 1 px or invalid."""
    shares = []
    for disparity, gt, mask in zip(maps, seq.disparity, seq.moving):
        where = np.isfinite(gt) & (mask if on_object else True)
        if where.any():
            shares.append(float(np.mean(~(np.abs(disparity[where] - gt[where]) <= 1.0))))
    return float(np.mean(shares)) if shares else float("nan")


def run(seq: SyntheticSequence, temporal: str, **options) -> tuple[list[np.ndarray], float, SequenceMatcher]:
    """The sequence's maps, its seconds and the matcher (the range estimated on the first frame;
    ``options`` are :class:`SequenceMatcher`'s)."""
    matcher = SequenceMatcher(temporal=temporal, **options)
    t0 = time.perf_counter()
    maps = [matcher.push(left, right).disparity for left, right in seq.pairs()]
    return maps, time.perf_counter() - t0, matcher


def measure(name: str, seq: SyntheticSequence, repeat: int, **options) -> dict:
    """Both modes on one sequence, taking turns ``repeat`` times (best time kept); ``options``
    are ``temporal="on"``'s :class:`SequenceMatcher` options."""
    row: dict = {"sequence": name, "frames": len(seq), "size": f"{seq.left[0].shape[1]}x{seq.left[0].shape[0]}"}
    best = {"off": np.inf, "on": np.inf}
    for _ in range(repeat):
        for temporal in ("off", "on"):
            maps, seconds, matcher = run(seq, temporal, **(options if temporal == "on" else {}))
            best[temporal] = min(best[temporal], seconds)
            row[temporal] = {"flicker": flicker(maps, seq), "bad1": bad1(maps, seq),
                             "bad1_object": bad1(maps, seq, on_object=True), "record": matcher.record()}
    for temporal in ("off", "on"):
        row[temporal]["fps"] = len(seq) / best[temporal]
    return row


def shared_sequence(data: Path, scene: str, frames: int, seed: int) -> SyntheticSequence | None:
    """The moving disc over a shared Middlebury 2014 (Q) or 2005 scene, or None without the data."""
    from stereocli.api import read_image

    folder = data / "middlebury2014" / "trainingQ" / scene
    if folder.is_dir():
        from stereocli.io.pfm import read_pfm

        gt = np.asarray(read_pfm(folder / "disp0GT.pfm"), np.float32)
        left, right = read_image(folder / "im0.png"), read_image(folder / "im1.png")
    else:
        folder = data / "middlebury2005" / scene
        if not folder.is_dir():
            return None
        from stereocli.evaluation.datasets import mb2005_divisor

        left, right = read_image(folder / "view1.png"), read_image(folder / "view5.png")
        raw = np.asarray(read_image(folder / "disp1.png"), np.float32)
        raw = raw[..., 0] if raw.ndim == 3 else raw
        divisor = mb2005_divisor(folder, raw.shape[1])[1]
        gt = np.where(raw > 0, raw / divisor, np.inf).astype(np.float32)
    return sequence_from_pair(left, right, np.ascontiguousarray(gt), frames=frames, seed=seed)


def table(rows: list[dict]) -> str:
    lines = ["| sequence | size x frames | flicker off → on | bad 1 off → on (%) | bad 1 on object off → on (%) "
             "| fps off → on | speed-up |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        off, on = r["off"], r["on"]
        obj = ("—" if np.isnan(off["bad1_object"]) else
               f"{100 * off['bad1_object']:.2f} → {100 * on['bad1_object']:.2f}")
        lines.append(f"| {r['sequence']} | {r['size']} x {r['frames']} | {100 * off['flicker']:.2f} % → "
                     f"{100 * on['flicker']:.2f} % ({on['flicker'] / max(off['flicker'], 1e-9):.2f}x) | "
                     f"{100 * off['bad1']:.2f} → {100 * on['bad1']:.2f} | {obj} | {off['fps']:.1f} → "
                     f"{on['fps']:.1f} | {on['fps'] / off['fps']:.2f}x |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--noise", type=float, default=3.0)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--refresh-every", type=int, default=None,
                        help="SequenceMatcher's refresh_every for temporal on (default: its own)")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--only", nargs="*", help="sequence names to run (default: all)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    sequences = {}
    for kind in ("still", "moving", "pan"):
        if not args.only or kind in args.only:
            sequences[kind] = lambda kind=kind: make_sequence(kind, frames=args.frames, width=args.width,
                                                              height=args.height, noise=args.noise)
    for scene in (*SHARED_SCENES, *VALIDATION_SCENES):
        if not args.only or f"{scene}+disc" in args.only:
            sequences[f"{scene}+disc"] = lambda scene=scene: shared_sequence(args.data, scene, args.frames, 0)
    options = {} if args.refresh_every is None else {"refresh_every": args.refresh_every}
    # Compile the kernels first, so the first sequence's time is not its compilation.
    warm = make_sequence("moving", frames=3, width=160, height=120)
    for temporal in ("off", "on"):
        run(warm, temporal)
    rows = []
    for name, make in sequences.items():
        seq = make()
        if seq is None:
            print(f"({name}: no shared data at {args.data}; skipped)")
            continue
        rows.append(measure(name, seq, args.repeat, **options))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    print()
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
