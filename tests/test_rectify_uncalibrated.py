"""rectify --uncalibrated: homographies from matches, one per rig, mapped back; real-data targets."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from stereocli.io.images import read_image, write_image
from stereocli.io.middlebury import read_calib_txt
from stereocli.rectification.uncalibrated import (
    UncalibratedRectification,
    _sample_disparity,
    disparity_to_original,
    estimate_rectification,
    transform_points,
    warp_pair,
)
from stereocli.synth.scenes import render, scene_surfaces


def known_warp(size: tuple[int, int], *, angle: float = 1.0, dy: float = 5.0, scale: float = 1.01,
               perspective: tuple[float, float] = (2e-6, -1e-6)) -> np.ndarray:
    """A small homography of the right view: turned ``angle`` degrees and scaled about the image
    centre, lowered ``dy`` px, with a slight perspective."""
    w, h = size
    cx, cy = (w - 1) / 2, (h - 1) / 2
    c, s = np.cos(np.radians(angle)) * scale, np.sin(np.radians(angle)) * scale
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [perspective[0], perspective[1], 1.0]])
    return np.array([[1, 0, cx], [0, 1, cy + dy], [0, 0, 1.0]]) @ turn @ np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]])


def gt_correspondences(disparity: np.ndarray, mask: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left pixels where ``mask`` holds and their true matches in the right view warped by ``W``
    (the ones that stay inside it), (N, 2) each."""
    h, w = disparity.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    left = np.column_stack([xs[mask], ys[mask]])
    right = transform_points(W, left - np.column_stack([disparity[mask], np.zeros(len(left))]))
    inside = (right[:, 0] >= 0) & (right[:, 0] <= w - 1) & (right[:, 1] >= 0) & (right[:, 1] <= h - 1)
    return left[inside], right[inside]


@pytest.fixture(scope="module")
def synthetic_rig(tmp_path_factory):
    """Two textured scenes of one rig whose right camera is turned, lowered and zoomed (``W``), a
    pair from another rig and a textureless pair, rectified by ``rectify --uncalibrated`` as one
    folder."""
    from stereocli.cli.errors import run_with_error_handling
    from stereocli.cli.main import cli

    w, h = 320, 240
    W = known_warp((w, h))
    root = tmp_path_factory.mktemp("rig")
    scenes = {}
    for name, kind, seed in (("a", "planes", 0), ("b", "curved", 1)):
        out = render(scene_surfaces(kind, w, h, seed), w, h, noise=0.8, seed=seed)
        write_image(root / "rig" / "left" / f"{name}.png", out["left"])
        write_image(root / "rig" / "right" / f"{name}.png", cv2.warpPerspective(out["right"], W, (w, h)))
        scenes[name] = out
    other = render(scene_surfaces("planes", w, h, 2), w, h, noise=0.8, seed=2)
    write_image(root / "rig" / "left" / "d.png", other["left"])
    write_image(root / "rig" / "right" / "d.png",
                cv2.warpPerspective(other["right"], known_warp((w, h), angle=-3, dy=-8, scale=0.98), (w, h)))
    flat = np.full((h, w, 3), 128, np.uint8)
    write_image(root / "rig" / "left" / "c.png", flat)
    write_image(root / "rig" / "right" / "c.png", flat)
    capture = _Capture()
    with capture:
        code = run_with_error_handling(cli, ["rectify", str(root / "rig"), "--uncalibrated", "-o", str(root / "out"),
                                             "--format", "json"])
    return scenes, W, root, code, capture


class _Capture:
    """stdout and stderr of an in-process run, for a module-scoped fixture (capsys is per test)."""

    def __enter__(self):
        import contextlib
        import io

        self.out, self.err = io.StringIO(), io.StringIO()
        self._stack = contextlib.ExitStack()
        self._stack.enter_context(contextlib.redirect_stdout(self.out))
        self._stack.enter_context(contextlib.redirect_stderr(self.err))
        return self

    def __exit__(self, *exc):
        self._stack.close()


