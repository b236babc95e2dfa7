"""ADCensus refinement (Mei et al. 2011): two-threshold cross arms, region voting, proper
interpolation; the two-threshold option of the ``cross`` aggregation; the adcensus preset."""

from __future__ import annotations

import numpy as np
import pytest

from local_scene import run_stages, scene
from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.kernels import aggregation as ka
from stereocli.matching.kernels import refine as kr
from stereocli.matching.kernels import voting as kv
from stereocli.matching.state import MatchState

# --- pure-numpy references -------------------------------------------------------------------


def arms_reference(image: np.ndarray, tau1: float, tau2: float, l1: int, l2: int) -> np.ndarray:
    """Two-threshold arms (Mei et al. 2011, eq. 4), one pixel and one arm at a time."""
    h, w, _ = image.shape
    arms = np.zeros((h, w, 4), np.int32)
    steps = [(0, -1), (0, 1), (-1, 0), (1, 0)]
    for y in range(h):
        for x in range(w):
            for a, (dy, dx) in enumerate(steps):
                n = 0
                while n < l1:
                    qy, qx = y + (n + 1) * dy, x + (n + 1) * dx
                    if not (0 <= qy < h and 0 <= qx < w):
                        break
                    to_p = np.abs(image[qy, qx] - image[y, x]).max()
                    to_prev = np.abs(image[qy, qx] - image[qy - dy, qx - dx]).max()
                    # the first step is always taken (supports are never a single pixel)
                    if n >= 1 and (to_p >= tau1 or to_prev >= tau1 or (n + 1 > l2 and to_p >= tau2)):
                        break
                    n += 1
                arms[y, x, a] = n
    return arms


