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

import numpy as np
import pytest

from conftest import REPO, assert_clean, two_scenes
from stereocli.io.images import read_image, write_image

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


# -- a resume redoes what another config or other inputs made -------------------------------------

def test_skip_existing_after_an_interrupted_overwrite_redoes_the_old_configs_items(run_cli, tmp_path, scenes):
    out = tmp_path / "out"
    assert run_cli("match", scenes, "-o", out, *FAST).code == 0
    # An --overwrite with another config that stopped after one of the two pairs.
    assert run_cli("match", scenes / "planes", "-o", out, *OTHER, "--overwrite").code == 0
    old_curved = (out / "curved" / "disp0.pfm").read_bytes()
    resumed = run_cli("match", scenes, "-o", out, *OTHER, "--skip-existing")
    assert resumed.code == 0, resumed.err
    assert "1 ok, 1 skipped, 0 failed" in resumed.err
    assert "Note: curved: stale outputs redone: made with other settings" in resumed.err
    assert "planes: stale" not in resumed.err
    record = _record(out)
    assert record["planes"]["status"] == "skipped" and "redone" not in record["planes"]
    assert record["curved"]["status"] == "ok" and record["curved"]["redone"].startswith("made with other settings")
    assert (out / "curved" / "disp0.pfm").read_bytes() != old_curved
    p2 = [json.loads((out / n / "params.json").read_text())["config"]["optimizer"]["p2"] for n in ("planes", "curved")]
    assert p2 == [2.5, 2.5]
    again = run_cli("match", scenes, "-o", out, *OTHER, "--skip-existing")
    assert again.code == 0 and "0 ok, 2 skipped" in again.err and "redone" not in again.err
    assert_clean(out, ("planes", "curved"))


def test_skip_existing_redoes_a_pair_whose_input_changed(run_cli, tmp_path, scenes):
    """What a ``rectify --overwrite`` into a folder ``match`` used does: the images change."""
    data = tmp_path / "data"
    shutil.copytree(scenes, data)
    assert run_cli("match", data, "-o", data, *FAST).code == 0  # match beside the images, as after rectify
    left = data / "planes" / "im0.png"
    write_image(left, np.ascontiguousarray(read_image(left)[::-1]))
    resumed = run_cli("match", data, "-o", data, *FAST, "--skip-existing")
    assert resumed.code == 0, resumed.err
    assert "1 ok, 1 skipped" in resumed.err
    assert f"Note: planes: stale outputs redone: the left input {left} changed since" in resumed.err
    assert _record(data)["planes"]["redone"].startswith(f"the left input {left} changed")


def test_skip_existing_redoes_items_whose_marker_predates_the_recipe(run_cli, tmp_path, scenes):
    out = tmp_path / "out"
    assert run_cli("match", scenes, "-o", out, *FAST).code == 0
    marker = out / "curved" / ".stereocli-match.done"
    old = {k: v for k, v in json.loads(marker.read_text()).items() if k in ("command", "outputs", "run", "finished")}
    marker.write_text(json.dumps(old) + "\n")  # as an older stereocli wrote it
    resumed = run_cli("match", scenes, "-o", out, *FAST, "--skip-existing")
    assert resumed.code == 0 and "1 ok, 1 skipped" in resumed.err, resumed.err
    assert "Note: curved: stale outputs redone: its marker records no settings or inputs" in resumed.err
    assert {"version", "config", "inputs"} <= set(json.loads(marker.read_text()))


def test_triangulate_resume_redoes_clouds_of_a_rematched_disparity(run_cli, tmp_path, scenes):
    res = tmp_path / "res"
    assert run_cli("match", scenes, "-o", res, *FAST).code == 0
    clouds = tmp_path / "clouds"
    assert run_cli("triangulate", res, "--scenes", scenes, "-o", clouds).code == 0
    assert run_cli("match", scenes / "curved", "-o", res, *OTHER, "--overwrite").code == 0
    resumed = run_cli("triangulate", res, "--scenes", scenes, "-o", clouds, "--skip-existing")
    assert resumed.code == 0, resumed.err
    assert "1 ok, 1 skipped" in resumed.err and "Note: curved: stale outputs redone" in resumed.err
    assert "the disparity input" in _record(clouds)["curved"]["redone"]