@pytest.mark.slow
def test_a_known_homography_is_undone_to_a_tenth_of_a_pixel(synthetic_rig):
    scenes, W, root, code, _ = synthetic_rig
    assert code == 3
    for name, scene in scenes.items():
        record = json.loads((root / "out" / name / "rectification.json").read_text())
        rect = UncalibratedRectification.from_dict(record)
        left, right = gt_correspondences(scene["disparity"], scene["mask"] == 255, W)
        a, b = transform_points(rect.H0, left), transform_points(rect.H1, right)
        dy, d = np.abs(a[:, 1] - b[:, 1]), a[:, 0] - b[:, 0]
        # Every true correspondence lands on one row, at a disparity inside the estimated range.
        assert np.median(dy) < 0.1 and dy.max() < 0.3, (np.median(dy), dy.max())
        span = record["range"]
        assert 0 <= span["min_disp"] <= d.min() and d.max() <= span["max_disp"]
        assert record["pair"]["inliers"] > 0.95 * record["pair"]["matches"] and record["pair"]["dy_median"] < 0.1
        # Rotations about the camera centres: no shear, aspect kept.
        for side in ("left", "right"):
            distortion = record["distortion"][side]
            assert abs(distortion["orthogonality_deg"] - 90) < 0.05 and abs(distortion["aspect"] - 1) < 0.005
    # Shifted so that the scene starts at disparity 0.
    assert min(json.loads((root / "out" / n / "rectification.json").read_text())["range"]["min_disp"]
               for n in scenes) == 0


