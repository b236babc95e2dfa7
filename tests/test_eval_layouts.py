"""``eval`` scores every layout it names: a lone KITTI pair with KITTI rules, KITTI folders
without the full disp_noc_0/ + disp_occ_0/ tree, Middlebury 2005/2006 scenes at Full, Half and
Third size, and ``--dataset`` is never ignored."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stereocli.evaluation.datasets import detect_layout, load_scene
from stereocli.io.images import read_image, write_disparity_png16, write_image
from stereocli.io.pfm import write_pfm

INF = np.inf


def _kitti_gt(path: Path, *, noc: bool = False) -> np.ndarray:
    """A 4x6 KITTI GT of 20 px: one unknown pixel; without the last column when ``noc``."""
    gt = np.full((4, 6), 20.0, dtype=np.float32)
    gt[0, 0] = INF
    if noc:
        gt[:, 5] = INF
    write_disparity_png16(path, gt)
    return gt


def _kitti_estimate(path: Path) -> Path:
    """20 px with one outlier (25: 5 px and 25 % off) and two holes the KITTI fill closes."""
    est = np.full((4, 6), 20.0, dtype=np.float32)
    est[1, 2] = 25.0
    est[2, 1:3] = INF
    if path.suffix == ".pfm":
        write_pfm(path, est)
    else:
        write_disparity_png16(path, est)
    return path


def test_a_lone_kitti_pair_is_scored_with_kitti_rules(run_cli, tmp_path):
    est = _kitti_estimate(tmp_path / "res" / "disp0.pfm")
    gt = tmp_path / "gt.png"
    _kitti_gt(gt)
    r = run_cli("eval", est, gt, "--dataset", "kitti", "--format", "json")
    assert r.code == 0, r.err
    report = r.json()
    assert report["rules"].startswith("KITTI 2015 rules")
    scene = report["scenes"][0]
    assert scene["dataset"] == "kitti" and "nonocc" not in scene  # occ only: no disp_noc given
    assert scene["all"]["D1"] == pytest.approx(100 / 23) and scene["all"]["density"] == pytest.approx(100 * 21 / 23)
    assert report["failures"] == [] and any("nonocc not scored" in n for n in report["notes"])
    # Without --dataset a bare 16-bit PNG is scored by MiddEval3 rules, and the message says how to get KITTI's.
    r = run_cli("eval", est, gt, "--format", "json")
    assert r.code == 3 and "--dataset kitti scores it by KITTI's rules" in r.json()["failures"][0]["message"]
    # A GT named disp_noc scores the non-occluded region.
    noc = tmp_path / "disp_noc.png"
    _kitti_gt(noc, noc=True)
    scene = run_cli("eval", est, noc, "--dataset", "kitti", "--format", "json").json()["scenes"][0]
    assert "all" not in scene and scene["nonocc"]["D1"] == pytest.approx(100 / 19)


def test_a_folder_holding_one_frames_noc_and_occ_files(run_cli, tmp_path):
    est = _kitti_estimate(tmp_path / "000000_10.png")
    frame = tmp_path / "frame"
    _kitti_gt(frame / "disp_occ.png")
    _kitti_gt(frame / "disp_noc.png", noc=True)
    r = run_cli("eval", est, frame, "--dataset", "kitti", "--format", "json")
    assert r.code == 0, r.err
    scene = r.json()["scenes"][0]
    assert scene["all"]["D1"] == pytest.approx(100 / 23) and scene["nonocc"]["D1"] == pytest.approx(100 / 19)


@pytest.mark.parametrize("present,region,d1", [("disp_occ_0", "all", 100 / 23), ("disp_noc_0", "nonocc", 100 / 19)])
def test_a_kitti_root_with_one_of_its_folders(run_cli, tmp_path, present, region, d1):
    root = tmp_path / "kitti"
    for name in ("000000_10", "000001_10"):
        _kitti_gt(root / present / f"{name}.png", noc=region == "nonocc")
        _kitti_estimate(tmp_path / "res" / f"{name}.png")
    r = run_cli("eval", tmp_path / "res", root, "--format", "json")
    assert r.code == 0, r.err
    scenes = r.json()["scenes"]
    assert [s["name"] for s in scenes] == ["000000_10", "000001_10"]
    assert all(set(s) & {"nonocc", "all"} == {region} and s[region]["D1"] == pytest.approx(d1) for s in scenes)
    # A single result against the root: the frame named like the result.
    r = run_cli("eval", tmp_path / "res" / "000001_10.png", root, "--format", "json")
    assert r.code == 0 and r.json()["scenes"][0]["name"] == "000001_10"


def test_a_frame_missing_from_a_folder_the_root_has_still_fails(run_cli, tmp_path):
    root = tmp_path / "kitti"
    for name in ("000000_10", "000001_10"):
        _kitti_gt(root / "disp_occ_0" / f"{name}.png")
        _kitti_estimate(tmp_path / "res" / f"{name}.png")
    _kitti_gt(root / "disp_noc_0" / "000000_10.png", noc=True)
    r = run_cli("eval", tmp_path / "res", root, "--format", "json")
    assert r.code == 3
    assert [f["name"] for f in r.json()["failures"]] == ["000001_10"]
    assert "disp_noc_0/000001_10.png: missing, nonocc not scored" in r.json()["failures"][0]["message"]


def test_dataset_kitti_reads_a_flat_folder_of_gt_files(run_cli, tmp_path):
    for name in ("a", "b"):
        _kitti_gt(tmp_path / "gt" / f"{name}.png")
        _kitti_estimate(tmp_path / "res" / f"{name}.png")
    r = run_cli("eval", tmp_path / "res", tmp_path / "gt", "--dataset", "kitti", "--format", "json")
    assert r.code == 0, r.err
    assert [(s["name"], s["dataset"]) for s in r.json()["scenes"]] == [("a", "kitti"), ("b", "kitti")]


def test_dataset_is_never_ignored_for_a_bare_gt_file(run_cli, tmp_path):
    gt = np.full((4, 6), 10.0, dtype=np.float32)
    write_image(tmp_path / "gt.pgm", (gt * 4).astype(np.uint8))
    est = tmp_path / "est.pfm"
    write_pfm(est, gt + 2.0)
    r = run_cli("eval", est, tmp_path / "gt.pgm", "--dataset", "middlebury2003")
    assert r.code == 2 and "--gt-scale" in r.err
    r = run_cli("eval", est, tmp_path / "gt.pgm", "--dataset", "middlebury2003", "--gt-scale", "4", "--format", "json")
    assert r.code == 0, r.err
    assert r.json()["rules"].startswith("Middlebury v2 rules") and r.json()["scenes"][0]["all"]["bad1.0"] == 100.0


# --------------------------------------------------------------------------- Middlebury 2005/2006

def _mb2005_scene(folder: Path, width: int, divisor: int) -> np.ndarray:
    """view1/view5/disp1.png of ``width`` px: GT values in full-size units (``d * divisor``)."""
    d = np.tile(np.linspace(5.0, 20.0, width, dtype=np.float32), (3, 1))
    raw = np.round(d * divisor).astype(np.uint8)
    raw[0, :4] = 0  # unknown
    write_image(folder / "disp1.png", raw)
    write_image(folder / "view1.png", np.zeros((3, width), np.uint8))
    write_image(folder / "view5.png", np.zeros((3, width), np.uint8))
    return np.where(raw > 0, raw / np.float32(divisor), np.inf).astype(np.float32)


@pytest.mark.parametrize("width,divisor", [(1390, 1), (1240, 1), (695, 2), (620, 2), (463, 3), (413, 3)])
def test_mb2005_scale_comes_from_the_size(tmp_path, width, divisor):
    truth = _mb2005_scene(tmp_path / "Books", width, divisor)
    assert detect_layout(tmp_path / "Books") == "middlebury2005"
    scene = load_scene(tmp_path / "Books")
    assert scene.gt_scale == divisor and scene.left_image == tmp_path / "Books" / "view1.png"
    np.testing.assert_array_equal(scene.gt, truth)


def test_mb2005_scene_scored_by_name_and_a_width_of_no_size_refused(run_cli, tmp_path):
    truth = _mb2005_scene(tmp_path / "gt" / "Books", 463, 3)
    write_pfm(tmp_path / "out" / "Books" / "disp0.pfm", np.where(np.isfinite(truth), truth + 0.75, 1.0))
    r = run_cli("eval", tmp_path / "out", tmp_path / "gt", "--format", "json")
    assert r.code == 0, r.err
    scene = r.json()["scenes"][0]
    assert scene["dataset"] == "middlebury2005" and r.json()["rules"].startswith("Middlebury 2005/2006 rules")
    assert scene["all"]["bad0.5"] == 100.0 and scene["all"]["bad1.0"] == 0.0
    odd = _mb2005_scene(tmp_path / "odd" / "Books", 900, 2)
    write_pfm(tmp_path / "odd_out" / "Books" / "disp0.pfm", np.where(np.isfinite(odd), odd, 1.0))
    r = run_cli("eval", tmp_path / "odd_out", tmp_path / "odd")
    assert r.code == 2 and "900 px wide, none of the Middlebury 2005/2006 sizes" in r.err and "--gt-scale" in r.err
    r = run_cli("eval", tmp_path / "odd_out", tmp_path / "odd", "--gt-scale", "2", "--format", "json")
    assert r.code == 0 and r.json()["scenes"][0]["all"]["bad0.5"] == 0.0


MB2005 = ("Books", "Dolls", "Laundry", "Moebius", "Reindeer")


@pytest.mark.parametrize("name", MB2005)
def test_mb2005_validation_scenes_decode_at_third_size(shared_data, name):
    """The GT at the detected scale (/3) warps the right view onto the left far better than at
    /2 or /4 (the scale is a fact of the data, not of a matcher)."""
    folder = shared_data / "middlebury2005" / name
    scene = load_scene(folder)
    assert scene.kind == "middlebury2005" and scene.gt_scale == 3.0
    left = read_image(folder / "view1.png", gray=True).astype(np.float32)
    right = read_image(folder / "view5.png", gray=True).astype(np.float32)
    raw = read_image(folder / "disp1.png").astype(np.float32)
    mask = scene.masks["nonocc"]

    def residual(divisor: float) -> float:
        ys, xs = np.nonzero(mask & (raw > 0))
        xr = np.round(xs - raw[ys, xs] / divisor).astype(int)
        keep = (xr >= 0) & (xr < left.shape[1])
        return float(np.mean(np.abs(left[ys[keep], xs[keep]] - right[ys[keep], xr[keep]])))

    assert residual(3.0) < 0.6 * min(residual(2.0), residual(4.0))


@pytest.mark.slow
def test_mb2005_validation_scenes_match_and_score(run_cli, shared_data, tmp_path):
    scenes = shared_data / "middlebury2005"
    r = run_cli("match", scenes / "Reindeer", scenes / "Books", "-o", tmp_path / "out", "-c", "fast", "-q")
    assert r.code == 0, r.err
    r = run_cli("eval", tmp_path / "out", scenes, "--format", "json")
    assert r.code == 3  # Dolls, Laundry, Moebius have no result
    report = r.json()
    assert sorted(f["name"] for f in report["failures"]) == ["Dolls", "Laundry", "Moebius"]
    scored = {s["name"]: s for s in report["scenes"]}
    assert sorted(scored) == ["Books", "Reindeer"]
    assert all(s["dataset"] == "middlebury2005" and s["nonocc"]["bad1.0"] < 15.0 for s in scored.values())
    assert sum("Third size (4" in note for note in report["notes"]) == 2
