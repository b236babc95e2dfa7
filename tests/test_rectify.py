"""rectify: maps, valid masks, calib.txt, row alignment of corresponding points, CLI outputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereocli.io.calib import load_calibration, save_calibration
from stereocli.io.images import read_image
from stereocli.io.middlebury import read_calib_txt
from stereocli.rectification import build_maps
from stereocli.synth.rig import default_rig, render_scene


@pytest.fixture(scope="module")
def scene_pair(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    rig = default_rig()
    save_calibration(out / "rig.yml", rig.calibration())
    render_scene(rig, out_dir=out / "pair")
    return out, rig


@pytest.mark.slow
def test_rectified_points_share_rows(scene_pair):
    _, rig = scene_pair
    calib = rig.calibration()
    maps = build_maps(calib, alpha=0.0)
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.3, 0.3, 200), rng.uniform(0.8, 3.0, 200)]
    pl, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), rig.K1, rig.D1)
    pr, _ = cv2.projectPoints(X, cv2.Rodrigues(rig.R)[0], rig.T, rig.K2, rig.D2)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ql = cv2.undistortPoints(pl, rig.K1, rig.D1, R=maps.rect.R1, P=maps.rect.P1, criteria=crit).reshape(-1, 2)
    qr = cv2.undistortPoints(pr, rig.K2, rig.D2, R=maps.rect.R2, P=maps.rect.P2, criteria=crit).reshape(-1, 2)
    assert np.abs(ql[:, 1] - qr[:, 1]).max() < 1e-6
    # disparity obeys Z = f B / (d + doffs) in the rectified frame
    f, B = maps.rect.P1[0, 0], -maps.rect.P2[0, 3] / maps.rect.P2[0, 0]
    Z = (X @ maps.rect.R1.T)[:, 2]
    np.testing.assert_allclose(f * B / (ql[:, 0] - qr[:, 0]), Z, rtol=1e-6)


def test_valid_masks_follow_alpha():
    calib = default_rig().calibration()
    cropped = build_maps(calib, alpha=0.0)
    full = build_maps(calib, alpha=1.0)
    assert (cropped.valid1 > 0).mean() > 0.99
    assert (full.valid1 > 0).mean() < (cropped.valid1 > 0).mean()
    assert set(np.unique(full.valid1)) <= {0, 255}
    # a mask pixel is valid exactly when its map samples inside the source image
    inside = (full.map1x >= 0) & (full.map1x <= 639) & (full.map1y >= 0) & (full.map1y <= 479)
    assert np.array_equal(full.valid1 > 0, inside)


def test_rectify_cli_writes_scene_folder(scene_pair, run_cli):
    root, rig = scene_pair
    out = root / "rect"
    res = run_cli("rectify", root / "pair" / "left.png", root / "pair" / "right.png", "--calib", root / "rig.yml",
                  "-o", out, "--check", "--min-depth", 0.8)
    assert res.code == 0, res.err
    scene = out / "pair"  # left.png/right.png of one folder: that folder is the scene
    for name in ("im0.png", "im1.png", "valid0.png", "valid1.png", "calib.txt", "check.png"):
        assert (scene / name).is_file(), name
    mb = read_calib_txt(scene / "calib.txt")
    maps = build_maps(rig.calibration(), alpha=0.0)
    assert mb.doffs == pytest.approx(0.0, abs=1e-9)
    assert mb.baseline == pytest.approx(120.0, rel=1e-3)  # metres -> mm
    assert mb.cam0[0, 0] == pytest.approx(maps.rect.P1[0, 0])
    assert mb.ndisp % 16 == 0 and mb.ndisp >= mb.cam0[0, 0] * 0.12 / 0.8
    assert read_image(scene / "im0.png").shape == (480, 640)
    assert read_image(scene / "check.png").shape == (480, 1280, 3)
    # the scene folder is what match reads (valid masks included)
    from stereocli.io.pairs import discover_pairs

    pairs, _ = discover_pairs([str(out)])
    assert pairs[0].left_valid and pairs[0].calib
    # refuses to clobber, resumes with --skip-existing
    assert run_cli("rectify", root / "pair" / "left.png", root / "pair" / "right.png", "--calib",
                   root / "rig.yml", "-o", out).code == 1
    assert run_cli("rectify", root / "pair" / "left.png", root / "pair" / "right.png", "--calib",
                   root / "rig.yml", "-o", out, "--skip-existing").code == 0


def test_rectify_errors(scene_pair, run_cli, tmp_path):
    root, _ = scene_pair
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 120), np.uint8))
    res = run_cli("rectify", small, small, "--calib", root / "rig.yml", "-o", tmp_path / "o")
    assert res.code == 1 and "calibration is for 640x480" in res.err
    res = run_cli("rectify", small, small, "--calib", tmp_path / "none.yml", "-o", tmp_path / "o")
    assert res.code == 1 and "none.yml" in res.err
    res = run_cli("rectify", small, small, "--calib", root / "rig.yml", "-o", tmp_path / "o", "--size", "big")
    assert res.code == 2


def test_rectify_opencv_folder_layout(shared_data, tmp_path, run_cli):
    folder = shared_data / "calibration" / "opencv-chessboard"
    if not folder.is_dir():
        pytest.skip("opencv-chessboard set absent")
    cal = tmp_path / "cv.yml"
    assert run_cli("calibrate", folder, "-o", cal, "--pattern", "9x6", "-q", "--no-cache").code == 0
    res = run_cli("rectify", folder, "--calib", cal, "-o", tmp_path / "rect")
    assert res.code == 0, res.err
    names = sorted(p.name for p in (tmp_path / "rect").iterdir() if p.is_dir())
    assert len(names) == 13 and names[0] == "01"
    assert load_calibration(tmp_path / "rect" / "01" / "calib.txt").units == "unit"
    # Each pair's calib.txt range reaches its board: the corners' disparities (up to ~203 px).
    from stereocli.io.middlebury import read_calib_txt

    reached = 0
    for name in names:
        pair = tmp_path / "rect" / name
        left, right = (cv2.imread(str(pair / f"im{i}.png"), cv2.IMREAD_GRAYSCALE) for i in (0, 1))
        found_l, corners_l = cv2.findChessboardCorners(left, (9, 6))
        found_r, corners_r = cv2.findChessboardCorners(right, (9, 6))
        if found_l and found_r:
            reached += 1
            board = corners_l.reshape(-1, 2)[:, 0] - corners_r.reshape(-1, 2)[:, 0]
            assert board.max() < read_calib_txt(pair / "calib.txt").ndisp, (name, board.max())
    assert reached >= 10
    # This project's own rectification raises no row-alignment warning.
    res = run_cli("match", tmp_path / "rect", "-o", tmp_path / "disp", "-c", "fast")
    assert res.code == 0 and "not aligned" not in res.err, res.err
