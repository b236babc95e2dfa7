"""Workers that fail must fail alone: a killed pool worker costs its own item only."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from conftest import REPO, assert_clean, two_scenes

N = 6


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("workers")
    two_scenes(root / "src", 128, 96)
    for i in range(N):
        shutil.copytree(root / "src" / ("planes", "curved")[i % 2], root / "data" / f"s{i}")
    return root / "data"


def _plan(data: Path | str, out: Path | str, **options):
    from stereocli.io.pairs import discover_pairs
    from stereocli.jobs.match import plan_items
    from stereocli.match.config import build_config

    pairs, _ = discover_pairs([str(data)])
    items = plan_items(pairs, out, config=build_config(["fast"], []).as_dict(), ndisp=None, min_disp=None)
    for item in items:
        item.options.update(options)
    return items


# --- the process pool ----------------------------------------------------------------------------


def kill_self_once(item):
    """Item function: on its first run, s1 SIGKILLs the worker process running it."""
    from stereocli.jobs.match import match_item

    marker = Path(item.options["marker_dir"]) / f"{item.name}.killed"
    if item.name == "s1" and not marker.exists():
        marker.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return match_item(item)


@pytest.mark.slow
@pytest.mark.parametrize("retries", [0, 1])
def test_a_killed_pool_worker_fails_its_own_item_only(tmp_path, scenes, retries):
    from stereocli.jobs.executors import run_batch

    out = tmp_path / "out"
    result = run_batch(_plan(scenes, out, marker_dir=str(tmp_path)), kill_self_once, jobs=2, retries=retries,
                       progress=False)
    assert int((tmp_path / "s1.killed").read_text()) != os.getpid(), "a pool worker should have been killed"
    statuses = {r.name: (r.status, r.attempts) for r in result.results}
    others = {f"s{i}": ("ok", 1) for i in range(N) if i != 1}  # each ran once
    if retries:
        assert result.exit_code == 0 and statuses == {**others, "s1": ("ok", 2)}
        assert_clean(out, tuple(f"s{i}" for i in range(N)))
    else:
        assert result.exit_code == 3 and statuses == {**others, "s1": ("failed", 1)}
        assert result.failed[0].message == "s1: worker process died while running this item (killed by SIGKILL)"
        assert_clean(out, tuple(others))


@pytest.mark.slow
def test_a_pool_worker_killed_from_outside_costs_at_most_its_item(tmp_path):
    two_scenes(tmp_path / "src", 256, 192)
    data = tmp_path / "data"
    for i in range(10):
        shutil.copytree(tmp_path / "src" / ("planes", "curved")[i % 2], data / f"k{i}")
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "stereocli", "match", str(data), "-o", str(out), "-c", "fast",
                             "--jobs", "2"], stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and not list(out.glob("*/.stereocli-match.done")):
            time.sleep(0.01)
        workers = [p for p in psutil.Process(proc.pid).children() if "spawn_main" in " ".join(p.cmdline())]
        assert workers, "the pool should be running"
        workers[0].kill()
        err = proc.communicate(timeout=300)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
    record = json.loads((out / "run.json").read_text())
    failed = [i for i in record["items"] if i["status"] == "failed"]
    assert len(failed) <= 1 and len(record["items"]) == 10, err
    assert proc.returncode == (3 if failed else 0), err
    for item in failed:
        assert item["message"] == f"{item['name']}: worker process died while running this item (killed by SIGKILL)"
    assert all(i["attempts"] == 1 for i in record["items"])
    assert_clean(out, tuple(i["name"] for i in record["items"] if i["status"] == "ok"))
