"""``stereocli match`` end to end: outputs, batch semantics, bad inputs and exit codes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import two_scenes
from stereocli.io.images import write_image
from stereocli.io.pfm import read_pfm


@pytest.fixture(scope="module")
def small_scenes(tmp_path_factory) -> Path:
    return two_scenes(tmp_path_factory.mktemp("scenes"), 160, 120)


def test_match_writes_outputs_and_run_record(run_cli, tmp_path, small_scenes):
    out = tmp_path / "out"
    r = run_cli("match", small_scenes, "-o", out, "--png16", "256", "--npy", "--viz", "--right")
    assert r.code == 0, r.err
    for name in ("planes", "curved"):
        folder = out / name
        disp = read_pfm(folder / "disp0.pfm")
        assert disp.shape == (120, 160) and disp.dtype == np.float32
        assert np.isfinite(disp).all()  # default preset fills holes
        assert (folder / "disp0.png").is_file() and (folder / "disp0.npy").is_file()
        assert (folder / "disp0_viz.png").is_file() and (folder / "disp1.pfm").is_file()
        assert float((folder / "time.txt").read_text()) > 0
        params = json.loads((folder / "params.json").read_text())
        assert params["config"]["cost"]["name"] and params["ndisp"] > 0 and "stage_seconds" in params
        assert "compiled at install" in params["kernels"]
    record = json.loads((out / "run.json").read_text())
    assert record["summary"] == {"ok": 2, "skipped": 0, "failed": 0}
    assert record["config"]["optimizer"]["name"] and record["versions"]["numpy"]


def test_keep_invalid_leaves_holes(run_cli, tmp_path, small_scenes):
    r = run_cli("match", small_scenes / "planes", "-o", tmp_path, "--keep-invalid")
    assert r.code == 0, r.err
    disp = read_pfm(tmp_path / "planes" / "disp0.pfm")
    assert np.isinf(disp).any()  # occlusions beside the foreground box stay invalid


def test_refuses_to_overwrite_then_skip_existing(run_cli, tmp_path, small_scenes):
    out = tmp_path / "out"
    assert run_cli("match", small_scenes / "planes", "-o", out).code == 0
    r = run_cli("match", small_scenes / "planes", "-o", out)
    assert r.code == 1 and "--overwrite" in r.err and len(r.err.strip().splitlines()) == 1
    r = run_cli("match", small_scenes / "planes", "-o", out, "--skip-existing")
    assert r.code == 0 and "1 skipped" in r.err
    assert run_cli("match", small_scenes / "planes", "-o", out, "--overwrite").code == 0


def test_dry_run_writes_nothing(run_cli, tmp_path, small_scenes):
    out = tmp_path / "out"
    r = run_cli("match", small_scenes, "-o", out, "--dry-run", "--set", "cost.window=[5,5]")
    assert r.code == 0
    plan = r.json()
    assert {i["name"] for i in plan["items"]} == {"planes", "curved"}
    assert plan["config"]["cost"]["window"] == [5, 5]
    assert plan["items"][0]["outputs"]["disparity"].endswith("disp0.pfm")
    assert not out.exists()


def test_range_from_options_or_calib(run_cli, tmp_path, small_scenes):
    pair = tmp_path / "pair"
    pair.mkdir()
    shutil.copy(small_scenes / "planes" / "im0.png", pair / "l.png")
    shutil.copy(small_scenes / "planes" / "im1.png", pair / "r.png")
    # Neither an option nor a calib.txt: the range is estimated from the images.
    r = run_cli("match", pair / "l.png", pair / "r.png", "-o", tmp_path / "o")
    assert r.code == 0
    assert json.loads((tmp_path / "o" / "l" / "params.json").read_text())["range"]["source"] == "estimated"
    r = run_cli("match", pair / "l.png", pair / "r.png", "-o", tmp_path / "o2", "--ndisp", "48")
    assert r.code == 0 and (tmp_path / "o2" / "l" / "disp0.pfm").is_file()
    assert json.loads((tmp_path / "o2" / "l" / "params.json").read_text())["ndisp"] == 48


def test_bad_inputs_one_line_errors(run_cli, tmp_path, small_scenes):
    write_image(tmp_path / "a.png", np.zeros((20, 30), np.uint8))
    write_image(tmp_path / "b.png", np.zeros((20, 31), np.uint8))
    r = run_cli("match", tmp_path / "a.png", tmp_path / "b.png", "-o", tmp_path / "o", "--ndisp", "8")
    assert r.code == 1 and "differ in size" in r.err and "Traceback" not in r.err
    (tmp_path / "c.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    r = run_cli("match", tmp_path / "a.png", tmp_path / "c.png", "-o", tmp_path / "o2", "--ndisp", "8")
    assert r.code == 1 and "c.png: unreadable or truncated" in r.err and "Traceback" not in r.err
    # The views are decoded side by side: whichever is broken is the one named.
    r = run_cli("match", tmp_path / "c.png", tmp_path / "a.png", "-o", tmp_path / "o2", "--ndisp", "8")
    assert r.code == 1 and "c.png: unreadable or truncated" in r.err and "Traceback" not in r.err
    empty = tmp_path / "empty"
    empty.mkdir()
    r = run_cli("match", empty, "-o", tmp_path / "o3", "--ndisp", "8")
    assert r.code == 1 and "empty folder" in r.err
    r = run_cli("match", small_scenes, "-o", tmp_path / "o4", "--set", "cost.name=censsus")
    assert r.code == 2 and "did you mean 'census'" in r.err
    r = run_cli("match", small_scenes, "-o", tmp_path / "o5", "--set", "runtime.memory_gb=0.1",
                "--ndisp", "100000")
    assert r.code in (1, 2, 3) and "GiB" in r.err


def test_partial_batch_exits_3_and_reports_unpaired(run_cli, tmp_path, small_scenes):
    root = tmp_path / "lr"
    (root / "left").mkdir(parents=True)
    (root / "right").mkdir()
    for stem in ("a", "b"):
        shutil.copy(small_scenes / "planes" / "im0.png", root / "left" / f"{stem}.png")
    shutil.copy(small_scenes / "planes" / "im1.png", root / "right" / "a.png")
    r = run_cli("match", root, "-o", tmp_path / "o", "--ndisp", "48")
    assert r.code == 3 and "b.png: no matching right image" in r.err
    record = json.loads((tmp_path / "o" / "run.json").read_text())
    assert record["summary"]["ok"] == 1 and record["summary"]["failed"] == 1


def test_jobs_give_identical_outputs(run_cli, tmp_path, small_scenes):
    assert run_cli("match", small_scenes, "-o", tmp_path / "j1").code == 0
    assert run_cli("match", small_scenes, "-o", tmp_path / "j2", "--jobs", "2").code == 0
    for name in ("planes", "curved"):
        a = (tmp_path / "j1" / name / "disp0.pfm").read_bytes()
        b = (tmp_path / "j2" / name / "disp0.pfm").read_bytes()
        assert a == b


def test_sigkill_leaves_no_partial_output_and_resume_completes(tmp_path, small_scenes):
    data = tmp_path / "data"
    for i in range(10):
        shutil.copytree(small_scenes / ("planes" if i % 2 else "curved"), data / f"s{i:02d}")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "stereocli", "match", str(data), "-o", str(out)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, env=env)
    deadline = time.time() + 120
    while time.time() < deadline and not list(out.glob("*/time.txt")):
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = sorted(p.parent.name for p in out.glob("*/time.txt"))
    assert 0 < len(done) < 10, "the kill should land mid-batch"
    for pfm in out.glob("*/disp0.pfm"):
        assert read_pfm(pfm).shape == (120, 160)  # every file under the final name is complete
    resumed = subprocess.run(cmd + ["--skip-existing"], capture_output=True, text=True, env=env)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{len(done)} skipped" in resumed.stderr
    assert len(list(out.glob("*/time.txt"))) == 10
    assert not list(out.glob("*/.*tmp*"))
