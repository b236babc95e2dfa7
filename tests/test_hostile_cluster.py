"""Cluster faults: addresses that are not a Dask scheduler, a scheduler killed mid-batch (with
and without retries), relative paths sent to workers that run elsewhere, a worker that cannot
see a path. Each ends with a clear exit code and one-line messages, never a hang."""

from __future__ import annotations

import http.server
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import distributed  # the test extra installs Dask
import psutil
import pytest

from conftest import REPO, assert_clean, two_scenes

FAST = ("-c", "fast")
CLUSTER = """
import sys, time, distributed
if __name__ == "__main__":
    cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                       silence_logs=40, env={"NUMBA_NUM_THREADS": "1"})
    print(cluster.scheduler_address, flush=True)
    time.sleep(600)
"""


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cluster")
    two_scenes(root / "src", 192, 144)
    for i in range(10):
        shutil.copytree(root / "src" / ("planes", "curved")[i % 2], root / "data" / f"s{i}")
    return root / "data"


@pytest.fixture()
def remote_cluster(tmp_path):
    """A LocalCluster (scheduler + one worker process) in a separate process started in another
    folder: killing that process kills the scheduler."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", CLUSTER], cwd=elsewhere, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    address = proc.stdout.readline().strip()
    assert address.startswith("tcp://")
    family = [proc.pid] + [c.pid for c in psutil.Process(proc.pid).children(recursive=True)]
    yield proc, address, elsewhere
    for pid in family:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def test_an_http_server_is_not_a_scheduler(run_cli, tmp_path, data, monkeypatch):
    import stereocli.jobs.dask as dask_jobs

    monkeypatch.setattr(dask_jobs, "CONNECT_SECONDS", 3)  # the default 10 s, shortened for the test
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _QuietHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        t0 = time.monotonic()
        r = run_cli("match", data / "s0", "-o", tmp_path / "out", *FAST,
                    "--scheduler", f"tcp://127.0.0.1:{server.server_address[1]}")
        assert time.monotonic() - t0 < 20
    finally:
        server.shutdown()
    assert r.code == 2 and "Dask scheduler" in r.err and len(r.err.strip().splitlines()) == 1, r.err
    assert not (tmp_path / "out").exists()


def test_an_unknown_protocol_fails_at_once(run_cli, tmp_path, data):
    r = run_cli("match", data / "s0", "-o", tmp_path / "out", *FAST, "--scheduler", "udp://127.0.0.1:8786")
    assert r.code == 2 and "no 'udp' protocol" in r.err and len(r.err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_relative_paths_reach_workers_started_elsewhere(run_cli, tmp_path, data, remote_cluster, monkeypatch):
    _, address, elsewhere = remote_cluster
    shutil.copytree(data / "s0", tmp_path / "in" / "s0")
    shutil.copytree(data / "s1", elsewhere / "in" / "s0")  # a same-named decoy beside the worker
    monkeypatch.chdir(tmp_path)
    r = run_cli("match", "in", "-o", "out", *FAST, "--scheduler", address)
    assert r.code == 0, r.err
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    assert record["items"][0]["inputs"]["left"] == str(tmp_path / "in" / "s0" / "im0.png")
    assert not (elsewhere / "out").exists()
    reference = run_cli("match", tmp_path / "in", "-o", tmp_path / "ref", *FAST)
    assert reference.code == 0
    assert (tmp_path / "out" / "s0" / "disp0.pfm").read_bytes() == (tmp_path / "ref" / "s0" / "disp0.pfm").read_bytes()


@pytest.mark.parametrize("retries", ["0", "2"])
def test_a_killed_scheduler_ends_the_run_with_the_finished_items(run_cli, tmp_path, data, remote_cluster, retries):
    proc, address, _ = remote_cluster
    out = tmp_path / "out"
    killed = []

    def kill_scheduler_after_the_first_pair():
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not list(out.glob("*/.stereocli-match.done")):
            time.sleep(0.01)
        proc.kill()
        killed.append(time.monotonic())

    killer = threading.Thread(target=kill_scheduler_after_the_first_pair)
    killer.start()
    r = run_cli("match", data, "-o", out, "-c", "default", "--scheduler", address, "--retries", retries)
    killer.join()
    assert killed and time.monotonic() - killed[0] < 30  # no hang
    assert r.code == 3, r.err
    assert "Traceback" not in r.err
    record = json.loads((out / "run.json").read_text())
    done = sorted(p.parent.name for p in out.glob("*/.stereocli-match.done"))
    by_status = {s: sorted(i["name"] for i in record["items"] if i["status"] == s) for s in ("ok", "failed")}
    assert by_status["ok"] == done and 0 < len(done) < 10
    assert len(by_status["failed"]) == 10 - len(done)
    assert all(f"Error: {name}: the Dask scheduler was lost" in r.err for name in by_status["failed"])
    assert_clean(out, tuple(done))
    resumed = run_cli("match", data, "-o", out, "-c", "default", "--skip-existing")
    assert resumed.code == 0 and f"{10 - len(done)} ok, {len(done)} skipped" in resumed.err


def test_a_worker_that_cannot_see_a_path_fails_that_item(tmp_path, data):
    from stereocli.io.pairs import discover_pairs
    from stereocli.jobs.executors import run_batch
    from stereocli.jobs.match import match_item, plan_items
    from stereocli.matching.config import build_config

    shutil.copytree(data / "s0", tmp_path / "in" / "s0")
    shutil.copytree(data / "s1", tmp_path / "in" / "s1")
    pairs, _ = discover_pairs([str(tmp_path / "in")])
    items = plan_items(pairs, tmp_path / "out", config=build_config(["fast"], []).as_dict(), ndisp=None,
                       min_disp=None)
    (tmp_path / "in" / "s1" / "im1.png").unlink()  # seen when planned, gone for the workers
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster:
        result = run_batch(items, match_item, scheduler=cluster.scheduler_address, progress=False)
    assert result.exit_code == 3
    failed = result.failed[0]
    assert failed.name == "s1" and "im1.png: not found on worker tcp://" in failed.message
    assert "shared filesystem" in failed.message
    assert_clean(tmp_path / "out", ("s0",))
