"""Hostile cases about what a batch writes and where: resumes that mix configs or inputs, pair
names that climb out of OUTDIR, outputs that replace inputs, names that take the run record's
place, locks that cannot be written or dangle, and scene names that are ambiguous or break the
report's rows.

Each case asserts the exit code and our own message, that nothing lands outside OUTDIR and
that no input changes.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, assert_clean, two_scenes

FAST = ("-c", "fast")
OTHER = ("-c", "fast", "--set", "optimizer.p2=2.5")  # another config, as fast to run
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    return two_scenes(tmp_path_factory.mktemp("scenes"), 128, 96)


@pytest.fixture(scope="module")
def results(scenes, tmp_path_factory) -> Path:
    """``scenes`` matched with the fast preset (read only)."""
    from stereocli.cli.errors import run_with_error_handling
    from stereocli.cli.main import cli

    out = tmp_path_factory.mktemp("results") / "res"
    assert run_with_error_handling(cli, ["match", str(scenes), "-o", str(out), *FAST, "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    """A calibration for 128x96 images."""
    from stereocli.io.calib import save_calibration
    from stereocli.synth.rig import default_rig

    path = tmp_path_factory.mktemp("rig") / "rig.yml"
    save_calibration(path, default_rig((128, 96)).calibration())
    return path


def _listing(folder: Path) -> dict[str, tuple[int, int]]:
    """Every path under ``folder`` with its size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def _record(out: Path) -> dict[str, dict]:
    return {item["name"]: item for item in json.loads((out / "run.json").read_text())["items"]}


# -- the lock ----------------------------------------------------------------------------------------

def test_a_dangling_lock_symlink_is_taken_over(run_cli, tmp_path, scenes):
    out = tmp_path / "out"
    out.mkdir()
    (out / ".stereocli.lock").symlink_to(tmp_path / "gone")
    r = run_cli("match", scenes, "-o", out, *FAST)
    assert r.code == 0, r.err
    assert not os.path.lexists(out / ".stereocli.lock")
    assert_clean(out, ("planes", "curved"))


def test_a_lock_that_cannot_be_written_is_not_left_behind(tmp_path, scenes):
    import resource

    def limit():  # files above 64 bytes cannot be written: the lock's JSON does not fit
        resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))

    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "stereocli", "match", scenes, "-o", out, *FAST], capture_output=True,
                       text=True, env=ENV, preexec_fn=limit, timeout=120)
    assert r.returncode == 1, r.stderr
    assert f"Error: {out / '.stereocli.lock'}: cannot write the lock file" in r.stderr
    assert not os.path.lexists(out / ".stereocli.lock") and not out.exists()
    again = subprocess.run([sys.executable, "-m", "stereocli", "match", scenes, "-o", out, *FAST],
                           capture_output=True, text=True, env=ENV, timeout=120)
    assert again.returncode == 0, again.stderr


