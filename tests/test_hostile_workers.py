"""Workers that fail must fail alone: a killed pool worker costs its own item only, a Dask worker
lost while running strips costs nothing, a retry avoids the worker that failed the item, a
worker whose outputs the client cannot see fails its items, and a worker running another
stereocli is refused.

Workers that see another filesystem are made honest on one machine with ``/proc/self/cwd``:
a path through it means "this process's working folder", so a worker started in another folder
sees other files at the same path, exactly as a node-local disk would.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import distributed  # the test extra installs Dask
import psutil
import pytest

from conftest import REPO, assert_clean, two_scenes
from stereocli.jobs.match import strip_task  # before match_losing_a_strip_worker replaces it

TESTS = Path(__file__).resolve().parent
N = 6
STRIPS = ["runtime.strip_rows=32", "runtime.strip_overlap=16"]
SELF_CWD = Path("/proc/self/cwd")
needs_proc_cwd = pytest.mark.skipif(not SELF_CWD.is_dir(), reason="needs /proc/self/cwd (Linux)")


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
    from stereocli.matching.config import build_config

    sets = options.pop("sets", [])
    pairs, _ = discover_pairs([str(data)])
    items = plan_items(pairs, out, config=build_config(["fast"], sets).as_dict(), ndisp=None, min_disp=None,
                       split_strips=options.pop("split_strips", False))
    for item in items:
        item.options.update(options)
    return items


def _same_maps(out: Path, reference: Path, names) -> None:
    for name in names:
        assert (out / name / "disp0.pfm").read_bytes() == (reference / name / "disp0.pfm").read_bytes(), name


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
        assert proc.poll() is None, "the batch should still be running"
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


# --- Dask: strips ---------------------------------------------------------------------------------


def match_losing_a_strip_worker(item):
    """Item function: match with its strips spread over the cluster, through
    :func:`dying_strip_task` (the item's worker records its pid for it)."""
    import stereocli.jobs.match as jobs_match

    (Path(os.environ["STRIP_MARKS"]) / "item.pid").write_text(str(os.getpid()))
    real = jobs_match.strip_task
    jobs_match.strip_task = dying_strip_task  # what cluster_strip_map sends to the cluster
    try:
        return jobs_match.match_item(item)
    finally:
        jobs_match.strip_task = real


def dying_strip_task(*args):
    """Strip task: on the item's worker, wait until another worker has died; the first strip that
    runs on another worker waits until that worker holds the only copy of its input (Dask drops
    the extra replica) and then SIGKILLs it, taking the strip and its input with it."""
    from distributed import get_worker, worker_client

    marks = Path(os.environ["STRIP_MARKS"])
    killed = marks / "killed"
    deadline = time.monotonic() + 60
    if os.getpid() == int((marks / "item.pid").read_text()):
        while not killed.exists() and time.monotonic() < deadline:  # the others steal the queued strips
            time.sleep(0.01)
    else:
        try:
            os.close(os.open(marks / "victim", os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return strip_task(*args)
        me = get_worker()
        with worker_client() as client:
            while time.monotonic() < deadline:
                if any(list(who) == [me.address] for key, who in client.who_has().items() if key in me.data):
                    break
                time.sleep(0.05)
        killed.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return strip_task(*args)


@pytest.mark.slow
def test_strips_lost_with_a_dead_worker_run_again(tmp_path, scenes):
    from stereocli.jobs.executors import run_batch
    from stereocli.jobs.match import match_item

    pair = scenes.parent / "src" / "curved"
    reference = tmp_path / "ref"
    assert run_batch(_plan(pair, reference, sets=STRIPS), match_item, progress=False).exit_code == 0
    marks = tmp_path / "marks"
    marks.mkdir()
    out = tmp_path / "out"
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40, env={"NUMBA_NUM_THREADS": "1", "STRIP_MARKS": str(marks)}) as cl:
        result = run_batch(_plan(pair, out, sets=STRIPS, split_strips=True), match_losing_a_strip_worker,
                           scheduler=cl.scheduler_address, progress=False)
    assert (marks / "killed").is_file(), "a worker running strips should have been killed"
    assert int((marks / "killed").read_text()) != int((marks / "item.pid").read_text())
    assert result.exit_code == 0, [r.message for r in result.failed]
    (res,) = result.results
    assert res.status == "ok" and res.attempts == 1 and res.details["strips"] == 3
    _same_maps(out, reference, ["curved"])
    assert_clean(out, ("curved",))


# --- Dask: workers started by the test, each in its own folder ------------------------------------


@pytest.fixture()
def scheduler():
    """A scheduler with no workers; ``start_worker`` adds them."""
    with distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None, silence_logs=40) as cluster:
        yield cluster.scheduler_address


@pytest.fixture()
def start_worker(scheduler):
    """``start_worker(name, cwd, pythonpath)``: a ``dask worker`` process (one thread) in folder
    ``cwd``; returns the addresses of the workers by name once all those started have joined."""
    started: list[subprocess.Popen] = []

    def start(name: str, cwd: Path, pythonpath: tuple = (REPO, TESTS)) -> dict[str, str]:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(map(str, pythonpath)), "NUMBA_NUM_THREADS": "1"}
        started.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", scheduler,
                                         "--name", name, "--nthreads", "1", "--no-dashboard",
                                         "--death-timeout", "60"], cwd=cwd, env=env,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        with distributed.Client(scheduler, set_as_default=False) as client:
            client.wait_for_workers(len(started), timeout=120)
            return {info["name"]: address for address, info in client.scheduler_info()["workers"].items()}

    yield start
    family = [p.pid for proc in started for p in psutil.Process(proc.pid).children(recursive=True)]
    for pid in family + [proc.pid for proc in started]:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    for proc in started:
        proc.wait()


