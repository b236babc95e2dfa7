"""Executors: the same batch inline, in a process pool and on Dask gives the same bytes; a
worker killed mid-item is survived; retries, resume, partial failure and a missing Dask."""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import distributed  # the test extra installs Dask
import numpy as np
import pytest

from stereocli.io.images import write_image
from stereocli.io.pfm import read_pfm
from stereocli.jobs.executors import run_batch
from stereocli.synth.scenes import write_scene

# Data outputs that must be byte-identical (time.txt and params.json hold timings).
DATA_FILES = ("disp0.pfm", "disp0.png", "disp1.pfm")
FAST = ("-c", "fast")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("scenes")
    for i in range(4):
        write_scene(root / f"s{i}", ("planes", "curved")[i % 2], width=128, height=96, seed=i)
    return root


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded worker processes, started once for the module."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40, env={"NUMBA_NUM_THREADS": "1"}) as cl:
        yield cl


def _data_bytes(out: Path) -> dict[str, bytes]:
    files = {}
    for name in DATA_FILES:
        for path in sorted(out.glob(f"*/{name}")):
            files[str(path.relative_to(out))] = path.read_bytes()
    return files


def _no_temporaries(out: Path) -> None:
    assert not [p for p in out.rglob(".*") if "tmp" in p.name]


def test_inline_process_pool_and_dask_give_identical_bytes(run_cli, tmp_path, scenes):
    args = (*FAST, "--png16", "256", "--right")
    outs = {}
    for label, extra in (("inline", ()), ("pool", ("--jobs", "2")), ("dask", ("--scheduler", "local"))):
        out = tmp_path / label
        r = run_cli("match", scenes, "-o", out, *args, *extra)
        assert r.code == 0, r.err
        outs[label] = _data_bytes(out)
        _no_temporaries(out)
    assert len(outs["inline"]) == 4 * len(DATA_FILES)
    assert outs["pool"] == outs["inline"]
    assert outs["dask"] == outs["inline"]
    record = json.loads((tmp_path / "dask" / "run.json").read_text())
    assert record["summary"] == {"ok": 4, "skipped": 0, "failed": 0}
    assert all(item["details"]["worker"].startswith("tcp://") for item in record["items"])


def test_remote_scheduler_resume_and_partial_failure(run_cli, tmp_path, scenes, cluster):
    addr = cluster.scheduler_address
    out = tmp_path / "out"
    r = run_cli("match", scenes / "s0", scenes / "s1", "-o", out, *FAST, "--scheduler", addr)
    assert r.code == 0, r.err
    r = run_cli("match", scenes, "-o", out, *FAST, "--scheduler", addr, "--skip-existing")
    assert r.code == 0 and "2 ok, 2 skipped, 0 failed" in r.err
    # One pair whose views differ in size: that item fails, the others succeed -> exit 3.
    bad = tmp_path / "bad"
    bad.mkdir()
    write_image(bad / "im0.png", np.zeros((20, 30), np.uint8))
    write_image(bad / "im1.png", np.zeros((20, 31), np.uint8))
    r = run_cli("match", scenes / "s2", bad, "-o", tmp_path / "o2", *FAST, "--ndisp", "16",
                "--scheduler", addr, "--retries", "1")
    assert r.code == 3 and "differ in size" in r.err
    items = {i["name"]: i for i in json.loads((tmp_path / "o2" / "run.json").read_text())["items"]}
    assert items["bad"]["status"] == "failed" and items["bad"]["attempts"] == 2
    assert items["s2"]["status"] == "ok" and items["s2"]["attempts"] == 1


def _plan(scenes: Path, out: Path, **marks):
    from stereocli.io.pairs import discover_pairs
    from stereocli.jobs.match import plan_items
    from stereocli.matching.config import build_config

    pairs, _ = discover_pairs([str(scenes)])
    items = plan_items(pairs, out, config=build_config(["fast"], []).as_dict(), ndisp=None, min_disp=None, right=True)
    for item in items:
        item.options.update(marks)
    return items


def kill_worker_once(item):
    """Item function: on the first attempt for s1, leave a half-written temporary beside the
    outputs and SIGKILL the worker process running it (as the OOM killer would)."""
    from stereocli.jobs.match import match_item

    marker = Path(item.options["marker_dir"]) / f"{item.name}.killed"
    if item.name == "s1" and not marker.exists():
        marker.write_text(str(os.getpid()))
        folder = Path(item.outputs["disparity"]).parent
        folder.mkdir(parents=True, exist_ok=True)
        (folder / ".disp0.deadbeef.tmp.pfm").write_bytes(b"Pf\n128 96\n-1\n" + b"\0" * 1000)
        os.kill(os.getpid(), signal.SIGKILL)
    return match_item(item)


