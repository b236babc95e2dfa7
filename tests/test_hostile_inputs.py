"""A corpus of bad and hostile inputs, one case per defect kind: each gives its exit code, a
one-line message naming the item, file or key, no traceback, and nothing partial on disk.

Kinds: wrong output reported as success, values that pass range checks (NaN, inf), hostile
YAML, one bad scene in a batch, exit codes, outputs of a failed pair, two runs into one folder,
torn overwrites (SIGKILL mid-commit), unlabelled third-party noise. Cluster faults and signals
are in ``test_hostile_cluster.py`` and ``test_interrupts.py``.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from conftest import REPO, assert_clean, two_scenes
from stereocli.io.images import write_image
from stereocli.io.pfm import read_pfm, write_pfm

FAST = ("-c", "fast")
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    return two_scenes(tmp_path_factory.mktemp("scenes"), 128, 96)


def copy_scenes(scenes: Path, dest: Path, edit: dict[str, Callable[[Path], None]] | None = None) -> Path:
    shutil.copytree(scenes, dest)
    for name, fn in (edit or {}).items():
        fn(dest / name)
    return dest


def calib_line(key: str, value: str) -> Callable[[Path], None]:
    def edit(folder: Path) -> None:
        lines = [ln for ln in (folder / "calib.txt").read_text().splitlines() if not ln.startswith(f"{key}=")]
        (folder / "calib.txt").write_text("\n".join(lines + [f"{key}={value}"]) + "\n")

    return edit


def billion_laughs(path: Path) -> Path:
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for prev, cur in zip("abcdefgh", "bcdefghi"):
        lines.append(f"{cur}: &{cur} [{','.join([f'*{prev}'] * 9)}]")
    path.write_text("\n".join(lines) + "\n")
    return path


def gt_without_pixels(scenes: Path, dest: Path) -> Path:
    copy_scenes(scenes, dest)
    write_pfm(dest / "curved" / "disp0GT.pfm", np.full((96, 128), np.inf, np.float32))
    return dest


@dataclass
class Case:
    """``build(tmp, scenes) -> (argv, output folder, folders expected complete)``."""

    id: str
    kind: str
    build: Callable
    code: int
    message: str


def _match(*extra, inputs=None):
    def build(tmp, scenes):
        return ["match", inputs(tmp, scenes) if inputs else scenes, "-o", tmp / "out", *FAST, *extra], tmp / "out", ()

    return build


def _with_result(cmd):
    """A command reading a matched ``res/`` folder (matched once per test, in-process)."""
    def build(tmp, scenes):
        return cmd(tmp, scenes), tmp / "out", ()

    build.needs_results = True
    return build


CASES = [
    # -- wrong output reported as success
    Case("png16-negative", "wrong output, exit 0", _match("--png16", "-256"), 2, "--png16"),
    Case("png16-nan", "wrong output, exit 0", _match("--png16", "nan"), 2, "not a finite number"),
    Case("png16-huge", "wrong output, exit 0", _match("--png16", "1e30"), 2, "--png16"),
    Case("triangulate-min-depth-nan", "wrong output, exit 0",
         _with_result(lambda t, s: ["triangulate", t / "res", "--scenes", s, "-o", t / "out", "--min-depth", "nan"]),
         2, "--min-depth"),
    Case("eval-gt-scale-inf", "wrong output, exit 0",
         _with_result(lambda t, s: ["eval", t / "res", s, "--gt-scale", "inf"]), 2, "--gt-scale"),
    Case("eval-gt-no-finite-pixel", "wrong output, exit 0",
         _with_result(lambda t, s: ["eval", t / "res" / "curved" / "disp0.pfm",
                                    gt_without_pixels(s, t / "gt") / "curved"]),
         1, "no pixel of the ground truth is known"),
    Case("calib-vmin-nan", "wrong output, exit 0",
         _match("--viz", inputs=lambda t, s: copy_scenes(s, t / "in", {"curved": calib_line("vmin", "nan")})),
         3, "vmin='nan' is not a finite number"),
    Case("calib-focal-zero", "wrong output, exit 0",
         _with_result(lambda t, s: ["triangulate", t / "res", "-o", t / "out", "--scenes",
                                    copy_scenes(s, t / "in", {"curved": calib_line("cam0", "[0 0 0; 0 0 0; 0 0 1]")})]),
         3, "cam0 is no camera matrix"),
    # -- values that pass the range checks
    Case("set-nan", "NaN passes range checks", _match("--set", "optimizer.p2=.nan"), 2, "optimizer.p2"),
    Case("set-inf-budget", "NaN passes range checks", _match("--set", "runtime.memory_gb=.inf"), 2,
         "runtime.memory_gb"),
    Case("config-show-nan", "NaN passes range checks",
         lambda t, s: (["config", "show", "--set", "optimizer.p2=.nan"], t / "out", ()), 2, "finite number"),
    Case("calib-ndisp-inf", "NaN passes range checks",
         _match(inputs=lambda t, s: copy_scenes(s, t / "in", {"curved": calib_line("ndisp", "inf")})), 3,
         "ndisp='inf' is not a finite number"),
    # -- hostile YAML
    Case("yaml-billion-laughs", "hostile YAML",
         lambda t, s: (["match", s, "-o", t / "out", "-c", billion_laughs(t / "laughs.yaml")], t / "out", ()), 2,
         "aliases are expanded"),
    Case("yaml-deep-brackets", "hostile YAML",
         lambda t, s: (["config", "show", "-c", _write(t / "deep.yaml", "cost: " + "[" * 100_000 + "]" * 100_000)],
                       t / "out", ()), 2, "nested deeper"),
    Case("set-deep-brackets", "hostile YAML", _match("--set", "cost.window=" + "[" * 100_000), 2, "nested deeper"),
    Case("yaml-huge", "hostile YAML",
         lambda t, s: (["config", "show", "-c", _write(t / "big.yaml", "# x\n" * 300_000)], t / "out", ()), 2,
         "at most 256 KiB"),
    # -- one bad scene sinks the batch
    Case("calib-ndisp-lots", "one bad scene",
         _match(inputs=lambda t, s: copy_scenes(s, t / "in", {"curved": calib_line("ndisp", "lots")})), 3,
         "curved: "),
    # -- wrong exit codes
    Case("memory-refusal", "exit codes", _match("--ndisp", "60000", "--set", "runtime.memory_gb=0.1"), 2,
         "GiB even in row strips"),
    Case("sgm-ndisp-limit", "exit codes", _match("--ndisp", "70000", "-c", "fast"), 2,
         "at most 65535 disparities"),
    Case("charuco-dictionary", "exit codes",
         lambda t, s: (["calibrate", _blank_pairs(t / "cal"), "-o", t / "out" / "rig.yml", "--pattern", "5x4",
                        "--pattern-type", "charuco", "--dictionary", "DICT_BOGUS"], t / "out", ()), 2,
         "unknown ArUco dictionary"),
    Case("garbled-detection-cache", "exit codes",
         lambda t, s: (["calibrate", _garbled_cache(_blank_pairs(t / "cal")), "-o", t / "out" / "rig.yml",
                        "--pattern", "9x6"], t / "out", ()), 1, "not found in any of the 4 images"),
    # -- outputs of a failed pair left under final names
    Case("confidence-without-stage", "failed pair's outputs", _match("--confidence"), 2, "no confidence map"),
    # -- two runs into one output folder
    Case("lock-held-by-live-run", "two runs, one folder",
         lambda t, s: (["match", s, "-o", _locked(t / "out", os.getppid(), socket.gethostname()), *FAST],
                       t / "out", ()), 1, "in use by another run"),
    Case("lock-held-on-another-host", "two runs, one folder",
         lambda t, s: (["match", s, "-o", _locked(t / "out", 1, "elsewhere.example"), *FAST], t / "out", ()), 1,
         "elsewhere.example"),
]


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _blank_pairs(folder: Path) -> Path:
    for side in ("left", "right"):
        (folder / side).mkdir(parents=True)
        for i in range(2):
            write_image(folder / side / f"{i:02d}.png", np.full((60, 80), 128, np.uint8))
    return folder


def _garbled_cache(folder: Path) -> Path:
    from stereocli.calib.detect import CACHE_VERSION, cache_key
    from stereocli.calib.pattern import Pattern

    keys = [cache_key(p, Pattern(9, 6), "auto") for p in sorted(folder.glob("*/*.png"))]
    entries = {keys[0]: {"size": 5, "corners": "x"}, keys[1]: "junk", keys[2]: {"corners": [[1, 2, 3]]}}
    cache = folder.parent / "out" / ".stereocli-detections.json"
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps({"version": CACHE_VERSION, "entries": entries}))
    return folder


def _locked(out: Path, pid: int, host: str) -> Path:
    out.mkdir(parents=True)
    (out / ".stereocli.lock").write_text(json.dumps({"pid": pid, "host": host, "started": "2030-01-01T00:00:00"}))
    return out


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_hostile_input(case: Case, run_cli, tmp_path, scenes):
    if getattr(case.build, "needs_results", False):
        assert run_cli("match", scenes, "-o", tmp_path / "res", *FAST, "-q").code == 0
    argv, out, complete = case.build(tmp_path, scenes)
    t0 = time.monotonic()
    r = run_cli(*argv)
    assert time.monotonic() - t0 < 60
    assert r.code == case.code, r.err
    assert case.message in r.err, r.err
    assert "Traceback" not in r.err
    errors = [line for line in r.err.splitlines() if line.startswith("Error")]
    assert errors and all(len(e) < 400 for e in errors), r.err
    if case.code == 3:  # a batch: the good scene is matched and recorded, the bad one is not on disk
        record = json.loads((out / "run.json").read_text())
        assert record["summary"] == {"ok": 1, "skipped": 0, "failed": 1}
        assert {i["name"]: i["status"] for i in record["items"]} == {"planes": "ok", "curved": "failed"}
        assert "curved: " in r.err and "Error: curved: " in r.err
        complete = ("planes",)
    if case.id == "garbled-detection-cache":
        assert "TypeError" not in r.err
    if case.id.startswith("lock-"):
        assert (out / ".stereocli.lock").is_file()  # the other run's lock is left alone
        (out / ".stereocli.lock").unlink()
    if argv[0] in ("match", "rectify", "triangulate"):
        assert_clean(out, complete)
    elif argv[0] == "calibrate":
        assert not (out / "rig.yml").exists() and not list(out.glob("rig*"))


def test_garbled_detection_cache_is_replaced(run_cli, tmp_path):
    folder = _garbled_cache(_blank_pairs(tmp_path / "cal"))
    r = run_cli("calibrate", folder, "-o", tmp_path / "out" / "rig.yml", "--pattern", "9x6")
    assert r.code == 1 and "TypeError" not in r.err
    cache = json.loads((tmp_path / "out" / ".stereocli-detections.json").read_text())
    assert all(isinstance(e, dict) and e["size"] == [80, 60] for e in cache["entries"].values())


def test_stale_lock_is_taken_over(run_cli, tmp_path, scenes):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = _locked(tmp_path / "out", dead.pid, socket.gethostname())
    r = run_cli("match", scenes, "-o", out, *FAST)
    assert r.code == 0, r.err
    assert_clean(out, ("planes", "curved"))


def test_png16_scale_no_pixel_fits_fails_the_pair(tmp_path):
    from stereocli.errors import DataError
    from stereocli.io.images import write_disparity_png16

    with pytest.raises(DataError, match="no valid disparity fits"):
        write_disparity_png16(tmp_path / "d.png", np.full((4, 4), 30.0, np.float32), 60000)
    assert not list(tmp_path.iterdir())


def _writes_then_fails(item):
    """Item function: writes its first output, then fails (a crash after a partial write)."""
    Path(item.outputs["a"]).write_text("new")
    raise RuntimeError("crashed after writing a.txt")


def test_a_failed_item_leaves_its_previous_outputs_untouched(tmp_path):
    from stereocli.jobs.executors import run_batch
    from stereocli.jobs.items import WorkItem

    folder = tmp_path / "out" / "p"
    item = WorkItem("p", {}, {"a": str(folder / "a.txt"), "b": str(folder / "b.txt")}, folder=str(folder),
                    command="test")
    result = run_batch([item], _writes_then_fails, overwrite=True, progress=False)
    assert result.exit_code == 1 and "p: RuntimeError: crashed after writing a.txt" in result.results[0].message
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


# -- torn overwrites: SIGKILL at chosen points of a commit ----------------------------------------

KILL_AT = r"""
import os, signal, sys
import stereocli.jobs.items as items
point = os.environ["KILL_AT"]
real_rename, real_replace = os.rename, os.replace
def rename(src, dst, *a, **k):
    real_rename(src, dst, *a, **k)
    if point == "swap" and str(dst).endswith(".old"):
        os.kill(os.getpid(), signal.SIGKILL)  # between moving the old folder aside and the new one in
