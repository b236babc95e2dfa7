"""Batch throughput per executor, and the strip-split speed-up of one large pair.

1. A batch of ``--pairs`` synthetic pairs (``stereocli.synth.scenes.write_scene``, rendered
   into a temporary folder; 4 distinct scenes, copied) is matched with the default config and
   ``--ndisp`` disparities by

   * ``inline``: one process (kernels use all cores);
   * ``pool``: the local process pool, ``--jobs 2``;
   * ``dask-1``: a Dask LocalCluster with 1 worker (one item at a time, kernels on all cores);
   * ``dask-2``: a Dask LocalCluster with 2 workers (kernels on half the cores each).

   Clusters are started (and warmed up on two pairs, so workers have loaded the numba cache)
   before the clock starts: pairs/second is the steady state a running cluster gives. The
   process pool's start-up is inside its time (it is started per batch).
2. One large pair (``--big``, row strips forced by ``--strip-rows``) is matched in-process
   (all cores, and one thread) and with its strips spread over the 2-worker cluster
   (``match --split-strips``); the outputs are checked to be bit-identical.

    python benchmarks/scaling.py [--pairs 24] [--size 640x480] [--big 1920x1440] [--json out.json]

Numbers depend on the machine (and on other load): run on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def make_pairs(root: Path, n: int, size: tuple[int, int], distinct: int = 4) -> Path:
    """``n`` pair folders: ``distinct`` rendered scenes, copied round-robin (rendering is slow)."""
    import shutil

    from stereocli.synth.scenes import write_scene

    data = root / "data"
    for i in range(min(n, distinct)):
        write_scene(data / f"p{i:03d}", ("planes", "curved")[i % 2], width=size[0], height=size[1], seed=i)
    for i in range(distinct, n):
        shutil.copytree(data / f"p{i % distinct:03d}", data / f"p{i:03d}")
    return data


def plan(data: Path, out: Path, config_args: list[str], sets: list[str], ndisp: int | None = None, **opts):
    from stereocli.io.pairs import discover_pairs
    from stereocli.jobs.match import plan_items
    from stereocli.matching.config import build_config

    pairs, _ = discover_pairs([str(data)])
    items = plan_items(pairs, out, config=build_config(config_args, sets).as_dict(), ndisp=ndisp, min_disp=None)
    for item in items:
        item.options.update(opts)
    return items


def timed_batch(items, **kwargs) -> float:
    from stereocli.jobs.executors import run_batch
    from stereocli.jobs.match import match_item

    t0 = time.perf_counter()
    result = run_batch(items, match_item, progress=False, **kwargs)
    seconds = time.perf_counter() - t0
    if result.exit_code:
        raise SystemExit(f"batch failed: {[r.message for r in result.failed]}")
    return seconds


def local_cluster(n_workers: int):
    import distributed

    threads = max(1, (os.cpu_count() or 1) // n_workers)
    # One item at a time per worker; its kernels use the worker's share of the cores (as --scheduler local).
    return distributed.LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                    dashboard_address=None, silence_logs=40,
                                    env={"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=24)
    ap.add_argument("--size", type=_size, default=(640, 480), help="pair size WxH for the batch")
    ap.add_argument("--ndisp", type=int, default=128, help="disparities searched per batch pair")
    ap.add_argument("--big", type=_size, default=(1920, 1440), help="pair size WxH for the strip-split test")
    ap.add_argument("--big-ndisp", type=int, default=256, help="disparities searched for the big pair")
    ap.add_argument("--strip-rows", type=int, default=360, help="rows per strip for the big pair")
    ap.add_argument("--config", action="append", default=[], help="preset or YAML (default: default preset)")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--skip-batch", action="store_true")
    ap.add_argument("--skip-split", action="store_true")
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()

    report: dict = {"cpu_count": os.cpu_count(), "config": args.config or ["default"], "sets": args.set}
    with tempfile.TemporaryDirectory(prefix="stereocli-scaling-") as tmp:
        root = Path(tmp)
        if not args.skip_batch:
            t0 = time.perf_counter()
            data = make_pairs(root, args.pairs, args.size)
            print(f"rendered {args.pairs} pairs of {args.size[0]}x{args.size[1]} in {time.perf_counter() - t0:.1f} s",
                  file=sys.stderr)
            batch = {}
            warm = plan(data, root / "warm", args.config, args.set, args.ndisp)[:2]
            timed_batch(warm)  # numba cache / first-call costs of this process
            runs = [("inline", {}), ("pool", {"jobs": 2})]
            for label, kwargs in runs:
                seconds = timed_batch(plan(data, root / label, args.config, args.set, args.ndisp), **kwargs)
                batch[label] = {"seconds": round(seconds, 2), "pairs_per_s": round(args.pairs / seconds, 3)}
                print(label, batch[label], file=sys.stderr)
            for n in (1, 2):
                label = f"dask-{n}"
                with local_cluster(n) as cluster:
                    addr = cluster.scheduler_address
                    warm = plan(data, root / f"warm{n}", args.config, args.set, args.ndisp)[:2 * n]
                    timed_batch(warm, scheduler=addr)
                    seconds = timed_batch(plan(data, root / label, args.config, args.set, args.ndisp), scheduler=addr)
                batch[label] = {"seconds": round(seconds, 2), "pairs_per_s": round(args.pairs / seconds, 3)}
                print(label, batch[label], file=sys.stderr)
            ref = {p.relative_to(root / "inline"): p.read_bytes() for p in (root / "inline").glob("*/disp0.pfm")}
            for label in batch:
                same = all((root / label / k).read_bytes() == v for k, v in ref.items())
                batch[label]["identical_to_inline"] = same
            report["batch"] = {"pairs": args.pairs, "size": list(args.size), "ndisp": args.ndisp, **batch}

        if not args.skip_split:
            report["split"] = split_benchmark(root, args)
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")


def split_benchmark(root: Path, args) -> dict:
    """One big pair: in-process (all cores / one thread) vs strips over 2 single-thread workers."""
    from stereocli.synth.scenes import write_scene

    big = root / "big"
    write_scene(big / "pair", "curved", width=args.big[0], height=args.big[1], seed=7)
    sets = [*args.set, f"runtime.strip_rows={args.strip_rows}"]
    out: dict = {"size": list(args.big), "ndisp": args.big_ndisp, "strip_rows": args.strip_rows}
    timed_batch(plan(big, root / "bwarm", args.config, sets, args.big_ndisp))  # warm the page cache and JIT
    for label, extra in (("inprocess_all_cores", []), ("inprocess_1_thread", ["runtime.threads=1"])):
        seconds = timed_batch(plan(big, root / label, args.config, sets + extra, args.big_ndisp))
        out[label] = round(seconds, 2)
        print(label, out[label], file=sys.stderr)
    with local_cluster(2) as cluster:
        addr = cluster.scheduler_address
        timed_batch(plan(big, root / "swarm", args.config, sets, args.big_ndisp, split_strips=True), scheduler=addr)
        split = plan(big, root / "split", args.config, sets, args.big_ndisp, split_strips=True)
        seconds = timed_batch(split, scheduler=addr)
        out["split_2_workers"] = round(seconds, 2)
        seconds = timed_batch(plan(big, root / "nosplit", args.config, sets, args.big_ndisp), scheduler=addr)
        out["one_worker_no_split"] = round(seconds, 2)
    params = json.loads((root / "split" / "pair" / "params.json").read_text())
    out["strips"] = params["strips"]
    out["speedup_vs_inprocess"] = round(out["inprocess_all_cores"] / out["split_2_workers"], 2)
    out["speedup_vs_one_worker"] = round(out["one_worker_no_split"] / out["split_2_workers"], 2)
    ref = (root / "inprocess_all_cores" / "pair" / "disp0.pfm").read_bytes()
    out["identical"] = all((root / label / "pair" / "disp0.pfm").read_bytes() == ref
                           for label in ("inprocess_1_thread", "split", "nosplit"))
    print("split", out, file=sys.stderr)
    return out


if __name__ == "__main__":
    main()