def fail_once(item):
    """Item function: raise on the first attempt for s2 (a transient error), then match."""
    from stereocli.jobs.match import match_item

    marker = Path(item.options["marker_dir"]) / f"{item.name}.failed"
    if item.name == "s2" and not marker.exists():
        marker.write_text("1")
        raise OSError("transient network filesystem error")
    return match_item(item)


def test_worker_killed_mid_item_is_retried_and_nothing_partial_remains(tmp_path, scenes, cluster):
    from stereocli.jobs.match import match_item

    ref = tmp_path / "ref"
    assert run_batch(_plan(scenes, ref), match_item).exit_code == 0
    out = tmp_path / "out"
    with distributed.Client(cluster, set_as_default=False) as client:
        before = set(client.scheduler_info()["workers"])
    result = run_batch(_plan(scenes, out, marker_dir=str(tmp_path)), kill_worker_once,
                       scheduler=cluster.scheduler_address, progress=False)
    assert (tmp_path / "s1.killed").is_file(), "the worker should have been killed"
    assert int((tmp_path / "s1.killed").read_text()) != os.getpid()
    assert result.exit_code == 0, [r.message for r in result.failed]
    assert [r.name for r in result.results] == ["s0", "s1", "s2", "s3"]  # each recorded once, in order
    assert all(r.status == "ok" for r in result.results)
    # Dask ran s1 again on another worker: both runs count.
    assert {r.name: r.attempts for r in result.results} == {"s0": 1, "s1": 2, "s2": 1, "s3": 1}
    _no_temporaries(out)
    assert _data_bytes(out) == _data_bytes(ref)
    for pfm in out.glob("*/disp0.pfm"):
        assert read_pfm(pfm).shape == (96, 128)
    # The nanny restarts the killed worker process: the cluster is whole again for later tests.
    with distributed.Client(cluster, set_as_default=False) as client:
        client.wait_for_workers(2, timeout=60)
        assert set(client.scheduler_info()["workers"]) != before


def test_worker_process_killed_from_outside_mid_batch(run_cli, tmp_path, cluster):
    """SIGKILL a worker process (found with client.run(os.getpid)) while it matches a pair."""
    src = tmp_path / "src"
    for i, name in enumerate(("planes", "curved")):
        write_scene(src / name, name, width=384, height=288, seed=10 + i)
    data = tmp_path / "data"
    for i in range(8):
        shutil.copytree(src / ("planes", "curved")[i % 2], data / f"k{i}")
    out = tmp_path / "out"
    killed = []

    def killer():
        with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
            pids = client.run(os.getpid)
            deadline = time.time() + 60
            while time.time() < deadline and not list(out.glob("*/time.txt")):
                time.sleep(0.01)
            busy = [w for w, tasks in client.processing().items() if tasks and w in pids]
            if busy:
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed.append(len(list(out.glob("*/time.txt"))))

    thread = threading.Thread(target=killer)
    thread.start()
    r = run_cli("match", data, "-o", out, *FAST, "--scheduler", cluster.scheduler_address)
    thread.join()
    assert killed and killed[0] < 8, "the kill should land mid-batch"
    assert r.code == 0 and "8 ok, 0 skipped, 0 failed" in r.err, r.err
    _no_temporaries(out)
    assert run_cli("match", src, "-o", tmp_path / "ref", *FAST).code == 0
    for i in range(8):
        ref = tmp_path / "ref" / ("planes", "curved")[i % 2] / "disp0.pfm"
        assert (out / f"k{i}" / "disp0.pfm").read_bytes() == ref.read_bytes()
    with distributed.Client(cluster, set_as_default=False) as client:
        client.wait_for_workers(2, timeout=60)


def test_failed_item_is_retried_on_every_executor(tmp_path, scenes, cluster):
    for label, kwargs in (("inline", {}), ("dask", {"scheduler": cluster.scheduler_address})):
        marks = tmp_path / f"marks_{label}"
        marks.mkdir()
        out = tmp_path / label
        result = run_batch(_plan(scenes, out, marker_dir=str(marks)), fail_once, retries=1, progress=False, **kwargs)
        by_name = {r.name: r for r in result.results}
        assert result.exit_code == 0 and by_name["s2"].attempts == 2 and by_name["s0"].attempts == 1, label
        # Without retries the transient failure stays a failure (exit 3) and nothing partial remains.
        out2 = tmp_path / f"{label}_noretry"
        marks2 = tmp_path / f"marks2_{label}"
        marks2.mkdir()
        result = run_batch(_plan(scenes, out2, marker_dir=str(marks2)), fail_once, progress=False, **kwargs)
        assert result.exit_code == 3 and [r.name for r in result.failed] == ["s2"]
        assert "transient" in result.failed[0].message
        _no_temporaries(out2)