def test_a_marker_from_another_version_does_not_match(run_cli, tmp_path, scenes):
    from stereocli.io.pairs import discover_pairs
    from stereocli.jobs.items import is_done, marker_matches
    from stereocli.jobs.match import plan_items
    from stereocli.matching.config import build_config

    out = tmp_path / "out"
    assert run_cli("match", scenes / "planes", "-o", out, *FAST).code == 0
    item = plan_items(discover_pairs([str(scenes / "planes")])[0], out, config=build_config(["fast"], []).as_dict(),
                      ndisp=None, min_disp=None)[0]
    assert marker_matches(item) == (True, "") and is_done(item)
    marker = out / "planes" / ".stereocli-match.done"
    marker.write_text(json.dumps({**json.loads(marker.read_text()), "version": "0.0.1"}))
    ok, reason = marker_matches(item)
    assert not ok and reason.startswith("made by stereocli 0.0.1") and not is_done(item)


# -- names that climb out of OUTDIR or take the batch's own names ---------------------------------

def _named_pair(folder: Path, scenes: Path, stem: str) -> tuple[Path, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    left, right = folder / f"{stem}.png", folder / "right.png"
    shutil.copy(scenes / "planes" / "im0.png", left)
    shutil.copy(scenes / "planes" / "im1.png", right)
    return left, right


@pytest.mark.parametrize("stem,name", [("..", "__"), (".", "_"), (".stereocli-match.done", "_stereocli-match.done")])
def test_a_pair_named_by_a_dot_stem_stays_inside_outdir(run_cli, tmp_path, scenes, stem, name):
    left, right = _named_pair(tmp_path / "in", scenes, stem)
    work = tmp_path / "work"
    (work / "time.txt").parent.mkdir()
    (work / "time.txt").write_text("a user's file\n")
    before = _listing(work)
    for extra in ((), ("--skip-existing",)):
        r = run_cli("match", left, right, "-o", work / "out", *FAST, "--ndisp", "32", *extra)
        assert r.code == 0, r.err
    after = _listing(work)
    assert {k: v for k, v in after.items() if not k.startswith("out")} == before
    assert sorted(p.name for p in (work / "out").iterdir()) == [name, "run.json"]
    assert_clean(work / "out", (name,))
    assert _record(work / "out")[name]["status"] == "skipped"


def test_rectify_names_are_sanitised_too(run_cli, tmp_path, scenes, rig):
    left, right = _named_pair(tmp_path / "in", scenes, "..")
    work = tmp_path / "work"
    work.mkdir()
    r = run_cli("rectify", left, right, "--calib", rig, "-o", work / "out", "--ndisp", "16")
    assert r.code == 0, r.err
    assert sorted(p.name for p in work.iterdir()) == ["out"]
    assert_clean(work / "out", ("__",))
    assert (work / "out" / "__" / "im0.png").is_file()


def test_a_scene_named_run_json_does_not_take_the_records_place(run_cli, tmp_path, scenes):
    data = tmp_path / "data"
    shutil.copytree(scenes / "planes", data / "run.json")
    shutil.copytree(scenes / "curved", data / "curved")
    out = tmp_path / "out"
    for extra, summary in (((), "2 ok, 0 skipped"), (("--skip-existing",), "0 ok, 2 skipped")):
        r = run_cli("match", data, "-o", out, *FAST, *extra)
        assert r.code == 0 and summary in r.err, r.err
        assert (out / "run.json").is_file() and set(_record(out)) == {"_run.json", "curved"}
    assert_clean(out, ("_run.json", "curved"))


def test_a_newline_in_a_scene_name_stays_out_of_output_names(run_cli, tmp_path, scenes):
    data = tmp_path / "data"
    shutil.copytree(scenes / "planes", data / "pla\nnes")
    r = run_cli("match", data, "-o", tmp_path / "out", *FAST)
    assert r.code == 0, r.err
    assert_clean(tmp_path / "out", ("pla_nes",))


def test_error_maps_of_a_scene_named_dot_dot_stay_inside_their_folder(run_cli, tmp_path, results, scenes):
    gt = tmp_path / "gt"
    shutil.copytree(scenes / "planes", gt / "planes")
    (gt / "planes" / "sub").mkdir()
    work = tmp_path / "work"
    r = run_cli("eval", results / "planes" / "disp0.pfm", gt / "planes" / "sub" / "..", "--error-maps", work / "maps")
    assert r.code == 0, r.err
    assert sorted(p.name for p in work.iterdir()) == ["maps"]
    maps = sorted(p.name for p in (work / "maps" / "__").iterdir())
    assert maps == ["bad.png", "disparity.png", "error.png", "gt.png"]


def test_a_symlinked_pair_folder_leading_out_of_outdir_is_refused(run_cli, tmp_path, scenes):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    (out / "planes").symlink_to(elsewhere)
    r = run_cli("match", scenes, "-o", out, *FAST, "--skip-existing")
    assert r.code == 2, r.err
    assert f"Error: planes: its output {out / 'planes' / 'disp0.pfm'} resolves to" in r.err
    assert "outside the output folder" in r.err
    assert not any(elsewhere.iterdir()) and sorted(p.name for p in out.iterdir()) == ["planes"]


# -- outputs that would replace inputs ------------------------------------------------------------

@pytest.mark.parametrize("policy", [(), ("--skip-existing",), ("--overwrite",)])
def test_rectify_never_replaces_its_own_inputs(run_cli, tmp_path, scenes, rig, policy):
    data = tmp_path / "photos"
    shutil.copytree(scenes, data)
    before = _listing(data)
    r = run_cli("rectify", data, "--calib", rig, "-o", data, "--ndisp", "16", *policy)
    assert r.code == 2, r.err
    assert f"would replace the input {data / 'curved' / 'im0.png'}" in r.err
    assert "--skip-existing" not in r.err and "--overwrite" not in r.err
    assert len([line for line in r.err.splitlines() if line.startswith("Error")]) == 1
    assert _listing(data) == before


def test_triangulate_never_replaces_its_own_inputs(run_cli, tmp_path, results, scenes):
    res = tmp_path / "res"
    shutil.copytree(results, res)
    conf = res / "planes" / "depth.pfm"  # a confidence map where triangulate writes the depth
    shutil.copy(res / "planes" / "disp0.pfm", conf)
    before = _listing(res)
    r = run_cli("triangulate", res / "planes", "--scenes", scenes, "--confidence", conf, "-o", res)
    assert r.code == 2, r.err
    assert f"would replace the input {conf}" in r.err
    assert _listing(res) == before


@pytest.mark.parametrize("target", ["result", "gt"])
def test_an_eval_report_never_replaces_what_it_scores(run_cli, tmp_path, results, scenes, target):
    res, gt = tmp_path / "res", tmp_path / "gt"
    shutil.copytree(results, res)
    shutil.copytree(scenes, gt)
    victim = res / "planes" / "disp0.pfm" if target == "result" else gt / "planes" / "disp0GT.pfm"
    before = victim.read_bytes()
    r = run_cli("eval", res, gt, "-o", victim, "--overwrite")
    assert r.code == 2, r.err
    assert "would replace the input" in r.err and len(r.err.strip().splitlines()) == 1
    assert victim.read_bytes() == before
    assert run_cli("eval", res, gt, "-o", res / "report.txt").code == 0  # a new file beside them is fine


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


# -- eval: ambiguous names, names that break rows -----------------------------------------------------

def test_two_results_matching_one_scene_case_insensitively_are_an_error(run_cli, tmp_path, results, scenes):
    res = tmp_path / "res"
    shutil.copytree(results / "curved", res / "curved")
    shutil.copytree(results / "planes", res / "Planes")
    shutil.copytree(results / "planes", res / "PLANES")
    r = run_cli("eval", res, scenes)
    assert r.code == 3, r.err
    assert "ambiguous result: 'PLANES' and 'Planes' both match 'planes'" in r.out + r.err
    assert "without ground truth" not in r.out


def test_two_gt_scenes_matching_a_result_case_insensitively_are_an_error(run_cli, tmp_path, results, scenes):
    gt = tmp_path / "gt"
    shutil.copytree(scenes / "planes", gt / "Planes")
    shutil.copytree(scenes / "planes", gt / "PLANES")
    r = run_cli("eval", results / "planes" / "disp0.pfm", gt)
    assert r.code == 1, r.err
    assert "ambiguous GT scene" in r.err and str(gt / "PLANES") in r.err and str(gt / "Planes") in r.err


@pytest.mark.parametrize("fmt", ["text", "markdown"])
def test_a_newline_in_a_scene_name_keeps_the_report_one_row_per_scene(run_cli, tmp_path, results, scenes, fmt):
    gt, res = tmp_path / "gt", tmp_path / "res"
    shutil.copytree(scenes / "curved", gt / "cur\nved")
    shutil.copytree(scenes / "planes", gt / "planes")
    shutil.copytree(results / "curved", res / "cur\nved")
    shutil.copytree(results / "planes", res / "planes")
    r = run_cli("eval", res, gt, "--format", fmt)
    assert r.code == 0, r.err
    rows = [line for line in r.out.splitlines() if "cur" in line]
    assert rows and all("cur\\nved" in line for line in rows)
    assert not [line for line in r.out.splitlines() if line.startswith("ved")]


def test_eval_finds_results_under_their_sanitised_names(run_cli, tmp_path, results, scenes):
    gt, res = tmp_path / "gt", tmp_path / "res"
    shutil.copytree(scenes / "planes", gt / "run.json")
    shutil.copytree(results / "planes", res / "_run.json")  # where match writes scene run.json
    r = run_cli("eval", res, gt, "--format", "json")
    assert r.code == 0, r.err
    assert [s["name"] for s in r.json()["scenes"]] == ["run.json"]
