#!/usr/bin/env python3
"""The default batch on a machine it shares: one core busy with another process, or none.

Runs ``stereocli match`` over the 15 MiddEval3-Q scenes as one process on all cores, with the
kernels' idle threads as ``stereocli`` sets them (a short spin, then sleep), spinning for
milliseconds between parallel regions (``spin``: GNU OpenMP's default,
``GOMP_SPINCOUNT=300000``) or sleeping at once (``sleep``: ``GOMP_SPINCOUNT=0``), and on one
core (``--set runtime.threads=1``). Under ``busy`` another process keeps one core
busy (a pure-Python loop) for the whole measurement. The variants take turns, ``--repeat``
rounds per load; each keeps its best and median wall time.

Printed ratios: each variant over the one-thread run under the same load (the kernels'
threads should never make a batch slower than one thread would), and over ``spin`` (how the
setting does against OpenMP's default, idle and busy).

    python benchmarks/shared_machine.py [--repeat 3] [--loads idle,busy]

Needs ``../shared/data`` beside the repository (prints "skipped" otherwise).
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
sys.path.insert(0, str(REPO / "benchmarks"))
from startup import stereocli_command  # noqa: E402  (the console script beside this Python)

DATA = REPO.parent / "shared" / "data" / "middlebury2014" / "trainingQ"

#: variant -> (extra environment, extra arguments)
VARIANTS = {
    "stereocli, 2 threads": ({}, []),
    "spin, 2 threads": ({"GOMP_SPINCOUNT": "300000"}, []),
    "sleep, 2 threads": ({"GOMP_SPINCOUNT": "0"}, []),
    "1 thread": ({}, ["--set", "runtime.threads=1"]),
}
BUSY_LOOP = "while True: pass"


def run(argv: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({done.returncode}):\n{done.stderr}")
    return time.perf_counter() - t0


def measure(out: Path, repeat: int) -> dict[str, list[float]]:
    base = stereocli_command() + ["match", str(DATA), "-o", str(out), "--overwrite", "-q"]
    times: dict[str, list[float]] = {v: [] for v in VARIANTS}
    for env, args in VARIANTS.values():  # warm-up: caches, page cache
        run(base + args, dict(os.environ, **env))
    for _ in range(repeat):
        for variant, (env, args) in VARIANTS.items():
            times[variant].append(run(base + args, dict(os.environ, **env)))
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="rounds of alternating runs per load")
    ap.add_argument("--loads", default="idle,busy", help="comma-separated: idle, busy")
    args = ap.parse_args()
    if not DATA.is_dir():
        print(f"skipped: {DATA} not found")
        return
    out = Path(tempfile.mkdtemp(prefix="stereocli-shared-"))
    try:
        print(f"{'load':5} {'variant':21} {'best s':>7} {'median s':>9} {'× 1 thread':>11} {'× spin':>7}")
        for load in [s.strip() for s in args.loads.split(",") if s.strip()]:
            busy = subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) if load == "busy" else None
            try:
                times = measure(out, args.repeat)
            finally:
                if busy is not None:
                    busy.kill()
                    busy.wait()
            med = {v: statistics.median(t) for v, t in times.items()}
            for variant, t in times.items():
                vs_one = med[variant] / med["1 thread"]
                vs_spin = med[variant] / med["spin, 2 threads"]
                print(f"{load:5} {variant:21} {min(t):7.2f} {med[variant]:9.2f} {vs_one:11.2f} {vs_spin:7.2f}")
    finally:
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
