"""calibrate: synthetic rig with known K, D, R, T; OpenCV's 9x6 sample set; bad inputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from stereocli.calib import CalibOptions, Pattern, calibrate_folder, detect_all
from stereocli.cli.main import cli
from stereocli.errors import DataError
from stereocli.io.calib import load_calibration, rotation_angle_deg
from stereocli.io.pairs import find_calibration_pairs
from stereocli.synth.rig import render_rig


@pytest.fixture(scope="module")
def rig_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rig")
    render_rig(out, n_pairs=12, seed=0)
    return out


@pytest.fixture(scope="module")
def calibrated(rig_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("cal") / "rig.yml"
    res = CliRunner().invoke(cli, ["calibrate", str(rig_dir), "-o", str(out), "--pattern", "9x6",
                                   "--square", "0.04m", "--format", "json", "-q"])
    assert res.exit_code == 0, res.output
    return out, json.loads(res.stdout)


def _distortion_px(n: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Pixel displacement caused by distortion alone at normalised points n (N, 2)."""
    pts = np.c_[n, np.ones(len(n))]
    distorted, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    ideal, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.zeros(5))
    return (distorted - ideal).reshape(-1, 2)


@pytest.mark.slow
def test_synthetic_rig_recovers_truth(rig_dir, calibrated):
    path, report = calibrated
    truth = load_calibration(rig_dir / "truth.yml")
    est = load_calibration(path)
    assert est.units == "m" and report["views_used"] == 12 and report["not_found"] == []
    for key in ("K1", "K2"):
        e, t = getattr(est, key), getattr(truth, key)
        for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)):  # fx, fy, cx, cy within 0.5 %
            assert abs(e[i, j] / t[i, j] - 1) < 0.005, (key, i, j, e[i, j], t[i, j])
    assert abs(est.baseline / truth.baseline - 1) < 0.005
    assert rotation_angle_deg(est.R, truth.R) < 0.1
    assert report["rms"]["stereo"] < 0.15
    assert report["rectified"]["epipolar_error_mean"] < 0.1
    # Distortion: k1 close, and the distortion displacement field (truth up to ~8 px) agrees
    # within 0.15 px everywhere inside the region the board corners covered.
    for side, D_true, D_est, K_true in (("left", truth.D1, est.D1, truth.K1), ("right", truth.D2, est.D2, truth.K2)):
        assert abs(D_est[0] - D_true[0]) < 0.01
        dets = detect_all(sorted(str(p) for p in (rig_dir / side).glob("*.png")), Pattern(9, 6, 0.04), progress=False)
        hull = cv2.convexHull(np.concatenate([d.corners for d in dets.values()]))
        xs, ys = np.meshgrid(np.arange(0, 640, 8.0), np.arange(0, 480, 8.0))
        grid = np.c_[xs.ravel(), ys.ravel()]
        inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0 for x, y in grid])
        n = cv2.undistortPoints(grid[inside].reshape(-1, 1, 2), K_true, D_true,
                                criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)).reshape(-1, 2)
        true_field = _distortion_px(n, K_true, D_true)
        est_field = _distortion_px(n, K_true, D_est)
        assert np.abs(true_field).max() > 3.0
        assert np.abs(est_field - true_field).max() < 0.15, side


def test_report_contents_and_files(calibrated):
    path, report = calibrated
    assert len(report["per_view"]) == 12 and all({"left", "right", "outlier"} <= set(v) for v in report["per_view"])
    assert report["baseline"]["units"] == "m" and report["baseline"]["direction"][0] < -0.99
    assert report["warnings"] == []
    on_disk = json.loads(path.with_name("rig.report.json").read_text())
    assert on_disk["rms"] == report["rms"]
    assert path.with_name(".stereocli-detections.json").is_file()


def test_detection_cache_reused_with_other_flags(rig_dir, tmp_path):
    cache = tmp_path / "cache.json"
    paths = sorted(str(p) for p in (rig_dir / "left").glob("*.png"))[:3]
    first = detect_all(paths, Pattern(9, 6), cache=cache, progress=False)
    again = detect_all(paths, Pattern(9, 6, square=0.5), cache=cache, progress=False)  # square does not matter
    assert not any(d.cached for d in first.values()) and all(d.cached for d in again.values())
    for p in paths:
        np.testing.assert_allclose(first[p].corners, again[p].corners, atol=1e-5)
    other = detect_all(paths, Pattern(8, 6), cache=cache, progress=False)  # another pattern: detected again
    assert not any(d.cached for d in other.values()) and not any(d.found for d in other.values())


