"""``triangulate`` writes only what the match supports: exact counts of the pixels dropped by
reason, in the library, the summary and the run record."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stereocli.io.middlebury import MiddleburyCalib, write_calib_txt
from stereocli.io.pfm import write_pfm
from stereocli.triangulation import DROP_REASONS, RectifiedGeometry, triangulate

GEOM = RectifiedGeometry(f=100.0, cx=4.5, cy=1.0, baseline=2.0, doffs=0.0)
INF = np.inf


def test_each_reason_counts_exactly():
    d = np.array([
        # x: 0    1     2     3     4     5     6     7     8     9
        [INF, 2.0, 3.0, 20.0, 1.5, 0.4, 5.0, 5.0, 5.0, 5.0],  # invalid, unmatched (x − d < −0.5) ×2,
        #                                                        outside the range, at infinity ×2
        [3.0, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0],   # x 0 lands left of the image, the rest on column 1
        [0.0, 0.9, 2.5, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0, 3.0],   # at infinity ×2, beyond 70, x 8 masked, x 9 not confident
    ], np.float32)
    confidence = np.ones(d.shape, np.float32)
    confidence[2, 9] = 0.0
    right_valid = np.ones(d.shape, bool)
    right_valid[1, 1] = False  # a black column of the right view's second row
    left_valid = np.ones(d.shape, bool)
    left_valid[2, 8] = False
    depth, cloud = triangulate(d, GEOM, disparity_range=(0, 16), right_valid=right_valid, left_valid=left_valid,
                               confidence=confidence, min_confidence=0.5, max_depth=70.0)
    assert list(cloud.dropped) == list(DROP_REASONS)
    assert cloud.dropped == {"invalid": 1, "outside_range": 1, "unmatched": 2 + 10 + 1, "at_infinity": 2 + 2,
                             "low_confidence": 1, "depth_limits": 1}
    kept = np.isfinite(depth)
    assert kept.astype(int).tolist() == [[0, 0, 0, 0, 0, 0, 1, 1, 1, 1],
                                         [0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
                                         [0, 0, 0, 1, 1, 1, 1, 1, 0, 0]]
    assert cloud.points.shape == (9, 3) and sum(cloud.dropped.values()) == d.size - 9
    np.testing.assert_allclose(depth[2, 3:8], 200.0 / 3, rtol=1e-6)
    np.testing.assert_allclose(depth[0, 6:], 40.0, rtol=1e-6)


def test_without_support_only_invalid_and_no_depth_are_dropped():
    d = np.array([[INF, 0.0, 0.5, 3.0, 200.0]], np.float32)
    _, cloud = triangulate(d, GEOM, disparity_range=(0, 16), supported=False)
    assert cloud.dropped == {"invalid": 1, "outside_range": 0, "unmatched": 0, "at_infinity": 1,
                             "low_confidence": 0, "depth_limits": 0}
    assert cloud.points.shape == (3, 3)


def test_subpixel_slack_at_the_range_ends():
    d = np.full((1, 40), 12.0, np.float32)
    d[0, 30:34] = [9.0, 8.9, 26.0, 26.1]
    _, cloud = triangulate(d, GEOM, disparity_range=(10, 16))
    assert cloud.dropped["outside_range"] == 2  # [10, 26) plus 1 px: 9.0 and 26.0 stay, 8.9 and 26.1 go
    assert cloud.dropped["unmatched"] == 12  # x − 12 < −0.5 for x < 12


def _scene(folder, disparity, *, params: dict | None = None, confidence=None, ndisp=16):
    folder.mkdir(parents=True, exist_ok=True)
    write_pfm(folder / "disp0.pfm", disparity)
    h, w = disparity.shape
    cam = np.array([[100.0, 0, w / 2], [0, 100.0, h / 2], [0, 0, 1]])
    write_calib_txt(folder / "calib.txt", MiddleburyCalib(cam0=cam, cam1=cam, baseline=50.0, width=w, height=h,
                                                          ndisp=ndisp))
    if params is not None:
        (folder / "params.json").write_text(json.dumps(params))
    if confidence is not None:
        write_pfm(folder / "conf0.pfm", confidence)


def _disparity() -> np.ndarray:
    d = np.full((6, 12), 4.0, np.float32)
    d[0, 6] = np.inf
    d[1, 6] = 30.0  # outside [2, 2 + 16) of params.json, inside calib.txt's [0, 32)
    d[2, 6] = 0.5  # at infinity (and outside [2, 18))
    return d


def test_folder_mode_counts_by_reason_in_summary_and_run_record(run_cli, tmp_path):
    conf = np.ones((6, 12), np.float32)
    conf[5, 11] = 0.1
    _scene(tmp_path / "disp" / "a", _disparity(), params={"range": {"min_disp": 2, "ndisp": 16}}, confidence=conf,
           ndisp=32)
    r = run_cli("triangulate", tmp_path / "disp", "-o", tmp_path / "out", "--summary", "--min-confidence", "0.5")
    assert r.code == 0, r.err
    summary = json.loads((tmp_path / "out" / "a" / "summary.json").read_text())
    # x − 4 < −0.5 for x < 4: 4 columns × 6 rows, less the three odd pixels above (none at x < 4).
    expected = {"invalid": 1, "outside_range": 2, "unmatched": 24, "at_infinity": 0, "low_confidence": 1,
                "depth_limits": 0}
    assert summary["dropped"] == expected
    assert summary["points"] == 72 - sum(expected.values())
    assert summary["range"]["min_disp"] == 2 and summary["range"]["ndisp"] == 16
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    [item] = record["items"]
    assert item["details"]["dropped"] == expected
    assert "(pixels dropped: 1 invalid, 2 outside_range, 24 unmatched, 1 low_confidence)" in r.err
    # Without params.json the calib.txt gives the range, [0, 32): 30 lands left of the right
    # image (x 6), 0.5 is at infinity.
    (tmp_path / "disp" / "a" / "params.json").unlink()
    r = run_cli("triangulate", tmp_path / "disp", "-o", tmp_path / "out2", "--summary")
    assert r.code == 0, r.err
    summary = json.loads((tmp_path / "out2" / "a" / "summary.json").read_text())
    assert summary["dropped"] == {"invalid": 1, "outside_range": 0, "unmatched": 25, "at_infinity": 1,
                                  "low_confidence": 0, "depth_limits": 0}


def test_single_file_mode_reads_conf0_beside_it(run_cli, tmp_path):
    import plyfile

    conf = np.full((6, 12), 0.75, np.float32)
    _scene(tmp_path / "a", _disparity(), confidence=conf)
    r = run_cli("triangulate", tmp_path / "a" / "disp0.pfm", "-o", tmp_path / "a.ply")
    assert r.code == 0, r.err
    vertex = plyfile.PlyData.read(str(tmp_path / "a.ply"))["vertex"]
    assert "confidence" in [p.name for p in vertex.properties] and (vertex["confidence"] == 0.75).all()


def test_min_confidence_needs_a_map(run_cli, tmp_path):
    _scene(tmp_path / "a", _disparity())
    r = run_cli("triangulate", tmp_path / "a" / "disp0.pfm", "-o", tmp_path / "a.ply", "--min-confidence", "0.2")
    assert r.code == 1
    assert "--min-confidence needs a confidence map" in r.err


@pytest.mark.parametrize("option, value", [("--min-depth", "-1"), ("--max-depth", "0"), ("--min-confidence", "1.5")])
def test_bounds_are_checked_and_shown(run_cli, tmp_path, option, value):
    _scene(tmp_path / "a", _disparity())
    r = run_cli("triangulate", tmp_path / "a" / "disp0.pfm", "-o", tmp_path / "a.ply", option, value)
    assert r.code == 2 and option in r.err
    help_text = run_cli("triangulate", "--help").out
    assert "[x>=0]" in help_text and "[x>0]" in help_text and "[0<=x<=1]" in help_text
    assert "x<=None" not in help_text
