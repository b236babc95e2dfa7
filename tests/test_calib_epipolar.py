"""The calibration report names the views and corners behind a rectified |dy| above 1 px, warns,
and gives each view's max |dy|."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from stereocli.calib.pattern import Pattern
from stereocli.calib.stereo import View, _epipolar_warning, rectified_epipolar_error
from stereocli.rectification import rectified_calibration
from stereocli.synth.rig import default_rig


def _views(rig, n: int = 3) -> list[View]:
    """Exact projections of a 9x6 board (4 cm squares) at ``n`` poses into both cameras."""
    board = Pattern(9, 6, 0.04).object_points().astype(np.float64)
    views = []
    for k in range(n):
        rvec = np.array([0.1 * k, -0.15, 0.05])
        tvec = np.array([-0.15 + 0.05 * k, -0.1, 0.7 + 0.1 * k])
        left, _ = cv2.projectPoints(board, rvec, tvec, rig.K1, rig.D1)
        R_board = cv2.Rodrigues(rvec)[0]
        in_right = (rig.R @ (R_board @ board.T + tvec[:, None])).T + rig.T
        right, _ = cv2.projectPoints(in_right, np.zeros(3), np.zeros(3), rig.K2, rig.D2)
        views.append(View(f"{k + 1:02d}", f"left{k + 1:02d}.png", f"right{k + 1:02d}.png", board.astype(np.float32),
                          left.reshape(-1, 2).astype(np.float32), right.reshape(-1, 2).astype(np.float32)))
    return views


def test_views_and_corners_above_the_limit_are_named():
    rig = default_rig()
    calib = rectified_calibration(rig.calibration())
    views = _views(rig)
    clean = rectified_epipolar_error(calib, views)
    assert max(clean["per_view"].values()) < 0.01 and clean["above_limit"] == []
    views[1].right_points[17, 1] += 2.5  # a corner detected 2.5 px off in the right image
    views[1].right_points[40, 1] -= 1.4
    views[2].right_points[3, 1] += 0.6  # under the limit: not named
    epi = rectified_epipolar_error(calib, views)
    assert list(epi["per_view"]) == ["01", "02", "03"]
    assert epi["per_view"]["01"] < 0.01 and 0.5 < epi["per_view"]["03"] < 0.7
    assert epi["per_view"]["02"] == pytest.approx(2.5, abs=0.1) and epi["max"] == epi["per_view"]["02"]
    [named] = epi["above_limit"]
    assert (named["name"], named["left_image"], named["right_image"]) == ("02", "left02.png", "right02.png")
    assert [c["index"] for c in named["corners"]] == [17, 40]
    assert named["corners"][0]["x"] == pytest.approx(float(views[1].left_points[17, 0]))
    assert named["corners"][1]["dy"] == pytest.approx(1.4, abs=0.1)


def test_warning_text():
    above = [{"name": "05", "left_image": "l", "right_image": "r", "max": 3.6,
              "corners": [{"index": i, "x": 10.0 * i, "y": 20.4, "dy": 3.6 - 0.5 * i} for i in range(5)]},
             {"name": "02", "left_image": "l", "right_image": "r", "max": 1.2,
              "corners": [{"index": 7, "x": 400.6, "y": 391.2, "dy": 1.2}]}]
    assert _epipolar_warning(above) == (
        "rectified |y_left - y_right| above 1 px at 6 corner(s) of 2 view(s): 05 (corner 0 at (0, 20) 3.60 px, "
        "corner 1 at (10, 20) 3.10 px, corner 2 at (20, 20) 2.60 px and 2 more); 02 (corner 7 at (401, 391) "
        "1.20 px); rows that far apart lose their matches: check these detections (corner index in detection "
        "order, left-image pixels) or calibrate without these views")


def test_real_rig_report_names_views_02_and_05(shared_data, tmp_path, run_cli):
    folder = shared_data / "calibration" / "opencv-chessboard"
    r = run_cli("calibrate", folder, "-o", tmp_path / "rig.yml", "--pattern", "9x6", "--square", "25mm")
    assert r.code == 0, r.err
    report = json.loads((tmp_path / "rig.report.json").read_text())
    per_view = {p["name"]: p["epipolar_error_max"] for p in report["per_view"]}
    assert len(per_view) == 13 and max(per_view.values()) == pytest.approx(report["rectified"]["epipolar_error_max"])
    assert {v["name"] for v in report["rectified"]["above_limit"]} == {"02", "05"}
    assert per_view["05"] == pytest.approx(3.65, abs=0.05)
    assert all(dy <= 1.0 for name, dy in per_view.items() if name not in ("02", "05"))
    assert "Warning: rectified |y_left - y_right| above 1 px at " in r.err and " view(s): 02 (corner " in r.err
    assert "max |dy| 3.65 > 1" in r.out  # the report's per-view table (stdout)
