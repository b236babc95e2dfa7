"""``stereocli eval`` on tiny synthetic layouts: exit codes, one-line errors, report formats, outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stereocli.cli.errors import run_with_error_handling
from stereocli.cli.main import cli
from stereocli.io.images import write_disparity_png16, write_image
from stereocli.io.pfm import encode_pfm, write_pfm

INF = np.inf


def run(capsys, *args):
    code = run_with_error_handling(cli, [str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def make_mb2014_scene(root: Path, name: str, h: int = 8, w: int = 12, ndisp: int = 8) -> np.ndarray:
    """A tiny Middlebury 2014 scene: GT ramp, one unknown pixel, an occluded column."""
    folder = root / name
    folder.mkdir(parents=True)
    gt = np.tile(np.linspace(1.0, 6.5, w, dtype=np.float32), (h, 1))
    gt[0, 0] = INF
    mask = np.full((h, w), 255, dtype=np.uint8)
    mask[:, 1] = 128
    mask[0, 0] = 0
    write_pfm(folder / "disp0GT.pfm", gt)
    write_image(folder / "mask0nocc.png", mask)
    write_image(folder / "im0.png", np.full((h, w, 3), 90, dtype=np.uint8))
    (folder / "calib.txt").write_text(
        f"cam0=[100 0 6; 0 100 4; 0 0 1]\ncam1=[100 0 6; 0 100 4; 0 0 1]\ndoffs=0\nbaseline=100\n"
        f"width={w}\nheight={h}\nndisp={ndisp}\nisint=0\nvmin=1\nvmax=7\n")
    return gt


@pytest.fixture()
def layout(tmp_path):
    gt_root = tmp_path / "gt"
    gts = {n: make_mb2014_scene(gt_root, n) for n in ("Adirondack", "PianoL", "Motorcycle")}
    res = tmp_path / "out"
    for name, gt in gts.items():
        est = np.where(np.isfinite(gt), gt, 3.0).astype(np.float32)
        if name == "PianoL":
            est = est + 1.5  # every pixel bad at 0.5 and 1.0, not at 2.0
        write_pfm(res / name / "disp0.pfm", est)
        (res / name / "time.txt").write_text("0.5\n")
    return gt_root, res, gts


def test_folder_json_report(capsys, layout):
    gt_root, res, _ = layout
    code, out, err = run(capsys, "eval", res, gt_root, "--format", "json")
    assert code == 0, err
    report = json.loads(out)
    names = [s["name"] for s in report["scenes"]]
    assert sorted(names) == ["Adirondack", "Motorcycle", "PianoL"]
    piano = next(s for s in report["scenes"] if s["name"] == "PianoL")
    assert piano["weight"] == 0.5
    for region in ("nonocc", "all"):
        for key in ("bad0.5", "bad1.0", "bad2.0", "bad4.0", "invalid", "avgerr", "rms"):
            assert key in piano[region]
    assert piano["nonocc"]["bad1.0"] == 100.0 and piano["nonocc"]["bad2.0"] == 0.0
    assert piano["time"] == 0.5
    # weighted: (0 + 0 + 0.5 * 100) / 2.5
    assert report["average"]["nonocc"]["bad1.0"] == pytest.approx(20.0)
    assert report["failures"] == []
    assert "MiddEval3" in report["rules"]


def test_text_csv_markdown(capsys, layout):
    gt_root, res, _ = layout
    code, out, _ = run(capsys, "eval", res, gt_root)
    assert code == 0
    assert "## region: nonocc" in out and "average (weighted)" in out and "s/GD" in out
    code, out, _ = run(capsys, "eval", res, gt_root, "--format", "csv", "--thresholds", "0.25,3")
    assert code == 0
    header = out.splitlines()[0].split(",")
    assert header[:5] == ["scene", "region", "weight", "bad0.25", "bad3.0"]
    assert len(out.splitlines()) == 1 + 2 * 4
    code, out, _ = run(capsys, "eval", res, gt_root, "--format", "markdown")
    assert code == 0 and "| scene | weight |" in out


def test_missing_result_is_a_failure_exit_3(capsys, layout):
    gt_root, res, _ = layout
    (res / "Motorcycle" / "disp0.pfm").unlink()
    code, out, err = run(capsys, "eval", res, gt_root, "--format", "json")
    assert code == 3
    report = json.loads(out)
    assert [f["name"] for f in report["failures"]] == ["Motorcycle"]
    assert "Motorcycle" in err


def test_nothing_scored_exit_1(capsys, layout, tmp_path):
    gt_root, _, _ = layout
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run(capsys, "eval", empty, gt_root)
    assert code == 1
    assert err.strip().splitlines()[-1].startswith("Error: no scene could be scored")


def test_single_pair_and_bad_inputs(capsys, layout, tmp_path):
    gt_root, res, _ = layout
    scene = gt_root / "Adirondack"
    code, out, _ = run(capsys, "eval", res / "Adirondack" / "disp0.pfm", scene, "--format", "json")
    assert code == 0 and json.loads(out)["scenes"][0]["nonocc"]["bad0.5"] == 0.0
    # pair found by name inside a folder of scenes
    code, out, _ = run(capsys, "eval", res / "PianoL" / "disp0.pfm", gt_root, "--format", "json")
    assert code == 0 and json.loads(out)["scenes"][0]["name"] == "PianoL"

    bad = tmp_path / "bad"
    bad.mkdir()
    write_pfm(bad / "wrong_size.pfm", np.ones((3, 5), dtype=np.float32))
    (bad / "nan.pfm").write_bytes(encode_pfm(np.full((8, 12), np.nan, dtype=np.float32)))
    (bad / "corrupt.pfm").write_bytes(b"Pf\n12 8\n-1.0\n" + b"\0" * 10)
    (bad / "garbage.pfm").write_bytes(b"hello")
    for name, needle in (("wrong_size.pfm", "1, 2 or 4"), ("nan.pfm", "NaN"), ("corrupt.pfm", "truncated"),
                         ("garbage.pfm", "not a PFM")):
        code, out, err = run(capsys, "eval", bad / name, scene)
        assert code == 1, name
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("Error:") and needle in lines[0], err
    code, _, err = run(capsys, "eval", tmp_path / "nope.pfm", scene)
    assert code == 1 and "no such file" in err
    code, _, err = run(capsys, "eval", res, gt_root, "--thresholds", "a,b")
    assert code == 2


def test_size_mismatch_in_folder_is_per_scene_failure(capsys, layout):
    gt_root, res, _ = layout
    write_pfm(res / "Motorcycle" / "disp0.pfm", np.ones((3, 5), dtype=np.float32))
    code, out, _ = run(capsys, "eval", res, gt_root, "--format", "json")
    assert code == 3
    fail = json.loads(out)["failures"]
    assert fail[0]["name"] == "Motorcycle" and "1, 2 or 4" in fail[0]["message"]


def test_missing_mask_reports_nonocc_error(capsys, layout):
    gt_root, res, _ = layout
    (gt_root / "Adirondack" / "mask0nocc.png").unlink()
    code, out, _ = run(capsys, "eval", res / "Adirondack", gt_root / "Adirondack", "--format", "json")
    assert code == 3
    report = json.loads(out)
    assert report["scenes"][0]["nonocc"] is None and report["scenes"][0]["all"]["bad0.5"] == 0.0
    assert "mask0nocc.png" in report["failures"][0]["message"]


def test_half_size_results_and_flat_pfm_files(capsys, layout, tmp_path):
    gt_root, _, gts = layout
    flat = tmp_path / "flat"
    for name, gt in gts.items():
        half = np.where(np.isfinite(gt[::2, ::2]), gt[::2, ::2] / 2, INF).astype(np.float32)
        write_pfm(flat / f"{name}.pfm", half)
    code, out, _ = run(capsys, "eval", flat, gt_root, "--format", "json")
    assert code == 0
    ad = next(s for s in json.loads(out)["scenes"] if s["name"] == "Adirondack")
    assert ad["scale_factor"] == 2
    # the ramp step is 0.5 px per column: odd columns differ from their block's left column by
    # exactly 0.5 (not bad); the top-left block is invalid (its GT corner is unknown): 3 of 95
    assert ad["all"]["invalid"] == pytest.approx(100 * 3 / 95)
    assert ad["all"]["bad0.5"] == pytest.approx(100 * 3 / 95)
    assert ad["all"]["avgerr"] == pytest.approx(0.5 * 46 / 92)


def test_error_maps_and_html(capsys, layout, tmp_path):
    gt_root, res, _ = layout
    maps, report_dir = tmp_path / "maps", tmp_path / "html"
    code, _, err = run(capsys, "eval", res, gt_root, "--error-maps", maps, "--html", report_dir)
    assert code == 0, err
    for name in ("Adirondack", "PianoL"):
        for f in ("disparity.png", "gt.png", "error.png", "bad.png"):
            assert (maps / name / f).stat().st_size > 0
    html = (report_dir / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 3 * 5 and "<table>" in html and "src='http" not in html
    code, _, err = run(capsys, "eval", res, gt_root, "--error-maps", maps)
    assert code == 1 and "--overwrite" in err
    code, _, _ = run(capsys, "eval", res, gt_root, "--error-maps", maps, "--overwrite")
    assert code == 0


def make_kitti(root: Path) -> dict[str, np.ndarray]:
    gts = {}
    for name in ("000000_10", "000001_10"):
        occ = np.full((4, 6), 20.0, dtype=np.float32)
        occ[0, 0] = INF
        noc = occ.copy()
        noc[:, 5] = INF
        write_disparity_png16(root / "disp_occ_0" / f"{name}.png", occ)
        write_disparity_png16(root / "disp_noc_0" / f"{name}.png", noc)
        gts[name] = occ
    return gts


def test_kitti_layout(capsys, tmp_path):
    gt_root = tmp_path / "kitti"
    make_kitti(gt_root)
    res = tmp_path / "res"
    est = np.full((4, 6), 20.0, dtype=np.float32)
    est[1, 2] = 25.0  # outlier: 5 > 3 and 25 % > 5 %
    est[2, 1:3] = INF  # filled from neighbours (20) -> inlier, but lowers density
    write_disparity_png16(res / "000000_10.png", est)
    write_disparity_png16(res / "000001_10.png", np.full((4, 6), 20.0, dtype=np.float32))
    code, out, err = run(capsys, "eval", res, gt_root, "--format", "json")
    assert code == 0, err
    report = json.loads(out)
    s0 = next(s for s in report["scenes"] if s["name"] == "000000_10")
    assert s0["all"]["D1"] == pytest.approx(100 / 23)  # 24 pixels, one unknown
    assert s0["all"]["density"] == pytest.approx(100 * 21 / 23)
    assert s0["nonocc"]["D1"] == pytest.approx(100 / 19)
    assert "KITTI" in report["rules"]
    code, out, _ = run(capsys, "eval", res / "000000_10.png", gt_root / "disp_noc_0" / "000000_10.png",
                       "--format", "json")
    assert code == 0 and json.loads(out)["scenes"][0]["all"]["D1"] == pytest.approx(100 / 23)