def replace(src, dst, *a, **k):
    real_replace(src, dst, *a, **k)
    if point == "shared" and ".stage" in str(src) and ".stage" not in str(dst) and str(dst).endswith(".pfm"):
        os.kill(os.getpid(), signal.SIGKILL)  # after the first output replaced in a shared folder
    if point == "staging" and ".stage" in str(dst) and str(dst).endswith("disp0.pfm"):
        os.kill(os.getpid(), signal.SIGKILL)  # the new map is written, nothing committed yet
items.os.rename, items.os.replace = rename, replace
import stereocli.io.atomic as atomic
atomic.os.replace = replace
from stereocli.cli.main import main
main()
"""


def _stereocli(*args, kill_at: str | None = None) -> subprocess.CompletedProcess:
    env = {**ENV, "KILL_AT": kill_at or ""}
    code = KILL_AT if kill_at else "from stereocli.cli.main import main; main()"
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, env=env,
                          timeout=120)


@pytest.mark.parametrize("point", ["staging", "swap", "shared"])
def test_sigkill_mid_overwrite_never_leaves_a_torn_pair(run_cli, tmp_path, scenes, point):
    data = tmp_path / "data"
    shutil.copytree(scenes / "planes", data / "planes")
    out = tmp_path / "out"
    if point == "shared":  # the pair folder holds another file: outputs are replaced one by one
        (out / "planes").mkdir(parents=True)
        (out / "planes" / "notes.txt").write_text("mine")
    first = run_cli("match", data, "-o", out, *FAST, "--png16", "256")
    assert first.code == 0, first.err
    old = {p.name: p.read_bytes() for p in (out / "planes").iterdir()}
    killed = _stereocli("match", data, "-o", out, "-c", "default", "--overwrite", kill_at=point)
    assert killed.returncode == -9
    folder = out / "planes"
    marker = folder / ".stereocli-match.done"
    if point == "staging":  # nothing committed: the old set, whole
        assert {p.name: p.read_bytes() for p in folder.iterdir()} == old
    elif point == "swap":  # the old set moved aside, the new one not in place: no pair at all
        assert not folder.exists()
    else:  # replaced files are not marked complete
        assert not marker.exists() and (folder / "notes.txt").read_text() == "mine"
    resumed = run_cli("match", data, "-o", out, "-c", "default", "--skip-existing")
    assert resumed.code == 0, resumed.err
    assert "1 ok, 0 skipped" in resumed.err  # the old set was made with another config: redone
    params = json.loads((folder / "params.json").read_text())
    assert params["config_sources"][-1].endswith("default.yaml")
    assert read_pfm(folder / "disp0.pfm").shape == (96, 128) and marker.is_file()
    assert_clean(out, ("planes",))


# -- the one-line rule: third-party output and unlabelled OS errors --------------------------------

def _noisy_png(src: Path, dest: Path) -> None:
    """``src`` with a corrupt ancillary chunk: libpng reads it and prints a warning."""
    import struct

    data = src.read_bytes()
    chunk_end = 8 + 8 + 13 + 4
    body = b"Comment\x00hello"
    bad = struct.pack(">I", len(body)) + b"tEXt" + body + struct.pack(">I", 0xDEADBEEF)
    dest.write_bytes(data[:chunk_end] + bad + data[chunk_end:])


def test_third_party_warnings_are_collected_not_interleaved(tmp_path, scenes):
    data = copy_scenes(scenes, tmp_path / "data")
    _noisy_png(scenes / "curved" / "im0.png", data / "curved" / "im0.png")
    write_image(data / "planes" / "im1.png", np.zeros((90, 128), np.uint8))  # planes fails: views differ
    r = _stereocli("match", data, "-o", tmp_path / "out", *FAST)
    assert r.returncode == 3, r.stderr
    lines = r.stderr.strip().splitlines()
    assert [ln for ln in lines if ln.startswith("Error")] == [next(ln for ln in lines if "differ in size" in ln)]
    assert "Error: planes: " in r.stderr
    assert not [ln for ln in lines if ln.startswith("libpng")], r.stderr
    assert lines[-1].startswith("Note: ") and "libpng warning" in lines[-1] and "-v shows them" in lines[-1]
    shown = _stereocli("match", data, "-o", tmp_path / "out2", *FAST, "-v")
    tail = shown.stderr[shown.stderr.index("third-party output"):]
    assert "libpng warning" in tail and "Error: planes" in shown.stderr[:shown.stderr.index("third-party output")]


def test_a_full_disk_error_names_the_pair_and_the_file(tmp_path, scenes):
    import resource

    def limit():  # files above 20 KiB cannot be written (EFBIG, as on a full or quota-limited disk)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20 * 1024, 20 * 1024))

    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "stereocli", "match", scenes, "-o", out, *FAST], capture_output=True,
                       text=True, env=ENV, preexec_fn=limit, timeout=120)
    assert r.returncode == 1, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("Error")]
    assert sorted(errors) == sorted(f"Error: {n}: {out / n / 'disp0.pfm'}: cannot write (File too large)"
                                    for n in ("planes", "curved"))
    assert_clean(out)
