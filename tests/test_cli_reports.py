"""What a new user reads: calibrate's report on stdout, whole preset descriptions, the README's
example config, --viz colour bars and --viz-range, the HTML report's time columns, and run.json
keeping the record of the run behind the outputs when --skip-existing resumes."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from conftest import REPO, two_scenes
from stereocli.io.images import read_image
from stereocli.runinfo import RunRecord

# --------------------------------------------------------------------------- calibrate

@pytest.mark.slow
def test_calibrate_prints_its_report_on_stdout(run_cli, tmp_path):
    from stereocli.synth.rig import render_rig

    render_rig(tmp_path / "rig", n_pairs=6, seed=0)
    r = run_cli("calibrate", tmp_path / "rig", "-o", tmp_path / "rig.yml", "--pattern", "9x6", "--square", "40mm")
    assert r.code == 0, r.err
    assert r.out.startswith("calibrated 6 of 6 pairs") and "epipolar error mean" in r.out
    report = json.loads((tmp_path / "rig.report.json").read_text())
    assert report["warnings"]  # fewer than 10 views
    assert [line for line in r.err.splitlines() if line.startswith("Warning: ")] == [
        f"Warning: {w}" for w in report["warnings"]]
    assert r.err.splitlines()[-1] == f"wrote {tmp_path / 'rig.yml'} and {tmp_path / 'rig.report.json'}"
    r = run_cli("calibrate", tmp_path / "rig", "-o", tmp_path / "rig.yml", "--pattern", "9x6", "--square", "40mm",
                "--overwrite", "--format", "json", "-q")
    assert r.code == 0 and r.err == ""
    assert r.json() == json.loads((tmp_path / "rig.report.json").read_text())


# --------------------------------------------------------------------------- config presets, README

def test_config_presets_prints_each_first_sentence_whole(run_cli):
    from stereocli.config import preset_names, preset_summary

    r = run_cli("config", "presets")
    assert r.code == 0
    entries = re.split(r"\n(?=\S)", r.out.strip())
    assert [e.split(":")[0] for e in entries] == preset_names()
    for entry in entries:
        assert all(len(line) <= 100 for line in entry.splitlines())
        text = " ".join(line.strip() for line in entry.splitlines())
        name, description = text.split(": ", 1)
        assert description.endswith(".") and preset_summary(name).endswith(description)
    assert "accurate: the best accuracy per second when time matters less than the map." in entries
    assert entries[preset_names().index("fast")].rstrip().endswith("plane_smooth (through every\n    third neighbour).")


def test_readme_example_config_is_valid_and_says_it_is_not_the_default(tmp_path):
    from stereocli.matching.config import build_config

    readme = (REPO / "README.md").read_text()
    section = readme.split("## Configuration", 1)[1]
    intro, rest = section.split("```yaml\n", 1)
    assert "not the `default` preset" in " ".join(intro.split())
    example = tmp_path / "example.yaml"
    example.write_text(rest.split("```", 1)[0])
    config = build_config([str(example)], [])
    assert config.as_dict() != build_config([], []).as_dict()


# --------------------------------------------------------------------------- --viz

def test_viz_has_a_colour_bar_and_takes_a_range(run_cli, tmp_path):
    from stereocli.io.pfm import read_pfm
    from stereocli.viz import colorize_disparity

    scenes = two_scenes(tmp_path / "in", 96, 64)
    r = run_cli("match", scenes / "planes", "-o", tmp_path / "out", "-c", "fast", "--viz-range", "0:40")
    assert r.code == 0, r.err
    viz = read_image(tmp_path / "out" / "planes" / "disp0_viz.png")
    disp = read_pfm(tmp_path / "out" / "planes" / "disp0.pfm")
    assert viz.shape == (64 + 34, 96, 3)  # the map above a 34-row bar
    np.testing.assert_array_equal(viz[:64], colorize_disparity(disp, 0.0, 40.0))
    ramp = colorize_disparity(np.array([[0.0, 40.0]], np.float32), 0.0, 40.0)
    np.testing.assert_array_equal(viz[64 + 5, [0, -1]], ramp[0])  # the bar runs from MIN to MAX
    labels = viz[64 + 12:]
    assert (labels.min(axis=2) < 128).sum() > 20  # the numbers drawn under the bar
    r = run_cli("match", scenes / "planes", "-o", tmp_path / "bad", "--viz-range", "40:0")
    assert r.code == 2 and "MIN below MAX" in r.err


# --------------------------------------------------------------------------- HTML report

def test_html_report_has_the_text_reports_time_columns(run_cli, tmp_path):
    from stereocli.io.pfm import write_pfm
    from test_eval_cli import make_mb2014_scene

    gt = make_mb2014_scene(tmp_path / "gt", "Adirondack")
    write_pfm(tmp_path / "res" / "Adirondack" / "disp0.pfm", np.where(np.isfinite(gt), gt, 3.0).astype(np.float32))
    (tmp_path / "res" / "Adirondack" / "time.txt").write_text("0.5\n")
    r = run_cli("eval", tmp_path / "res", tmp_path / "gt", "--html", tmp_path / "html")
    assert r.code == 0, r.err
    page = (tmp_path / "html" / "report.html").read_text()
    header = next(line for line in r.out.splitlines() if line.startswith("scene "))
    row = next(line for line in r.out.splitlines() if line.startswith("Adirondack"))
    columns, cells = header.split()[1:], row.split()[1:]
    assert columns[-3:] == ["time", "s/MP", "s/GD"]
    first_table = page.split("<table>")[1].split("</table>")[0]
    assert re.findall(r"<th>([^<]*)</th>", first_table) == ["scene"] + columns
    html_row = next(r for r in first_table.split("\n") if "<td>Adirondack</td>" in r)
    assert re.findall(r"<td>([^<]*)</td>", html_row) == ["Adirondack"] + cells


# --------------------------------------------------------------------------- run.json history

def _record(path, items: list[tuple[str, str]], started: str) -> None:
    record = RunRecord("match", ["stereocli", "match"])
    record.data["started"] = started
    for name, status in items:
        record.add_item({"name": name, "status": status})
    record.write(path)


def test_run_json_keeps_the_runs_behind_the_outputs(tmp_path):
    path = tmp_path / "run.json"
    _record(path, [("a", "ok"), ("b", "failed")], "T1")
    _record(path, [("a", "skipped"), ("b", "ok")], "T2")
    _record(path, [("a", "skipped"), ("b", "skipped"), ("c", "ok")], "T3")
    data = json.loads(path.read_text())
    assert data["started"] == "T3" and [run["started"] for run in data["previous"]] == ["T1", "T2"]
    assert {i["name"]: i.get("made_by") for i in data["items"]} == {"a": "T1", "b": "T2", "c": None}
    assert all("previous" not in run for run in data["previous"])
    # A run that makes a and b again leaves T1 and T2 nothing in the folder; T3 still made c.
    _record(path, [("a", "ok"), ("b", "ok")], "T4")
    data = json.loads(path.read_text())
    assert [run["started"] for run in data["previous"]] == ["T3"]
    _record(path, [("a", "ok"), ("b", "ok"), ("c", "ok")], "T5")
    assert "previous" not in json.loads(path.read_text())
    path.write_text("{not json")
    _record(path, [("a", "ok")], "T6")
    data = json.loads(path.read_text())
    assert "previous" not in data and data["previous_unreadable"].startswith("run.json of an earlier run could not")


def test_skip_existing_resume_keeps_the_first_runs_record(run_cli, tmp_path):
    scenes = two_scenes(tmp_path / "in", 96, 64)
    out = tmp_path / "out"
    assert run_cli("match", scenes, "-o", out, "-c", "fast").code == 0
    first = json.loads((out / "run.json").read_text())
    r = run_cli("match", scenes, "-o", out, "-c", "fast", "--skip-existing")
    assert r.code == 0 and "0 ok, 2 skipped, 0 failed" in r.err
    data = json.loads((out / "run.json").read_text())
    assert data["summary"] == {"ok": 0, "skipped": 2, "failed": 0}
    assert data["previous"] == [first]
    assert {i["name"]: i["made_by"] for i in data["items"]} == {"planes": first["started"],
                                                               "curved": first["started"]}