@needs_proc_cwd
@pytest.mark.slow
def test_outputs_the_client_cannot_see_fail_their_items(tmp_path, scenes, scheduler, start_worker, monkeypatch):
    import stereocli.jobs.dask as dask_jobs
    from stereocli.jobs.executors import run_batch
    from stereocli.jobs.match import match_item

    monkeypatch.setattr(dask_jobs, "VISIBLE_SECONDS", 1)  # outputs would appear at once on this machine
    node = tmp_path / "node"
    (node / "out").mkdir(parents=True)  # the worker's own folder at the client's output path
    (tmp_path / "client").mkdir()
    monkeypatch.chdir(tmp_path / "client")
    address = start_worker("node-local", node)["node-local"]
    items = _plan(scenes, SELF_CWD / "out")
    result = run_batch(items, match_item, scheduler=scheduler, progress=False)
    assert result.exit_code == 1 and len(result.failed) == N
    for res, item in zip(result.results, items):
        assert res.message == (f"{item.name}: {item.marker}: not visible to this client although worker {address} "
                               "committed the item (Dask workers need a shared filesystem with the same paths; is the "
                               "output folder on the worker's own disk?)")
        assert (node / "out" / item.name / "disp0.pfm").is_file()  # written, where only the worker sees it
    assert_clean(tmp_path / "client" / "out")


@needs_proc_cwd
@pytest.mark.slow
def test_a_retry_avoids_the_worker_that_failed_the_item(tmp_path, scenes, scheduler, start_worker, monkeypatch):
    from stereocli.jobs.executors import run_batch
    from stereocli.jobs.match import match_item

    shutil.copytree(scenes, tmp_path / "client" / "in")
    (tmp_path / "blind").mkdir()
    monkeypatch.chdir(tmp_path / "client")
    start_worker("sees", tmp_path / "client")
    workers = start_worker("blind", tmp_path / "blind")  # no ./in: it cannot see the inputs
    out = tmp_path / "out"
    result = run_batch(_plan(SELF_CWD / "in", out), match_item, scheduler=scheduler, retries=3, progress=False)
    assert result.exit_code == 0, [r.message for r in result.failed]
    runs = {r.name: r.details.get("workers", [r.details["worker"]]) for r in result.results}
    assert any(ran[0] == workers["blind"] for ran in runs.values()), "the blind worker should have taken items"
    for res in result.results:  # at most one run on the blind worker, then the other one
        assert runs[res.name][-1] == workers["sees"] and runs[res.name].count(workers["blind"]) <= 1
        assert res.attempts == len(runs[res.name])
    assert_clean(out, tuple(f"s{i}" for i in range(N)))


