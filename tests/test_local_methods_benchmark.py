"""benchmarks/local_methods.py: the classic local refinement chain and the derived depth-discontinuity
mask used by ``--breakdown``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "local_methods.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("local_methods_benchmark", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_disc_mask_is_a_dilated_band_around_jumps(bench):
    gt = np.full((20, 40), 5.0, np.float32)
    gt[:, 20:] = 10.0  # a 5 px jump between columns 19 and 20
    nonocc = np.ones(gt.shape, bool)
    disc = bench.derive_disc_mask(gt, nonocc)
    expected = np.zeros(gt.shape, bool)
    expected[:, 15:25] = True  # both jump pixels, widened by 4 px on each side (9-wide window)
    np.testing.assert_array_equal(disc, expected)


def test_disc_mask_ignores_small_steps_and_unknown_gt(bench):
    gt = np.full((12, 30), 5.0, np.float32)
    gt[:, 10:] = 7.0  # a 2 px step is not a discontinuity (jump must exceed 2 px)
    gt[:, 25:] = np.inf  # unknown GT next to known GT is no jump either
    assert not bench.derive_disc_mask(gt, np.ones(gt.shape, bool)).any()


def test_disc_mask_stays_inside_nonocc(bench):
    gt = np.zeros((15, 15), np.float32)
    gt[7:, :] = 9.0  # a horizontal edge: vertical neighbours jump
    nonocc = np.ones(gt.shape, bool)
    nonocc[:, :5] = False
    disc = bench.derive_disc_mask(gt, nonocc)
    assert not disc[:, :5].any()
    assert disc[2:12, 5:].all() and not disc[:2].any() and not disc[12:].any()


SUBPIXEL_STEPS = {"subpixel", "plane_smooth"}


@pytest.mark.parametrize("subpixel", [True, False])
def test_every_method_runs_wta_lr_check_then_hole_filling(bench, subpixel):
    for method in bench.METHODS:
        config = bench.config_for(method, 1, subpixel)
        assert config.optimizer.stage.name == "wta", method
        stages = [c.stage for c in config.refinement]
        names = [s.name for s in stages]
        fills = [i for i, s in enumerate(stages) if s.traits.fills_holes]
        assert fills and names.count("lr_check") == 1, (method, names)
        assert names.index("lr_check") < fills[0], (method, names)  # fill the holes the check leaves
        # the check decides on the WTA winners, not on the sub-pixel values (they run first)
        assert config.refinement[names.index("lr_check")].params.compare == "integer", method
        assert bool(SUBPIXEL_STEPS & set(names)) == subpixel, (method, names)


def _slanted_pair(h=64, w=128, seed=0):
    """Textured slanted plane: right(x_r) = left(x_r + 4 + 0.04·x_r), so the left-view disparity
    at column x is x − (x − 4)/1.04 (3.8 … 8.7 px across the image: every fraction equally often)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 40, 3)).astype(np.float32), (0, 0), 1.5)
    tex = np.clip((tex - tex.mean()) * 3 + 128, 0, 255).astype(np.float32)
    xs = np.arange(w, dtype=np.float32)
    mapx = np.tile(xs + 20 + 4.0 + 0.04 * xs, (h, 1)).astype(np.float32)
    mapy = np.tile(np.arange(h, dtype=np.float32)[:, None], (1, w))
    left = np.ascontiguousarray(tex[:, 20:20 + w])
    right = cv2.remap(tex, mapx, mapy, cv2.INTER_CUBIC)
    gt = np.tile(xs - (xs - 4.0) / 1.04, (h, 1)).astype(np.float32)
    mask = np.zeros((h, w), bool)
    mask[10:-10, 30:-10] = True  # away from the borders, where windows and the search range are cut
    return left, right, gt, mask


def test_chain_is_dense_and_sub_pixel_accurate_on_a_slanted_plane(bench):
    from stereocli.matching.pipeline import match_pair

    left, right, gt, mask = _slanted_pair()
    method = "guided_filter"
    sub = match_pair(left, right, bench.config_for(method, 1), ndisp=16).disparity
    integer = match_pair(left, right, bench.config_for(method, 1, subpixel=False), ndisp=16).disparity
    assert np.isfinite(sub).all() and np.isfinite(integer).all()  # dense: every hole filled
    # `median` averages the two middle values where its window is cut to an even count (the
    # image's outermost rows and columns), so only the interior must be integer-valued.
    inner = integer[1:-1, 1:-1]
    np.testing.assert_array_equal(inner, np.round(inner))
    err_sub, err_int = np.abs(sub - gt)[mask], np.abs(integer - gt)[mask]
    assert (err_sub <= 1).all() and (err_int <= 1).all()
    # Rounding a disparity that sweeps evenly through fractions costs 0.25 px on average; a
    # working sub-pixel step must beat that clearly (a near-integer map would not).
    assert 0.2 < err_int.mean() < 0.3
    assert err_sub.mean() < 0.2