def vote_reference(disp, arms, min_disp, ndisp, min_votes, min_share, stride=1):
    # stride > 1: the support sampled on a grid of that step through the pixel, min_votes
    # counted on the full region (divided by stride²).
    out = disp.copy()
    h, w = disp.shape
    min_votes = max(1, -(-min_votes // (stride * stride)))
    for y, x in zip(*np.nonzero(~np.isfinite(disp))):
        votes = []
        for yy in range(y - arms[y, x, 2] // stride * stride, y + arms[y, x, 3] + 1, stride):
            row = disp[yy, x - arms[yy, x, 0] // stride * stride: x + arms[yy, x, 1] + 1: stride]
            votes.extend(row[np.isfinite(row)].tolist())
        votes = np.array(votes)
        if votes.size < min_votes or votes.size == 0:
            continue
        k = np.floor(votes + 0.5).astype(int) - min_disp
        votes = votes[(k >= 0) & (k < ndisp)]
        k = k[(k >= 0) & (k < ndisp)]
        if votes.size < min_votes or votes.size == 0:
            continue
        hist = np.bincount(k, minlength=ndisp)
        best = int(np.argmax(hist))
        if hist[best] >= min_share * votes.size:
            out[y, x] = votes[k == best].mean()
    return out


# --- kernels ---------------------------------------------------------------------------------


def test_two_threshold_arms_match_reference():
    rng = np.random.default_rng(3)
    # blocky image: smooth patches plus noise, so all three stopping rules occur
    img = np.repeat(np.repeat(rng.uniform(0, 255, (5, 6, 3)), 6, 0), 5, 1)[:28, :27]
    img = np.ascontiguousarray(img + rng.normal(0, 3, img.shape), np.float32)
    got = ka.cross_arms_two_threshold(img, 20.0, 6.0, 9, 4)
    np.testing.assert_array_equal(got, arms_reference(img, 20.0, 6.0, 9, 4))


def test_two_threshold_arms_long_only_in_uniform_colour():
    # Row: uniform 100 for 40 px, then a slow ramp (+4 per px). From x=0 the arm runs up to
    # L1 = 34 through the uniform part; from the ramp start (x=40) rightwards the colour drifts
    # 4, 8, 12, ...: τ1 = 20 alone would allow 4 steps, τ2 = 6 beyond L2 = 1 stops it after 1.
    row = np.concatenate([np.full(40, 100.0), 100.0 + 4.0 * np.arange(1, 21)]).astype(np.float32)
    img = np.ascontiguousarray(np.tile(row, (3, 1))[..., None])
    arms = ka.cross_arms_two_threshold(img, 20.0, 6.0, 34, 1)
    assert arms[1, 0, 1] == 34  # right arm of the first pixel: L1
    assert arms[1, 39, 1] == 1  # 100 → 104 → 108: the 2nd step exceeds τ2 beyond L2 = 1
    loose = ka.cross_arms_two_threshold(img, 20.0, 255.0, 34, 1)
    assert loose[1, 39, 1] == 4  # only τ1: 104, 108, 112, 116 pass, 120 (Δ20) does not


def test_region_vote_matches_reference_and_fills_from_own_region():
    rng = np.random.default_rng(5)
    h, w = 30, 40
    img = np.zeros((h, w, 3), np.float32)
    img[:, w // 2:] = 200.0  # two colour regions
    disp = np.where(np.arange(w)[None, :] < w // 2, 4.0, 11.0).astype(np.float32).repeat(h, 0)
    disp = disp + rng.normal(0, 0.1, disp.shape).astype(np.float32)
    holes = rng.random((h, w)) < 0.3
    disp[holes] = np.inf
    arms = ka.cross_arms_two_threshold(img, 20.0, 6.0, 12, 6)
    got = kv.region_vote(disp, arms, 0, 16, 20, 0.4)
    np.testing.assert_allclose(got, vote_reference(disp, arms, 0, 16, 20, 0.4), rtol=0, atol=1e-5)
    truth = np.where(np.arange(w)[None, :] < w // 2, 4.0, 11.0).repeat(h, 0)
    filled = holes & np.isfinite(got)
    assert filled.sum() > 0.9 * holes.sum()
    assert np.abs(got[filled] - truth[filled]).max() < 0.5  # never takes the other region's value


@pytest.mark.parametrize("stride", [2, 3])
def test_region_vote_on_a_sampling_grid_matches_reference(stride):
    rng = np.random.default_rng(stride)
    h, w = 32, 44
    img = np.zeros((h, w, 3), np.float32)
    img[:, w // 2:] = 200.0
    disp = np.where(np.arange(w)[None, :] < w // 2, 4.0, 11.0).astype(np.float32).repeat(h, 0)
    disp = disp + rng.normal(0, 0.2, disp.shape).astype(np.float32)
    disp[rng.random((h, w)) < 0.3] = np.inf
    arms = ka.cross_arms_two_threshold(img, 20.0, 6.0, 12, 6)
    got = kv.region_vote(disp, arms, 0, 16, 20, 0.4, stride)
    np.testing.assert_allclose(got, vote_reference(disp, arms, 0, 16, 20, 0.4, stride), rtol=0, atol=1e-5)
    assert np.isfinite(got).sum() > np.isfinite(disp).sum()


def test_region_vote_thresholds_leave_undecided_pixels_invalid():
    img = np.zeros((9, 9, 1), np.float32)
    arms = ka.cross_arms_two_threshold(img, 20.0, 6.0, 4, 4)  # 9×9 support everywhere at the centre
    disp = np.full((9, 9), np.inf, np.float32)
    disp[:, :4] = 2.0  # 36 votes for 2
    disp[:, 5:] = 7.0  # 36 votes for 7
    tie = kv.region_vote(disp, arms, 0, 10, 20, 0.6)
    assert np.isinf(tie[4, 4])  # 50 % share < 60 %
    few = kv.region_vote(disp, arms, 0, 10, 100, 0.4)
    assert np.isinf(few[4, 4])  # 72 votes < 100
    ok = kv.region_vote(disp, arms, 0, 10, 20, 0.5)
    assert ok[4, 4] in (2.0, 7.0)


def test_proper_interpolation_background_for_occlusions_colour_for_mismatches():
    h, w = 11, 21
    img = np.zeros((h, w, 3), np.float32)
    img[:, 11:] = 200.0  # foreground colour on the right
    disp = np.full((h, w), 3.0, np.float32)
    disp[:, 11:] = 9.0
    disp[2:9, 7:14] = np.inf  # a hole straddling the depth edge
    label = np.zeros((h, w), np.uint8)
    occluded = label.copy()
    occluded[2:9, 7:14] = 1
    out = kv.proper_interpolation(disp, occluded, img, kv.DIRECTIONS16, 100)
    assert np.all(out[2:9, 7:14] == 3.0)  # occlusions: the background (lowest) value
    mismatched = label.copy()
    mismatched[2:9, 7:14] = 2
    out = kv.proper_interpolation(disp, mismatched, img, kv.DIRECTIONS16, 100)
    np.testing.assert_array_equal(out[2:9, 7:11], 3.0)  # background-coloured pixels
    np.testing.assert_array_equal(out[2:9, 11:14], 9.0)  # foreground-coloured pixels
    none_found = kv.proper_interpolation(disp, occluded, img, kv.DIRECTIONS16, 1)
    assert np.isinf(none_found[5, 10])  # nothing reliable within one step (knight moves included)
    assert none_found[2, 7] == 3.0


# --- stages ----------------------------------------------------------------------------------


def _matched_scene():
    left, right, gt, mask = scene(64, 96, 3, 9)
    stages = [("cost", "census", {"window": [5, 5]}), ("aggregation", "box", {"window": [5, 5]}),
              ("optimizer", "wta", {})]
    state = run_stages(left, right, 16, stages)
    from stereocli.matching.kernels.winners import wta_right

    state.disparity_right = wta_right(state.cost, 0, np.float32(state.cost_max))
    return state, gt, mask


def _apply(state: MatchState, name: str, values: dict) -> None:
    stage = registry.get("refinement", name)
    stage.func(state, stage.make_params(values))


def test_lr_check_voting_interpolation_give_dense_correct_map():
    state, gt, mask = _matched_scene()
    _apply(state, "lr_check", {"max_diff": 1.0})
    checked = state.disparity.copy()
    holes = ~np.isfinite(checked)
    assert holes[mask].mean() < 0.05 and holes.sum() > 100  # occlusions + borders rejected
    # The random texture keeps arms short (3×3-ish supports): lower τS so voting acts here.
    _apply(state, "region_voting", {"min_votes": 4})
    voted = holes & np.isfinite(state.disparity)
    assert voted.sum() > 0.2 * holes.sum()
    assert (np.abs(state.disparity - gt)[voted & mask] <= 1).all()
    _apply(state, "proper_interpolation", {})
    assert np.isfinite(state.disparity).all()
    assert (np.abs(state.disparity - gt)[mask] > 1).mean() < 0.01


def test_proper_interpolation_fills_occluded_band_with_background():
    state, gt, mask = _matched_scene()
    _apply(state, "lr_check", {"max_diff": 1.0})
    occluded = kr.classify_holes(state.disparity, state.disparity_right, 0, 15, 1.0) == 1
    _apply(state, "proper_interpolation", {})
    # The band left of the foreground (x0 − 6 .. x0 − 1) is occluded in the right view: its
    # pixels classified as occluded take the background disparity (3), not the foreground's (9).
    # (Those the right view claims are mismatches and take the most similar colour's value.)
    y0, y1, x0 = 64 // 4, 3 * 64 // 4, 96 // 3
    band = np.zeros_like(occluded)
    band[y0 + 2:y1 - 2, x0 - 6:x0] = True
    assert (band & occluded).sum() > 100
    np.testing.assert_array_equal(state.disparity[band & occluded], 3.0)


@pytest.mark.parametrize("name,values,key", [
    ("region_voting", {"max_arm": 10, "max_arm2": 20}, "max_arm2"),
    ("region_voting", {"min_share": 1.5}, "min_share"),
    ("region_voting", {"iterations": 0}, "iterations"),
    ("proper_interpolation", {"tol": -1.0}, "tol"),
])
def test_invalid_parameters_are_errors(name, values, key):
    with pytest.raises(ConfigError, match=key):
        registry.get("refinement", name).make_params(values, source="x.yaml", section="refinement[0]")


def test_cross_two_threshold_option():
    with pytest.raises(ConfigError, match="max_arm2"):
        registry.get("aggregation", "cross").make_params({"max_arm": 10, "tau2": 6.0, "max_arm2": 17})
    left, right, gt, mask = scene(64, 96, 3, 9)
    base = [("cost", "ad_census", {"window": [7, 9]})]
    one = run_stages(left, right, 16, base + [("aggregation", "cross", {})])
    zero = run_stages(left, right, 16, base + [("aggregation", "cross", {"tau2": 0.0})])
    np.testing.assert_array_equal(one.cost, zero.cost)  # tau2 = 0 is today's single threshold
    two = run_stages(left, right, 16, base + [("aggregation", "cross", {"max_arm": 34, "tau2": 6.0}),
                                             ("optimizer", "wta", {})])
    assert (np.abs(two.disparity - gt)[mask] > 1).mean() < 0.01


@pytest.mark.shared_data
def test_adcensus_preset_meets_tsukuba_target(shared_data):
    """The adcensus preset scores ≤ 1.5 % nonocc bad > 1 on Tsukuba (derived mask)."""
    import cv2

    from stereocli.evaluation.metrics import derive_nonocc_mask, middlebury_stats
    from stereocli.matching.config import build_config
    from stereocli.matching.pipeline import match_pair

    folder = shared_data / "middlebury2001" / "tsukuba"
    left = cv2.imread(str(folder / "im3.png"))[..., ::-1].copy()
    right = cv2.imread(str(folder / "im4.png"))[..., ::-1].copy()
    gt = cv2.imread(str(folder / "disp3.pgm"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 16
    gt[gt == 0] = np.inf
    disp = match_pair(left, right, build_config(["adcensus"], []), ndisp=16).disparity
    assert np.isfinite(disp).all()
    assert middlebury_stats(disp, gt, derive_nonocc_mask(gt))["bad1.0"] <= 1.5