def test_disparity_to_original_inverts_the_warp():
    # An exactly rectified original pair (d = 0.05 x + 0.02 y + 9), warped by row-preserving
    # homographies; the map back recovers d everywhere and no vertical disparity.
    h, w = 60, 80
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    truth = 0.05 * xs + 0.02 * ys + 9
    H0 = np.array([[1.1, 0.05, 3.0], [0.0, 1.1, 2.0], [0.0, 0.0, 1.0]])
    H1 = np.array([[1.0, 0.0, -4.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ H0
    # The rectified disparity at each rectified pixel p' = H0 p: x(H0 p) − x(H1 (p − d)).
    size = (100, 75)
    rys, rxs = np.mgrid[0:size[1], 0:size[0]].astype(np.float64)
    p = transform_points(np.linalg.inv(H0), np.column_stack([rxs.ravel(), rys.ravel()]))
    d = 0.05 * p[:, 0] + 0.02 * p[:, 1] + 9
    q = transform_points(H1, p - np.column_stack([d, np.zeros(len(d))]))
    rectified = (rxs.ravel() - q[:, 0]).reshape(size[1], size[0]).astype(np.float32)
    dx, dy = disparity_to_original(rectified, H0, H1, (h, w))
    assert np.isfinite(dx).all()
    np.testing.assert_allclose(dx, truth, atol=2e-3)
    np.testing.assert_allclose(dy, 0, atol=2e-3)
    # Unknown rectified disparities stay unknown.
    rectified[:, :50] = np.inf
    dx, _ = disparity_to_original(rectified, H0, H1, (h, w))
    assert np.isinf(dx[:, :10]).all() and np.isfinite(dx[:, -10:]).all()


def test_sampling_blends_one_surface_and_never_two():
    step = np.array([[1.0, 1.5, 20.0, 20.0]] * 3, np.float32)
    values = _sample_disparity(step, np.array([0.5, 1.4, 2.5, 5.0]), np.array([1.0, 1.0, 1.0, 1.0]))
    assert values[0] == pytest.approx(1.25)  # same surface: bilinear
    assert values[1] == pytest.approx(1.5)  # across the edge: the nearest pixel, not 8.7
    assert values[2] == pytest.approx(20.0)
    assert np.isinf(values[3])  # outside the map


def test_rig_folder_one_pair_of_homographies_and_a_textureless_pair(synthetic_rig, tmp_path, run_cli):
    _, _, root, code, capture = synthetic_rig
    out = root / "out"
    assert code == 3, capture.err.getvalue()
    errors = [line for line in capture.err.getvalue().splitlines() if line.startswith("Error")]
    assert errors == ["Error: c: too little texture to rectify: 0 point matches (at least 12)"]
    assert not (out / "c").exists()
    # The pair from another rig is rectified with the rig's homographies, and reported.
    warnings = [line for line in capture.err.getvalue().splitlines() if line.startswith("Warning")]
    assert len(warnings) == 1 and warnings[0].startswith("Warning: d: only ") and "--per-pair" in warnings[0]
    report = json.loads(capture.out.getvalue())
    assert not report["pairs"]["d"]["fits"] and report["pairs"]["a"]["fits"]
    rig = report["estimate"]["rigs"][0]
    assert rig["pairs"] == ["a", "b", "c", "d"] and rig["estimated_from"] == ["a", "b", "d"]
    records = [json.loads((out / n / "rectification.json").read_text()) for n in ("a", "b")]
    assert records[0]["H0"] == records[1]["H0"] and records[0]["H1"] == records[1]["H1"]
    for name, record in zip(("a", "b"), records):
        assert report["pairs"][name]["inliers"] > 100
        assert read_image(out / name / "im0.png").shape[1::-1] == tuple(record["size"])
        calib = read_calib_txt(out / name / "calib.txt")
        assert calib.extra == {"rectification": "uncalibrated"} and calib.baseline == 0
        assert calib.ndisp % 16 == 0 and calib.ndisp > record["range"]["max_disp"]
    run = json.loads((out / "run.json").read_text())
    assert run["config"]["estimate"]["rigs"][0]["estimated_from"] == ["a", "b", "d"]
    assert {i["name"]: i["status"] for i in run["items"]} == {"a": "ok", "b": "ok", "c": "failed", "d": "ok"}
    # A lone textureless pair: that pair fails, exit 1.
    res = run_cli("rectify", root / "rig" / "left" / "c.png", root / "rig" / "right" / "c.png",
                  "--uncalibrated", "-o", tmp_path / "flat")
    assert res.code == 1 and "too little texture" in res.err and "Traceback" not in res.err


def test_triangulate_refuses_an_uncalibrated_calib_txt(synthetic_rig, tmp_path, run_cli):
    _, _, root, _, _ = synthetic_rig
    from stereocli.io.pfm import write_pfm

    size = json.loads((root / "out" / "a" / "rectification.json").read_text())["size"]
    write_pfm(tmp_path / "disp0.pfm", np.full((size[1], size[0]), 20, np.float32))
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", root / "out" / "a" / "calib.txt",
                  "-o", tmp_path / "cloud.ply")
    assert res.code == 1 and not (tmp_path / "cloud.ply").exists()
    assert "written by rectify --uncalibrated" in res.err and "needs a calibration" in res.err
    assert len([line for line in res.err.splitlines() if line.startswith("Error")]) == 1


def test_sift_matches_of_a_rectified_pair(synthetic_rig):
    from stereocli.features.points import match_points

    scene = synthetic_rig[0]["a"]  # its right view as rendered, before the warp
    left, right = scene["left"], scene["right"]
    found = match_points(left, right, method="sift")
    truth = scene["disparity"][np.rint(found.left[:, 1]).astype(int), np.rint(found.left[:, 0]).astype(int)]
    assert len(found) > 100 and np.median(np.abs(found.dy)) < 0.05
    assert np.median(np.abs(found.dx - truth)) < 0.1
    with pytest.raises(ValueError, match="valid: orb, sift"):
        match_points(left, right, method="surf")


def test_option_conflicts_are_usage_errors(tmp_path, run_cli):
    image = tmp_path / "x.png"
    write_image(image, np.zeros((20, 20), np.uint8))
    for args in (["--uncalibrated", "--calib", "rig.yml"], ["--uncalibrated", "--alpha", "1"], [], ["--per-pair"]):
        res = run_cli("rectify", image, image, "-o", tmp_path / "o", *args)
        assert res.code == 2, (args, res.err)


# --------------------------------------------------------------------------- real data

def _sift_dy(left: np.ndarray, right: np.ndarray, *, consistent: bool = True) -> np.ndarray:
    """|y_left − y_right| of independent SIFT matches (ratio test 0.7, mutual best).

    With ``consistent``, the gross mismatches are dropped first: the matches that do not fit a
    fundamental matrix of their own (MAGSAC++, 1 px), fitted freely to this pair. That matrix
    absorbs whatever geometry the pair has, so a pair that is not row-aligned keeps its large
    |dy|; only matches that fit no geometry go. (Without it, p90 measures the mismatch rate:
    1.71 px on PlaytableP as Middlebury rectified it.)"""
    from stereocli.io.images import grey_uint8

    sift = cv2.SIFT_create()
    (ka, da), (kb, db) = (sift.detectAndCompute(grey_uint8(im), None) for im in (left, right))
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    back = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(db, da, k=1)}
    good = [m for m, n in matcher.knnMatch(da, db, k=2) if m.distance < 0.7 * n.distance
            and back.get(m.trainIdx) == m.queryIdx]
    a = np.float32([ka[m.queryIdx].pt for m in good])
    b = np.float32([kb[m.trainIdx].pt for m in good])
    if consistent and len(good) >= 16:
        cv2.setRNGSeed(0)
        _, inliers = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, 1.0, 0.999, 10000)
        if inliers is not None:
            a, b = a[inliers.ravel() > 0], b[inliers.ravel() > 0]
    return np.abs(a[:, 1] - b[:, 1])


