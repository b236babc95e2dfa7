"""Matching next to the part of a rectified image that lies outside its source (a valid mask)."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli.matching.config import build_config
from stereocli.matching.pipeline import extend_rows_into_invalid, match_pair
from test_sgm import warp_pair


def test_rows_are_extended_from_the_nearest_valid_pixel():
    image = np.arange(1, 25, dtype=np.float32).reshape(4, 6)
    valid = np.array([[0, 0, 1, 1, 1, 0],   # border on both sides
                      [1, 1, 0, 0, 0, 1],   # a gap: each side takes its nearer neighbour (ties: left)
                      [0, 0, 0, 0, 0, 0],   # nothing valid: left alone
                      [1, 1, 1, 1, 1, 1]], bool)
    extend_rows_into_invalid(image, valid)
    np.testing.assert_array_equal(image, [[3, 3, 3, 4, 5, 5],
                                          [7, 8, 8, 8, 12, 12],
                                          [13, 14, 15, 16, 17, 18],
                                          [19, 20, 21, 22, 23, 24]])


def test_colour_rows_are_extended_whole_pixels():
    image = np.arange(2 * 4 * 3, dtype=np.float32).reshape(2, 4, 3)
    valid = np.array([[0, 1, 1, 0], [1, 1, 1, 1]], bool)
    expected = image.copy()
    expected[0, 0], expected[0, 3] = image[0, 1], image[0, 2]
    extend_rows_into_invalid(image, valid)
    np.testing.assert_array_equal(image, expected)


@pytest.mark.parametrize("preset", ["default", "fast"])
def test_pixels_matching_next_to_a_black_masked_border_are_found(preset):
    # A plane at 12 px; the right view's first 10 columns are black and masked, as a rectified
    # image's border is. The left pixels whose matches lie just right of it (x in [22, 30))
    # must still be found: their matching windows reach into the black band.
    gt = np.full((64, 120), 12.0, np.float32)
    left, right = warp_pair(gt, seed=4)
    right = right.copy()
    right[:, :10] = 0
    right_valid = np.ones(gt.shape, bool)
    right_valid[:, :10] = False
    d = match_pair(left, right, build_config([preset]), ndisp=32, right_valid=right_valid).disparity
    near = d[4:-4, 22:30]
    assert np.mean(np.abs(np.where(np.isfinite(near), near, 0) - 12.0) <= 1.0) >= 0.95
