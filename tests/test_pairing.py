"""One pairing rule for every subcommand: the layouts of docs/formats.md ("Input layouts"), case
by case, the same names in calibrate, rectify, match and triangulate, and outputs that chain by
name (rectify -> match -> triangulate, match -> eval)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from stereocli.errors import DataError
from stereocli.io.images import write_image
from stereocli.io.pairs import discover_pairs, find_calibration_pairs


def _img(path: Path, value: int = 0) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_image(path, np.full((4, 6), value, np.uint8))
    return path


def _names(*inputs) -> list[str]:
    pairs, problems = discover_pairs([str(i) for i in inputs])
    assert not problems, problems
    return [p.name for p in pairs]


def _files(folder: Path, *names: str) -> Path:
    for name in names:
        _img(folder / name)
    return folder


def _sides(pairs) -> list[tuple[str, str]]:
    return [(Path(p.left).name, Path(p.right).name) for p in pairs]


# --------------------------------------------------------------------------- scene folders

@pytest.mark.parametrize("left,right", [("im0", "im1"), ("im2", "im6"), ("im3", "im4"), ("view1", "view5"),
                                        ("left", "right")])
def test_a_scene_folder_is_named_by_the_folder(tmp_path, left, right):
    scene = _files(tmp_path / "Scene", f"{left}.png", f"{right}.png")
    (scene / "calib.txt").write_text("cam0=[1 0 2; 0 1 2; 0 0 1]\nndisp=16\n")
    pairs, problems = discover_pairs([str(scene)])
    assert [p.name for p in pairs] == ["Scene"] and not problems
    assert _sides(pairs) == [(f"{left}.png", f"{right}.png")] and pairs[0].calib == str(scene / "calib.txt")
    # Its two files given alone are the same scene, with the same name.
    assert _names(scene / f"{left}.png", scene / f"{right}.png") == ["Scene"]


def test_of_several_scene_pairs_the_one_with_ground_truth_is_the_scene(tmp_path):
    scene = _files(tmp_path / "barn1", *(f"im{k}.pgm" for k in range(9)))
    with pytest.raises(DataError, match=r"ambiguous scene: .*im0.pgm/im1.pgm and im2.pgm/im6.pgm"):
        discover_pairs([str(scene)])
    _img(scene / "disp2.pgm")
    pairs, _ = discover_pairs([str(scene)])
    assert [p.name for p in pairs] == ["barn1"] and _sides(pairs) == [("im2.pgm", "im6.pgm")]


def test_a_folder_of_scene_folders(tmp_path):
    _files(tmp_path / "data" / "a", "im0.png", "im1.png")
    _files(tmp_path / "data" / "b", "view1.png", "view5.png")
    _files(tmp_path / "data" / "notes", "sketch.png")
    _files(tmp_path / "data" / "rig", "left01.png", "right01.png")
    pairs, problems = discover_pairs([str(tmp_path / "data")])
    assert [p.name for p in pairs] == ["a", "b"]
    assert len(problems) == 2 and problems[0].startswith(f"{tmp_path / 'data' / 'notes'}: holds images but no")
    assert problems[1] == (f"{tmp_path / 'data' / 'rig'}: holds 2 left*/right* files (left01.png, ...), not one "
                           f"scene; give {tmp_path / 'data' / 'rig'} itself to pair them")


# --------------------------------------------------------------------------- side-word files in one folder

@pytest.mark.parametrize("left,right,name", [
    ("left01.jpg", "right01.jpg", "01"),
    ("left_0001.png", "right_0001.png", "0001"),
    ("0001_left.png", "0001_right.png", "0001"),
    ("Left-7.png", "Right-7.png", "7"),
    ("img_left_7.png", "img_right_7.png", "img_7"),
])
def test_side_word_files_pair_by_the_rest_of_the_name(tmp_path, left, right, name):
    folder = _files(tmp_path / "rig", left, right)
    pairs, problems = discover_pairs([str(folder)])
    assert [p.name for p in pairs] == [name] and _sides(pairs) == [(left, right)] and not problems
    assert [n for n, _, _ in find_calibration_pairs(folder)] == [name]
    assert _names(folder / left, folder / right) == [name]  # the two files alone: the same name


def test_side_word_pairs_come_in_natural_order(tmp_path):
    folder = _files(tmp_path / "rig", *(f"{side}{k}.png" for k in (10, 2, 1) for side in ("left", "right")))
    assert _names(folder) == ["1", "2", "10"]


def test_a_side_word_inside_another_word_is_no_side(tmp_path):
    folder = _files(tmp_path / "rig", "left01.png", "right01.png", "bright_02.png")
    pairs, problems = discover_pairs([str(folder)])
    assert [p.name for p in pairs] == ["01"]
    assert problems == [(f"{folder / 'bright_02.png'}: no left/right word in its name (the folder pairs "
                         "left*/right* files); not paired")]
    with pytest.raises(DataError, match="do not pair up .*bright_02.png"):
        find_calibration_pairs(folder)


def test_an_unpaired_side_word_file_is_named(tmp_path):
    folder = _files(tmp_path / "rig", "left01.png", "right01.png", "left02.png")
    pairs, problems = discover_pairs([str(folder)])
    assert [p.name for p in pairs] == ["01"]
    assert problems == [f"{folder / 'left02.png'}: no matching right image in {folder}"]


def test_two_files_of_one_side_and_name_are_ambiguous(tmp_path):
    folder = _files(tmp_path / "rig", "left_01.png", "01_left.png", "right01.png")
    with pytest.raises(DataError, match=r"ambiguous pair name '01': .*01_left.png and .*left_01.png"):
        discover_pairs([str(folder)])


# --------------------------------------------------------------------------- subfolders

@pytest.mark.parametrize("left,right", [("left/0001.png", "right/0001.png"),
                                        ("left/left_0001.png", "right/right_0001.png"),
                                        ("left/0001_l.png", "right/0001_r.png"),
                                        ("cam0/0001.png", "cam1/0001.png"),
                                        ("cam0/0001_left.png", "cam1/0001_right.png")])
def test_subfolders_pair_by_the_stem_without_its_side(tmp_path, left, right):
    folder = _files(tmp_path / "rig", left, right)
    pairs, problems = discover_pairs([str(folder)])
    assert [p.name for p in pairs] == ["0001"] and not problems
    assert _sides(pairs) == [(Path(left).name, Path(right).name)]
    assert [n for n, _, _ in find_calibration_pairs(folder)] == ["0001"]
    # The two subfolders given as folders, and two files: the same names.
    assert _names(folder / Path(left).parent, folder / Path(right).parent) == ["0001"]
    assert _names(folder / left, folder / right) == ["0001"]


def test_unpaired_files_in_subfolders_are_reported(tmp_path):
    folder = _files(tmp_path / "rig", "left/01.png", "left/02.png", "right/01.png", "right/03.png")
    pairs, problems = discover_pairs([str(folder)])
    assert [p.name for p in pairs] == ["01"]
    assert problems == [f"{folder / 'left' / '02.png'}: no matching right image in {folder / 'right'}",
                        f"{folder / 'right' / '03.png'}: no matching left image in {folder / 'left'}"]


# --------------------------------------------------------------------------- ambiguity

@pytest.mark.parametrize("files,named", [
    (("im0.png", "im1.png", "left01.png", "right01.png"), ("im0.png/im1.png", "left*/right* files")),
    (("left/01.png", "right/01.png", "cam0/01.png", "cam1/01.png"), ("left/ + right/", "cam0/ + cam1/")),
    (("left01.png", "right01.png", "s/im0.png", "s/im1.png"), ("left*/right* files", "scene folder")),
    (("im0.png", "im1.png", "left/01.png", "right/01.png"), ("im0.png/im1.png", "left/ + right/")),
])
def test_a_folder_with_two_layouts_is_an_error_naming_them(tmp_path, files, named):
    folder = _files(tmp_path / "mixed", *files)
    for pairing in (lambda: discover_pairs([str(folder)]), lambda: find_calibration_pairs(folder)):
        with pytest.raises(DataError) as err:
            pairing()
        assert str(err.value).startswith(f"{folder}: ambiguous: it holds ")
        assert all(n in str(err.value) for n in named), str(err.value)


def test_two_files_not_of_one_folder_are_named_by_the_left_stem(tmp_path):
    assert _names(_img(tmp_path / "a.png"), _img(tmp_path / "b.png")) == ["a"]


# --------------------------------------------------------------------------- every subcommand, one name

RIG = Path(__file__).resolve().parents[1] / "samples" / "rig"


def _rig_as(folder: Path, left: str, right: str, count: int = 2) -> Path:
    """The first ``count`` pairs of samples/rig, named ``left.format(k)`` / ``right.format(k)``."""
    for k in range(1, count + 1):
        for side, pattern in (("left", left), ("right", right)):
            target = folder / pattern.format(k)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(RIG / side / f"{k:02d}.png", target)
    return folder


@pytest.mark.parametrize("left,right", [("left{:02d}.png", "right{:02d}.png"),
                                        ("left_{:04d}.png", "right_{:04d}.png"),
                                        ("{:04d}_left.png", "{:04d}_right.png"),
                                        ("cam0/{:04d}.png", "cam1/{:04d}.png")])
def test_every_subcommand_names_the_pairs_alike(run_cli, tmp_path, left, right):
    rig = _rig_as(tmp_path / "rig", left, right)
    expected = [n for n, _, _ in find_calibration_pairs(rig)]  # what calibrate names its views
    assert len(expected) == 2
    r = run_cli("rectify", rig, "--calib", RIG / "truth.yml", "-o", tmp_path / "rect", "--dry-run")
    assert r.code == 0, r.err
    assert [i["name"] for i in json.loads(r.out)] == expected
    r = run_cli("match", rig, "-o", tmp_path / "out", "--ndisp", "64", "--dry-run")
    assert r.code == 0, r.err
    assert [i["name"] for i in r.json()["items"]] == expected


def test_the_chessboard_rig_pairs_in_match_as_in_calibrate(run_cli, shared_data, tmp_path):
    folder = shared_data / "calibration" / "opencv-chessboard"
    expected = ["01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"]
    assert [n for n, _, _ in find_calibration_pairs(folder)] == expected
    r = run_cli("match", folder, "-o", tmp_path / "out", "--ndisp", "64", "--dry-run")
    assert r.code == 0, r.err
    assert [i["name"] for i in r.json()["items"]] == expected and r.json()["unpaired"] == []


@pytest.mark.slow
def test_rectify_outputs_feed_match_and_match_outputs_feed_triangulate(run_cli, tmp_path):
    rig = _rig_as(tmp_path / "rig", "{:04d}_left.png", "{:04d}_right.png")
    assert run_cli("rectify", rig, "--calib", RIG / "truth.yml", "-o", tmp_path / "rect", "--ndisp", "64").code == 0
    assert sorted(p.name for p in (tmp_path / "rect").iterdir()) == ["0001", "0002", "run.json"]
    r = run_cli("match", tmp_path / "rect", "-o", tmp_path / "disp", "-c", "fast")
    assert r.code == 0, r.err
    assert sorted(p.name for p in (tmp_path / "disp").iterdir()) == ["0001", "0002", "run.json"]
    r = run_cli("triangulate", tmp_path / "disp", "--scenes", tmp_path / "rect", "-o", tmp_path / "cloud", "--dry-run")
    assert r.code == 0, r.err
    plan = {i["name"]: i["inputs"] for i in json.loads(r.out)}
    assert sorted(plan) == ["0001", "0002"]
    for name, inputs in plan.items():
        assert inputs["calibration"] == str(tmp_path / "rect" / name / "calib.txt")
        assert inputs["image"] == str(tmp_path / "rect" / name / "im0.png")


def test_triangulate_finds_its_pair_in_scenes_of_any_layout(run_cli, tmp_path):
    """--scenes is paired like match's input: a disparity named 0001 takes the left image of the
    pair named 0001 in a folder of 0001_left/0001_right files."""
    rig = _rig_as(tmp_path / "rig", "{:04d}_left.png", "{:04d}_right.png", count=1)
    disp = tmp_path / "disp" / "0001"
    disp.mkdir(parents=True)
    (disp / "disp0.pfm").write_bytes(b"Pf\n640 480\n-1.0\n" + np.ones((480, 640), "<f4").tobytes())
    r = run_cli("triangulate", tmp_path / "disp", "--scenes", rig, "--calib", RIG / "truth.yml", "-o",
                tmp_path / "cloud", "--dry-run")
    assert r.code == 0, r.err
    assert json.loads(r.out)[0]["inputs"]["image"] == str(rig / "0001_left.png")


def test_match_outputs_feed_eval_by_name(run_cli, tmp_path):
    from conftest import two_scenes

    gt = two_scenes(tmp_path / "gt", 96, 64)
    pairs = tmp_path / "pairs"
    pairs.mkdir()
    for scene in ("planes", "curved"):
        shutil.copy(gt / scene / "im0.png", pairs / f"{scene}_left.png")
        shutil.copy(gt / scene / "im1.png", pairs / f"{scene}_right.png")
    r = run_cli("match", pairs, "-o", tmp_path / "out", "-c", "fast", "--ndisp", "32")
    assert r.code == 0, r.err
    r = run_cli("eval", tmp_path / "out", gt, "--format", "json")
    assert r.code == 0, r.err
    assert sorted(s["name"] for s in r.json()["scenes"]) == ["curved", "planes"]
    assert r.json()["failures"] == []
