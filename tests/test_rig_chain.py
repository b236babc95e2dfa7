"""Acceptance: a rig end to end with the README's default options (calibrate → rectify → match →
triangulate), on the real 13-pair chessboard rig in ../shared/data and on the bundled synthetic
rig, whose boards' true poses are known.

Every cloud holds only points inside the depth range the searched disparities allow and none
deeper than 100× the board; the dense disparity at the detected board corners agrees with the
corner-to-corner disparity, and the squares measured in 3-D from it have their true size."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import SAMPLES
from stereocli.calib.pattern import Pattern, detect
from stereocli.io.images import read_image
from stereocli.io.middlebury import read_calib_txt
from stereocli.io.pfm import read_pfm

pytestmark = pytest.mark.slow


@dataclass
class Board:
    """One pair's board, measured: corner disparity errors (px), square size errors (fraction),
    the board's depth, and the depths of its cloud."""

    name: str
    corner_errors: np.ndarray
    square_errors: np.ndarray
    board_depth: float
    cloud_depths: np.ndarray
    depth_bounds: tuple[float, float]
    corners_3d: np.ndarray  # (rows, cols, 3) from the dense disparity, rectified left camera frame


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return (image[y0, x0] * (1 - fx) * (1 - fy) + image[y0, x0 + 1] * fx * (1 - fy)
            + image[y0 + 1, x0] * (1 - fx) * fy + image[y0 + 1, x0 + 1] * fx * fy)


def _chain(run_cli, photos: Path, out: Path, square: str) -> None:
    """The README's chain with default options."""
    steps = [("calibrate", photos, "-o", out / "rig.yml", "--pattern", "9x6", "--square", square, "-q"),
             ("rectify", photos, "--calib", out / "rig.yml", "-o", out / "rect", "-q"),
             ("match", out / "rect", "-o", out / "disp", "-q"),
             ("triangulate", out / "disp", "--scenes", out / "rect", "-o", out / "clouds", "-q")]
    for step in steps:
        r = run_cli(*step)
        assert r.code == 0, (step[0], r.err)


def _boards(out: Path, pattern: Pattern) -> list[Board]:
    import plyfile

    boards = []
    for scene in sorted(p for p in (out / "rect").iterdir() if p.is_dir()):
        left, right = read_image(scene / "im0.png"), read_image(scene / "im1.png")
        corners_left, _, _ = detect(left, pattern)
        corners_right, _, _ = detect(right, pattern)
        assert corners_left is not None and corners_right is not None, scene.name
        calib = read_calib_txt(scene / "calib.txt")
        f, baseline, doffs = calib.cam0[0, 0], calib.baseline, calib.doffs
        cx, cy = calib.cam0[0, 2], calib.cam0[1, 2]
        truth = corners_left[:, 0] - corners_right[:, 0]
        disparity = read_pfm(out / "disp" / scene.name / "disp0.pfm")
        x, y = corners_left[:, 0].astype(np.float64), corners_left[:, 1].astype(np.float64)
        dense = _bilinear(disparity.astype(np.float64), x, y)
        z = f * baseline / (dense + doffs)
        points = np.stack([z * (x - cx) / f, z * (y - cy) / f, z], 1).reshape(pattern.rows, pattern.cols, 3)
        sides = np.concatenate([np.linalg.norm(np.diff(points, axis=1), axis=2).ravel(),
                                np.linalg.norm(np.diff(points, axis=0), axis=2).ravel()])
        params = json.loads((out / "disp" / scene.name / "params.json").read_text())
        low, high = params["min_disp"], params["min_disp"] + params["ndisp"]
        # Depths the searched range allows: [min_disp - 1, min_disp + ndisp] with the sub-pixel
        # slack, and d + doffs >= 2 px (triangulate's at_infinity).
        bounds = (f * baseline / (high + doffs), f * baseline / max(low - 1 + doffs, 2.0))
        cloud = plyfile.PlyData.read(str(out / "clouds" / scene.name / "cloud.ply"))["vertex"]
        boards.append(Board(scene.name, np.abs(dense - truth), np.abs(sides - pattern.square) / pattern.square,
                            float(np.median(f * baseline / (truth + doffs))), np.asarray(cloud["z"], np.float64),
                            bounds, points))
    return boards


def _check(boards: list[Board], n_pairs: int) -> None:
    assert len(boards) == n_pairs
    for board in boards:
        low, high = board.depth_bounds
        depths = board.cloud_depths
        assert depths.size > 0, board.name
        assert depths.min() >= low * (1 - 1e-5) and depths.max() <= high * (1 + 1e-5), (board.name, low, high)
        assert depths.max() < 100 * board.board_depth, board.name
    corners = np.concatenate([b.corner_errors for b in boards])
    squares = np.concatenate([b.square_errors for b in boards])
    assert np.median(corners) <= 0.25 and np.percentile(corners, 90) <= 0.75
    assert np.median(squares) <= 0.015 and np.percentile(squares, 90) <= 0.04


def test_real_rig(shared_data, tmp_path, run_cli):
    _chain(run_cli, shared_data / "calibration" / "opencv-chessboard", tmp_path, "25mm")
    _check(_boards(tmp_path, Pattern(9, 6, 25.0)), 13)


def test_synthetic_rig_against_its_true_poses(tmp_path, run_cli):
    from stereocli.io.calib import load_calibration
    from stereocli.synth.rig import Board as SyntheticBoard
    from stereocli.synth.rig import board_poses, default_rig

    _chain(run_cli, SAMPLES / "rig", tmp_path, "40mm")
    boards = _boards(tmp_path, Pattern(9, 6, 40.0))
    _check(boards, 12)
    # The exact answer: each board's corners where its true pose puts them, in the rectified left
    # camera frame of the calibration the chain estimated (mm).
    board = SyntheticBoard()
    R1 = load_calibration(tmp_path / "rig.yml").R1
    errors = []
    for measured, (Rb, tb) in zip(boards, board_poses(default_rig(), board, 12, seed=0)):
        corners = (Rb @ Pattern(9, 6, board.square).object_points().T.astype(np.float64) + tb[:, None]).T
        truth = (R1 @ corners.T).T * 1000.0
        found = measured.corners_3d.reshape(-1, 3)
        # Nearest true corner (the detector may number a board from its other end).
        gaps = np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=2).min(axis=1)
        errors.append(gaps / found[:, 2])
    errors = np.concatenate(errors)
    assert np.median(errors) <= 0.005 and np.percentile(errors, 90) <= 0.02
