"""``stereocli eval`` on every executor: the same report in-process, with ``--jobs 2`` and on
Dask; failures keep their messages and exit codes; retries re-run crashed scenes only."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from stereocli.evaluation import api, folders
from stereocli.io.pfm import read_pfm, write_pfm
from stereocli.jobs import evaluate as jobs_evaluate

# GT scenes: the bundled synthetic samples (Middlebury 2014 layout, every GT pixel known), plus
# a copy of "planes" named Playroom so the MiddEval3 weight 0.5 enters the average.
SCENES = {"curved": "curved", "planes": "planes", "Playroom": "planes"}
HOLE = (slice(100, 110), slice(40, 60))  # 200 invalid pixels in "curved"


@pytest.fixture(scope="module")
def gt_root(tmp_path_factory, samples) -> Path:
    root = tmp_path_factory.mktemp("gt")
    for name, src in SCENES.items():
        shutil.copytree(samples / "scenes" / src, root / name)
    return root


def write_results(out: Path, gt_root: Path, skip: tuple[str, ...] = (), bad: tuple[str, ...] = ()) -> Path:
    """Estimates with known errors: planes +0.75 px, Playroom -1.5 px, curved exact with a hole."""
    for name in SCENES:
        if name in skip:
            continue
        gt = read_pfm(gt_root / name / "disp0GT.pfm")
        if name in bad:
            est = np.ones((7, 9), np.float32)  # no 1x/2x/4x size relation to the GT: bad data
        elif name == "planes":
            est = gt + np.float32(0.75)
        elif name == "Playroom":
            est = gt - np.float32(1.5)
        else:
            est = gt.copy()
            est[HOLE] = np.inf
        write_pfm(out / name / "disp0.pfm", est.astype(np.float32))
        (out / name / "time.txt").write_text("0.5\n")
    return out


def _check_known_values(report: dict, npix: int) -> None:
    scenes = {s["name"]: s for s in report["scenes"]}
    assert [s["name"] for s in report["scenes"]] == ["Playroom", "curved", "planes"]  # GT order
    assert report["failures"] == []
    planes, playroom, curved = scenes["planes"]["all"], scenes["Playroom"]["all"], scenes["curved"]["all"]
    assert planes["bad0.5"] == 100.0 and planes["bad1.0"] == 0.0 and planes["invalid"] == 0.0
    assert planes["avgerr"] == pytest.approx(0.75, abs=1e-5)
    assert playroom["bad1.0"] == 100.0 and playroom["bad2.0"] == 0.0
    assert playroom["avgerr"] == pytest.approx(1.5, abs=1e-5)
    assert curved["invalid"] == pytest.approx(100 * 200 / npix) and curved["bad0.5"] == curved["invalid"]
    assert curved["avgerr"] == 0.0
    assert scenes["Playroom"]["weight"] == 0.5 and scenes["planes"]["time"] == 0.5
    # weighted average: (100 * 0.5 + 0 + invalid share) / 2.5 at bad1.0
    assert report["average"]["all"]["bad1.0"] == pytest.approx((0.5 * 100 + 100 * 200 / npix) / 2.5)


def _map_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*.png"))}


def test_same_report_in_process_and_with_a_process_pool(run_cli, tmp_path, gt_root):
    res = write_results(tmp_path / "res", gt_root)
    inline = run_cli("eval", res, gt_root, "--format", "json", "--error-maps", tmp_path / "m1")
    assert inline.code == 0, inline.err
    _check_known_values(inline.json(), npix=320 * 240)
    pool = run_cli("eval", res, gt_root, "--format", "json", "--error-maps", tmp_path / "m2", "--jobs", "2")
    assert pool.code == 0, pool.err
    assert pool.out == inline.out
    # keep_arrays (error maps / HTML): the scored arrays come back from the workers intact.
    maps = _map_bytes(tmp_path / "m1")
    assert len(maps) == 3 * 4 and _map_bytes(tmp_path / "m2") == maps
    text = run_cli("eval", res, gt_root)
    assert text.code == 0 and run_cli("eval", res, gt_root, "--jobs", "2").out == text.out


def test_same_report_on_a_local_dask_cluster(run_cli, tmp_path, gt_root):
    res = write_results(tmp_path / "res", gt_root)
    inline = run_cli("eval", res, gt_root, "--format", "json")
    dask = run_cli("eval", res, gt_root, "--format", "json", "--scheduler", "local", "--retries", "1")
    assert dask.code == 0, dask.err
    assert dask.out == inline.out


def test_missing_and_bad_scenes_fail_the_same_way_with_jobs(run_cli, tmp_path, gt_root):
    res = write_results(tmp_path / "res", gt_root, skip=("planes",), bad=("curved",))
    runs = [run_cli("eval", res, gt_root, "--format", "json", *extra) for extra in ((), ("--jobs", "2"))]
    for r in runs:
        assert r.code == 3
        failures = r.json()["failures"]
        assert [f["name"] for f in failures] == ["curved", "planes"]
        assert "1, 2 or 4" in failures[0]["message"] and "missing result" in failures[1]["message"]
        assert [s["name"] for s in r.json()["scenes"]] == ["Playroom"]
    assert runs[1].out == runs[0].out and runs[1].err == runs[0].err
    assert "Failed: planes: missing result" in runs[1].err
    # Nothing scored: exit 1 with the usual one-line error, whichever executor.
    nothing = write_results(tmp_path / "none", gt_root, skip=("planes",), bad=("curved", "Playroom"))
    r = run_cli("eval", nothing, gt_root, "--jobs", "2")
    assert r.code == 1 and r.err.strip().splitlines()[-1] == "Error: no scene could be scored (3 failed)"


def test_scheduler_errors_are_config_errors(run_cli, tmp_path, gt_root, monkeypatch):
    res = write_results(tmp_path / "res", gt_root)
    r = run_cli("eval", res, gt_root, "--scheduler", "not an address")
    assert r.code == 2 and "tcp://host:port" in r.err and not r.out
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask were not installed
    for args in ((res, gt_root), (res / "planes" / "disp0.pfm", gt_root / "planes")):  # folder and pair mode
        r = run_cli("eval", *args, "--scheduler", "local")
        assert r.code == 2 and 'pip install "stereocli[dask]"' in r.err, r.err
        assert len(r.err.strip().splitlines()) == 1 and not r.out


def test_retries_rerun_crashed_scenes_only(tmp_path, gt_root, monkeypatch):
    res = write_results(tmp_path / "res", gt_root, bad=("Playroom",))
    reference = api.evaluate(res, gt_root).as_dict()
    calls: dict[str, int] = {}
    real = folders.evaluate_pair

    def flaky(estimate, scene, **kwargs):
        name = kwargs["name"]
        calls[name] = calls.get(name, 0) + 1
        if name == "curved" and calls[name] == 1:
            raise RuntimeError("transient crash")
        return real(estimate, scene, **kwargs)

    monkeypatch.setattr(folders, "evaluate_pair", flaky)
    report = jobs_evaluate.evaluate(res, gt_root, retries=2, progress=False)
    assert report.as_dict() == reference and report.exit_code == 3
    # curved crashed once and was re-run; Playroom's bad data is a result, not a crash: run once.
    assert calls == {"Playroom": 1, "curved": 2, "planes": 1}
    calls.clear()
    report = jobs_evaluate.evaluate(res, gt_root, progress=False)  # no retries: the crash is a scene failure
    assert [f["name"] for f in report.failures] == ["Playroom", "curved"]
    assert report.failures[1]["message"] == "RuntimeError: transient crash"
    assert [s.name for s in report.scenes] == ["planes"] and report.exit_code == 3