#: Scene folder, left and right image and ndisp of the Middlebury pairs the targets are tested on.
MIDDLEBURY = [("middlebury2014/trainingQ/Adirondack", "im0", "im1", 80), ("middlebury2001/tsukuba", "im3", "im4", 16)]


def warped_middlebury_case(folder, left_name: str, right_name: str, ndisp: int) -> dict:
    """Rectify a Middlebury pair whose right view was warped by :func:`known_warp` and measure:
    independent SIFT |dy| (median, p90), the same of the ground truth's correspondences (exact,
    up to the original pair's own rectification), their smallest rectified disparity,
    and the default preset's nonocc bad 2.0 on the original pair and mapped back from the
    rectified one (both scored where the warp left the true match in view)."""
    from stereocli.evaluation.api import evaluate_pair
    from stereocli.evaluation.datasets import load_scene
    from stereocli.matching.config import build_config
    from stereocli.matching.pipeline import match_pair

    left, right = read_image(folder / f"{left_name}.png"), read_image(folder / f"{right_name}.png")
    h, w = left.shape[:2]
    W = known_warp((w, h))
    warped = cv2.warpPerspective(right, W, (w, h), flags=cv2.INTER_LINEAR)
    estimate = estimate_rectification([(left, warped)])
    rect, pair = estimate.rectification, estimate.pairs[0]
    r0, r1, valid0, valid1 = warp_pair(left, warped, rect)
    dy, raw = _sift_dy(r0, r1), _sift_dy(r0, r1, consistent=False)
    gt = load_scene(folder)
    a, b = gt_correspondences(gt.gt, gt.masks["nonocc"] & np.isfinite(gt.gt), W)
    config = build_config()
    original = match_pair(left, right, config, ndisp=ndisp).disparity
    rectified = match_pair(r0, r1, config, ndisp=16 * -(-(pair.max_disp + 1) // 16), left_valid=valid0,
                           right_valid=valid1).disparity
    # Back to the original left image, then through W⁻¹ into the original right image.
    dx, dyy = disparity_to_original(rectified, rect.H0, rect.H1, (h, w))
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    known = np.isfinite(dx)
    back = transform_points(np.linalg.inv(W), np.column_stack([xs[known] - dx[known], ys[known] - dyy[known]]))
    mapped = np.full((h, w), np.inf, np.float32)
    mapped[known] = xs[known] - back[:, 0]
    reach = np.zeros((h, w), bool)
    reach[tuple(np.round(a[:, ::-1]).astype(int).T)] = True
    gt.masks = {k: None if v is None else v & reach for k, v in gt.masks.items()}
    ra, rb = transform_points(rect.H0, a), transform_points(rect.H1, b)
    gt_dy = np.abs(ra[:, 1] - rb[:, 1])
    return {"dy_median": float(np.median(dy)), "dy_p90": float(np.percentile(dy, 90)), "sift_matches": len(dy),
            "raw_dy_median": float(np.median(raw)), "raw_dy_p90": float(np.percentile(raw, 90)),
            "raw_matches": len(raw),
            "gt_dy_median": float(np.median(gt_dy)), "gt_dy_p90": float(np.percentile(gt_dy, 90)),
            "gt_min_disparity": float((ra[:, 0] - rb[:, 0]).min()),
            "bad2_original": evaluate_pair(original, gt).metrics["nonocc"]["bad2.0"],
            "bad2_mapped": evaluate_pair(mapped, gt).metrics["nonocc"]["bad2.0"],
            "range": [pair.min_disp, pair.max_disp],
            "distortion": rect.as_dict()["distortion"]}


@pytest.mark.parametrize("scene,left_name,right_name,ndisp", MIDDLEBURY)
def test_middlebury_pair_with_a_warped_right_view(shared_data, scene, left_name, right_name, ndisp):
    result = warped_middlebury_case(shared_data / scene, left_name, right_name, ndisp)
    assert result["dy_median"] <= 0.3 and result["dy_p90"] <= 1.2, result
    assert result["gt_min_disparity"] >= 0, result  # every true correspondence at disparity >= 0
    # ... and not far above: every px of shift costs a column at the left edge
    assert result["gt_min_disparity"] <= 8, result
    assert result["bad2_mapped"] <= 1.5 * result["bad2_original"], result


def corner_dy_medians(folder) -> dict[str, float | None]:
    """Per rectified pair in ``folder``: the median |y_left − y_right| of its 9x6 chessboard
    corners (None when a board is not found in both images)."""
    medians = {}
    for pair in sorted(p for p in folder.iterdir() if (p / "im0.png").is_file()):
        found = []
        for image in (cv2.imread(str(pair / f"im{i}.png"), cv2.IMREAD_GRAYSCALE) for i in (0, 1)):
            ok, corners = cv2.findChessboardCorners(image, (9, 6))
            if ok:
                criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
                found.append(cv2.cornerSubPix(image, corners, (11, 11), (-1, -1), criteria).reshape(-1, 2))
        medians[pair.name] = float(np.median(np.abs(found[0][:, 1] - found[1][:, 1]))) if len(found) == 2 else None
    return medians


def test_real_rig_folder_boards_come_back_on_rows(shared_data, tmp_path, run_cli):
    folder = shared_data / "calibration" / "opencv-chessboard"
    res = run_cli("rectify", folder, "--uncalibrated", "-o", tmp_path / "rect", "--format", "json")
    assert res.code == 0, res.err
    report = res.json()
    assert len(report["pairs"]) == 13 and len(report["estimate"]["rigs"]) == 1
    records = [json.loads((tmp_path / "rect" / name / "rectification.json").read_text()) for name in report["pairs"]]
    assert len({json.dumps([r["H0"], r["H1"]]) for r in records}) == 1  # one pair of homographies
    for name in report["pairs"]:
        assert read_calib_txt(tmp_path / "rect" / name / "calib.txt").ndisp > report["pairs"][name]["range"]["max_disp"]
    medians = corner_dy_medians(tmp_path / "rect")
    assert len(medians) == 13 and sum(m is not None and m <= 0.8 for m in medians.values()) >= 10, medians
