"""Signals: SIGINT (to the process group or the parent) and SIGTERM stop a batch on every
executor: exit 130/143, ``run.json`` with the finished items and ``"interrupted": true``, no
partial output, no orphan worker; ``--skip-existing`` then resumes exactly. A parent killed
with SIGKILL takes its pool workers with it."""

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

N = 16
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("interrupts")
    two_scenes(root / "src", 256, 192)
    for i in range(N):
        shutil.copytree(root / "src" / ("planes", "curved")[i % 2], root / "data" / f"s{i:02d}")
    return root / "data"


def _done(out: Path) -> list[str]:
    return sorted(p.parent.name for p in out.glob("*/.stereocli-match.done"))


def _start(data: Path, out: Path, *extra: str) -> tuple[subprocess.Popen, list[psutil.Process]]:
    """Start a batch in its own process group; return it and its worker processes once the
    first pair is committed."""
    proc = subprocess.Popen([sys.executable, "-m", "stereocli", "match", str(data), "-o", str(out), *extra],
                            stderr=subprocess.PIPE, text=True, env=ENV, start_new_session=True)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and not _done(out) and proc.poll() is None:
        time.sleep(0.01)
    children = psutil.Process(proc.pid).children(recursive=True) if proc.poll() is None else []
    return proc, children


def _gone(processes: list[psutil.Process], within: float = 10) -> bool:
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        if not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in processes):
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("executor,sig,target", [
    pytest.param(executor, sig, target, id=f"{executor}-{sig.name}-{target}") for executor, sig, target in (
        ("inline", signal.SIGINT, "group"),
        ("pool", signal.SIGINT, "group"),
        ("pool", signal.SIGTERM, "parent"),
        ("dask", signal.SIGINT, "group"),
        ("dask", signal.SIGTERM, "parent"),
    )])
def test_a_signal_stops_the_batch_and_resume_is_exact(run_cli, tmp_path, data, executor, sig, target):
    out = tmp_path / "out"
    extra = {"inline": (), "pool": ("--jobs", "2"), "dask": ("--scheduler", "local")}[executor]
    proc, workers = _start(data, out, *extra)
    assert proc.poll() is None, "the batch should still be running"
    sent = time.monotonic()
    if target == "group":
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    err = proc.communicate(timeout=30)[1]
    assert time.monotonic() - sent < 10
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert f"Interrupted ({signal.Signals(sig).name})" in err
    assert _gone(workers), "worker processes outlived the batch"
    record = json.loads((out / "run.json").read_text())
    assert record["interrupted"] is True and record["signal"] == signal.Signals(sig).name and record["planned"] == N
    done = _done(out)
    assert 0 < len(done) < N
    assert {i["name"] for i in record["items"] if i["status"] == "ok"} <= set(done)
    assert all(i["status"] == "ok" for i in record["items"])
    assert_clean(out, tuple(done))
    resumed = run_cli("match", data, "-o", out, "--skip-existing")
    assert resumed.code == 0 and f"{N - len(done)} ok, {len(done)} skipped, 0 failed" in resumed.err
    assert len(_done(out)) == N


def test_pool_workers_exit_when_the_parent_is_killed(tmp_path, data):
    out = tmp_path / "out"
    proc, workers = _start(data, out, "--jobs", "2")
    assert proc.poll() is None and workers
    proc.kill()
    proc.wait()
    assert _gone(workers), "pool workers outlived their killed parent"


def test_the_run_record_covers_the_batch(run_cli, tmp_path, data):
    out = tmp_path / "out"
    r = run_cli("match", data / "s00", data / "s01", "-o", out, "-c", "fast")
    assert r.code == 0, r.err
    record = json.loads((out / "run.json").read_text())
    items = record["items"]
    assert record["interrupted"] is False
    assert record["seconds"] >= sum(i["seconds"] for i in items)
    for item in items:  # time.txt is the matching time, a part of the item's own time
        matching = float((out / item["name"] / "time.txt").read_text())
        assert 0 < matching <= item["seconds"] and matching == pytest.approx(item["details"]["seconds"], abs=1e-4)


def _interrupted_in_a_kernel(item):
    """Item function: what CPython makes of a signal handler raising while a compiled kernel
    returns (a SystemError with the interrupt as its context)."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt:
        # no `from`: CPython makes the interrupt the context, not the cause
        raise SystemError("CPUDispatcher(<function kernel>) returned a result with an exception set")  # noqa: B904


def test_an_interrupt_inside_a_kernel_stops_the_batch_not_just_the_item(tmp_path):
    from stereocli.jobs.executors import run_batch
    from stereocli.jobs.items import WorkItem

    items = [WorkItem(f"p{i}", {}, {"a": str(tmp_path / "out" / f"p{i}" / "a.txt")},
                      folder=str(tmp_path / "out" / f"p{i}"), command="test") for i in range(3)]
    result = run_batch(items, _interrupted_in_a_kernel, progress=False)
    assert result.interrupted == signal.SIGINT and result.exit_code == 130 and result.results == []
    assert not list((tmp_path / "out").rglob("*"))