def _other_stereocli(root: Path, change: str) -> Path:
    """A copy of the package with another version number, or one kernel source or one other
    source changed (the version the same)."""
    shutil.copytree(REPO / "stereocli", root / "stereocli", ignore=shutil.ignore_patterns("__pycache__", "_aot"))
    if change == "version":
        init = root / "stereocli" / "__init__.py"
        init.write_text(re.sub(r'__version__ = "[^"]*"', '__version__ = "0.0.0+other"', init.read_text()))
    else:
        changed = {"kernels": "matching/kernels/census.py", "sources": "matching/pipeline.py"}[change]
        with open(root / "stereocli" / changed, "a") as source:
            source.write("\n# changed\n")
    return root


@pytest.mark.slow
@pytest.mark.parametrize("change", ["version", "kernels", "sources"])
def test_a_worker_with_another_stereocli_is_refused(run_cli, tmp_path, scenes, scheduler, start_worker, change):
    from stereocli import __version__
    from stereocli.runtime.aot import kernel_sources_hash

    other = _other_stereocli(tmp_path / "other", change)
    address = start_worker("other", tmp_path, (other, TESTS))["other"]
    out = tmp_path / "out"
    r = run_cli("match", scenes, "-o", out, "-c", "fast", "--scheduler", scheduler)
    version = "0.0.0+other" if change == "version" else __version__
    ours = kernel_sources_hash()
    message = re.compile(rf"worker {address} runs stereocli {re.escape(version)} \(kernels (\w+), sources (\w+)\), "
                         rf"this client stereocli {__version__} \(kernels {ours}, sources (\w+)\); refused: "
                         "install the same stereocli on every worker")
    assert r.code == 2, r.err
    errors = [line for line in r.err.splitlines() if line.startswith("Error:")]
    assert len(errors) == N
    for i, line in enumerate(errors):
        found = message.fullmatch(line.removeprefix(f"Error: s{i}: "))
        assert found, line
        assert (found[1] == ours) == (change != "kernels") and found[2] != found[3]
    record = json.loads((out / "run.json").read_text())
    assert all(i["attempts"] == 0 for i in record["items"])
    assert_clean(out)


@pytest.mark.slow
def test_items_refused_by_a_worker_run_on_the_others(run_cli, tmp_path, scenes, scheduler, start_worker):
    other = _other_stereocli(tmp_path / "other", "version")
    start_worker("same", tmp_path)
    workers = start_worker("other", tmp_path, (other, TESTS))
    out = tmp_path / "out"
    r = run_cli("match", scenes, "-o", out, "-c", "fast", "--scheduler", scheduler)
    assert r.code == 0, r.err
    warnings = [line for line in r.err.splitlines() if line.startswith("Warning:")]
    assert len(warnings) == 1 and f"worker {workers['other']} runs stereocli 0.0.0+other" in warnings[0]
    assert warnings[0].endswith("its items run on the other workers")
    record = json.loads((out / "run.json").read_text())
    assert {i["details"]["worker"] for i in record["items"]} == {workers["same"]}
    assert all(i["attempts"] == 1 for i in record["items"])
    assert run_cli("match", scenes, "-o", tmp_path / "ref", "-c", "fast").code == 0
    _same_maps(out, tmp_path / "ref", [f"s{i}" for i in range(N)])