def test_max_view_error_drops_and_swap_warns(rig_dir):
    res = calibrate_folder(rig_dir, Pattern(9, 6, 0.04, units="m"), CalibOptions(max_view_error=0.05), progress=False)
    assert res.report["dropped"] and res.report["views_used"] < 12
    assert all(max(v["left"], v["right"]) <= 0.05 for v in res.report["per_view"])
    swapped = calibrate_folder(rig_dir, Pattern(9, 6, 0.04, units="m"), progress=False, swap=True)
    assert swapped.calibration.T[0] > 0
    assert any("swapped" in w for w in swapped.report["warnings"])


def test_pairing_single_folder_by_number(tmp_path):
    for name in ("left01.jpg", "left02.jpg", "right01.jpg", "right02.jpg", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    pairs = find_calibration_pairs(tmp_path)
    assert [(n, Path(left).name, Path(right).name) for n, left, right in pairs] == [
        ("01", "left01.jpg", "right01.jpg"), ("02", "left02.jpg", "right02.jpg")]


def test_bad_inputs(rig_dir, tmp_path, run_cli):
    def _invoke(*args):
        r = run_cli("calibrate", *args)
        r.output = r.err
        r.exit_code = r.code
        assert len(r.err.strip().splitlines()) == 1  # one-line errors
        return r

    out = tmp_path / "o.yml"
    # wrong pattern size: the target is found nowhere
    res = _invoke(rig_dir, "-o", out, "--pattern", "10x7", "--no-cache", "--detector", "classic")
    assert res.exit_code == 1 and "not found in any of the 24 images" in res.output
    # malformed pattern
    res = _invoke(rig_dir, "-o", out, "--pattern", "nine-by-six")
    assert res.exit_code == 2 and "COLSxROWS" in res.output
    # mismatched left/right counts
    bad = tmp_path / "unpaired"
    shutil.copytree(rig_dir, bad)
    (bad / "right" / "12.png").unlink()
    res = _invoke(bad, "-o", out, "--pattern", "9x6")
    assert res.exit_code == 1 and "do not pair up" in res.output and "12.png" in res.output
    # mixed image sizes
    mixed = tmp_path / "mixed"
    shutil.copytree(rig_dir, mixed, ignore=lambda d, names: [n for n in names if n[:2] in ("04", "05", "06", "07",
                                                                                      "08", "09", "10", "11", "12")])
    im = cv2.imread(str(mixed / "left" / "03.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(mixed / "left" / "03.png"), cv2.resize(im, (320, 240)))
    res = _invoke(mixed, "-o", out, "--pattern", "9x6", "--no-cache")
    assert res.exit_code == 1 and "mixed image sizes" in res.output
    # too few views
    few = tmp_path / "few"
    for side in ("left", "right"):
        (few / side).mkdir(parents=True)
        for k in (1, 2):
            shutil.copy(rig_dir / side / f"{k:02d}.png", few / side)
    res = _invoke(few, "-o", out, "--pattern", "9x6", "--no-cache")
    assert res.exit_code == 1 and "need at least 3" in res.output
    # unknown output format, missing folder
    res = _invoke(rig_dir, "-o", tmp_path / "o.cfg", "--pattern", "9x6")
    assert res.exit_code == 2
    res = _invoke(tmp_path / "nothere", "-o", out, "--pattern", "9x6")
    assert res.exit_code == 1 and "not a folder" in res.output


def test_unreadable_image_is_named(rig_dir, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(rig_dir, broken)
    (broken / "left" / "05.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match="05.png"):
        calibrate_folder(broken, Pattern(9, 6), progress=False)


@pytest.mark.shared_data
def test_opencv_sample_set(shared_data, tmp_path):
    folder = shared_data / "calibration" / "opencv-chessboard"
    if not folder.is_dir():
        pytest.skip("opencv-chessboard set absent")
    res = CliRunner().invoke(cli, ["calibrate", str(folder), "-o", str(tmp_path / "cv.yml"), "--pattern", "9x6",
                                   "--square", "1", "--format", "json", "-q", "--cache", str(tmp_path / "c.json")])
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout)
    assert report["views_used"] == 13 and len(report["per_view"]) == 13
    assert report["rms"]["stereo"] < 1.0
    assert report["rectified"]["epipolar_error_mean"] < 0.5
    assert report["baseline"]["direction"][0] < -0.99  # left camera really is on the left
    # view 02 is the known bad one in this set
    assert [v["name"] for v in report["per_view"] if v["outlier"]] == ["02"]


def test_fisheye_and_joint_models_run(rig_dir):
    for opts in (CalibOptions(fisheye=True), CalibOptions(joint=True, rational=True)):
        res = calibrate_folder(rig_dir, Pattern(9, 6, 0.04, units="m"), opts, progress=False)
        assert abs(res.calibration.baseline / 0.12 - 1) < 0.005, opts
        assert res.report["rectified"]["epipolar_error_mean"] < 0.1
    assert res.calibration.D1.size >= 8  # rational model: k1..k6 (OpenCV 5 pads to 14)
