"""No invented disparities: pixels no right-view pixel can show are unmatched (invalid, or with
a fill their row's nearest visible background; confidence 0; counted), every stage stays in the
searched range, and confidence is 0 wherever the disparity is invalid or was filled."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from stereocli.matching.config import build_config
from stereocli.matching.kernels.maps import fill_background
from stereocli.matching.pipeline import match_pair
from stereocli.matching.visibility import find_unmatched, keep_in_range, right_candidates
from test_sgm import warp_pair


def test_right_candidates_count_the_disparities_that_land_on_the_right_view():
    # 8 px wide, range [2, 5): x − d must lie in [0, 8).
    assert right_candidates((1, 8), 2, 3).tolist() == [[0, 0, 1, 2, 3, 3, 3, 3]]
    # Negative range [-3, -1): x − d is x + 3 or x + 2, inside a 5 px row for x < 3 only.
    assert right_candidates((1, 5), -3, 2).tolist() == [[2, 2, 1, 0, 0]]
    valid = np.ones((2, 8), bool)
    valid[1, :4] = False  # a black rectification border in the right view's second row
    assert right_candidates((2, 8), 2, 3, valid).tolist() == [[0, 0, 1, 2, 3, 3, 3, 3], [0, 0, 0, 0, 0, 0, 1, 2]]


def test_unmatched_strip_and_masks():
    left_valid = np.ones((2, 8), bool)
    left_valid[0, 7] = False
    right_valid = np.ones((2, 8), bool)
    right_valid[1, :4] = False
    outside = find_unmatched((2, 8), 2, 3, left_valid, right_valid).outside_views
    assert outside.astype(int).tolist() == [[1, 1, 0, 0, 0, 0, 0, 1], [1, 1, 1, 1, 1, 1, 0, 0]]


def test_keep_in_range_clamps_beyond_the_subpixel_slack():
    d = np.array([[np.inf, 3.0, 1.5, 0.9, 12.0, 13.2, 40.0]], np.float32)
    out = keep_in_range(d, 2, 10)  # [2, 12) plus 1 px: [1, 12]
    assert out.tolist() == [[np.inf, 3.0, 1.5, 1.0, 12.0, 12.0, 12.0]]
    inside = np.array([[1.0, 12.0, np.inf]], np.float32)
    assert keep_in_range(inside, 2, 10) is inside


@pytest.fixture(scope="module")
def plane_pair():
    # A textured plane at 20 px, searched over [12, 44): the left strip x < 12 has no candidate.
    gt = np.full((48, 96), 20.0, np.float32)
    return warp_pair(gt, seed=2)


def test_strip_without_candidates_is_invalid_or_filled_from_its_row(plane_pair):
    left, right = plane_pair
    kept = match_pair(left, right, build_config(), min_disp=12, ndisp=32, keep_invalid=True, want_confidence=True)
    assert np.isinf(kept.disparity[:, :12]).all()
    assert (kept.confidence[:, :12] == 0).all()
    assert kept.unmatched == {"pixels": 48 * 12}
    filled = match_pair(left, right, build_config(), min_disp=12, ndisp=32, want_confidence=True)
    assert np.isfinite(filled.disparity).all()
    # The nearest visible background of the row: the first pixel right of the strip.
    np.testing.assert_array_equal(filled.disparity[:, :12], np.repeat(filled.disparity[:, 12:13], 12, axis=1))
    assert (filled.confidence[:, :12] == 0).all()
    assert filled.unmatched == {"pixels": 48 * 12}


def test_right_mask_border_is_unmatched(plane_pair):
    left, right = plane_pair
    right_valid = np.ones(left.shape[:2], bool)
    right_valid[:, :30] = False
    result = match_pair(left, right, build_config(), min_disp=0, ndisp=16, right_valid=right_valid,
                        keep_invalid=True)
    # Left x < 30 lands on x − d ≤ x < 30 for every d of [0, 16): a black column.
    assert result.unmatched == {"pixels": 48 * 30}
    assert np.isinf(result.disparity[:, :30]).all()


def test_no_stage_leaves_the_range(plane_pair):
    left, right = plane_pair
    config = build_config(["fast"])
    calls = list(config.refinement)
    median = next(i for i, c in enumerate(calls) if c.stage.name == "median")

    def overshoot(state, params):  # a map stage whose fit runs past both ends of the range
        d = state.disparity.copy()
        d[:, 40:50] = 7.0
        d[:, 50:60] = 60.0
        state.disparity = d

    calls[median] = dataclasses.replace(calls[median], stage=dataclasses.replace(calls[median].stage, func=overshoot))
    result = match_pair(left, right, dataclasses.replace(config, refinement=calls), min_disp=12, ndisp=32)
    assert (result.disparity[:, 40:50] == 11.0).all() and (result.disparity[:, 50:60] == 44.0).all()
    finite = result.disparity[np.isfinite(result.disparity)]
    assert finite.min() >= 11.0 and finite.max() <= 44.0


def test_confidence_is_zero_where_invalid_or_filled(tmp_path):
    from conftest import two_scenes
    from stereocli.io.images import read_image

    scene = two_scenes(tmp_path, 160, 120) / "planes"
    left, right = read_image(scene / "im0.png"), read_image(scene / "im1.png")
    kept = match_pair(left, right, build_config(), ndisp=32, keep_invalid=True, want_confidence=True)
    holes = ~np.isfinite(kept.disparity)
    assert holes.sum() > 100  # the occlusions beside the box
    assert (kept.confidence[holes] == 0).all() and (kept.confidence[~holes] > 0).any()
    filled = match_pair(left, right, build_config(), ndisp=32, want_confidence=True)
    assert np.isfinite(filled.disparity).all()
    assert (filled.confidence[holes] == 0).all()
    np.testing.assert_array_equal(filled.confidence[~holes], kept.confidence[~holes])


def test_fill_background_of_a_cleared_strip_is_the_first_value_on_its_right():
    d = np.array([[np.inf, np.inf, 5.0, 4.0], [np.inf, 3.0, np.inf, 6.0]], np.float32)
    assert fill_background(d).tolist() == [[5.0, 5.0, 5.0, 4.0], [3.0, 3.0, 3.0, 6.0]]


def test_params_json_counts_unmatched_pixels(run_cli, tmp_path):
    from conftest import two_scenes

    scenes = two_scenes(tmp_path / "scenes", 96, 64)
    r = run_cli("match", scenes / "planes", "-o", tmp_path / "out", "--ndisp", "24", "--min-disp", "6")
    assert r.code == 0, r.err
    params = json.loads((tmp_path / "out" / "planes" / "params.json").read_text())
    assert params["unmatched"] == {"pixels": 64 * 6}


def test_calib_txt_mindisp_sets_the_searched_range(run_cli, tmp_path):
    from conftest import two_scenes
    from stereocli.errors import DataError
    from stereocli.io.middlebury import calib_range, read_calib_txt

    scene = two_scenes(tmp_path / "scenes", 96, 64) / "planes"
    calib = scene / "calib.txt"
    assert "mindisp" not in calib.read_text()
    ndisp = read_calib_txt(calib).ndisp
    assert calib_range(read_calib_txt(calib), calib) == (0, ndisp)
    calib.write_text(calib.read_text() + "mindisp=6\n")
    assert calib_range(read_calib_txt(calib), calib) == (6, ndisp - 6)
    r = run_cli("match", scene, "-o", tmp_path / "out")
    assert r.code == 0, r.err
    params = json.loads((tmp_path / "out" / "planes" / "params.json").read_text())
    assert (params["min_disp"], params["ndisp"], params["range"]["source"]) == (6, ndisp - 6, "calib.txt")
    assert params["unmatched"] == {"pixels": 64 * 6}
    calib.write_text(calib.read_text().replace("mindisp=6", f"mindisp={ndisp}"))
    with pytest.raises(DataError, match=f"mindisp={ndisp} leaves no disparity below ndisp={ndisp}"):
        calib_range(read_calib_txt(calib), calib)
