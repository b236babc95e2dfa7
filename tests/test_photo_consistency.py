"""``photo_consistency``: pixels whose colour disagrees with the right pixel they match re-decide
among their neighbours' disparities. On synthetic pairs with exact ground truth, a thin
structure that took the background's disparity and a fattened rim are restored exactly, a
correct map is left alone, and the compiled pass equals a numpy definition; on the real Tsukuba
pair, ``quality`` gains its lamp arms back and meets the Middlebury v2 targets."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import v2_bad1
from local_scene import render
from stereocli import registry
from stereocli.matching.cost import box_mean_image
from stereocli.matching.kernels import photo as kp
from stereocli.matching.state import MatchState
from test_kernels_sgm import on_one_and_two_threads

INF = np.float32(np.inf)
H, W = 40, 80
BACKGROUND, OBJECT = 2, 8  # px


def _texture(height: int, width: int, seed: int) -> np.ndarray:
    """(H, W, 3) float32 random colours in [60, 250): every pixel differs from its neighbours."""
    return np.random.default_rng(seed).uniform(60, 250, (height, width, 3)).astype(np.float32)


def _pair(rect: tuple[int, int, int, int], front: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A textured background at 2 px and a rectangular object (rows ``y0:y1``, columns ``x0:x1``
    of ``rect``; colours from ``front``, (H, W + 40, 3)) at 8 px: the left view, the right view,
    the left-referenced ground truth (float32 px) and the object's mask."""
    left, right, truth, (y0, y1, x0, x1) = render(_texture(H, W + 40, seed=1), front, H, W, BACKGROUND, OBJECT, rect)
    mask = np.zeros((H, W), bool)
    mask[y0:y1, x0:x1] = True
    return left, right, truth, mask


def _occluded(object_mask: np.ndarray) -> np.ndarray:
    """The background pixels of the left view whose match the object hides in the right view."""
    covered = np.zeros_like(object_mask)
    ys, xs = np.nonzero(object_mask)
    covered[ys, xs - OBJECT] = True  # right-view pixels showing the object
    rows, cols = np.nonzero(~object_mask)
    occluded = np.zeros_like(object_mask)
    inside = cols - BACKGROUND >= 0
    occluded[rows[inside], cols[inside]] = covered[rows[inside], cols[inside] - BACKGROUND]
    return occluded


def _run(left, right, disparity, **values) -> tuple[np.ndarray, dict]:
    stage = registry.get("refinement", "photo_consistency")
    state = MatchState(left, right, 0, 16)
    state.disparity = disparity.copy()
    stage.func(state, stage.make_params(values))
    return state.disparity, state.notes.get("photo_consistency", {})


def _thin_post() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 3-px wide vertical post (rows 5-34, columns 40-42) of one dark colour in front of the
    background; returns the pair, the ground truth and the post's mask."""
    return _pair((5, 35, 40, 43), np.full((H, W + 40, 3), 30.0, np.float32))


def test_a_thin_structure_that_took_the_background_gets_its_disparity_back():
    left, right, truth, post = _thin_post()
    # The map lost the post's middle (rows 10-27) to the background: there the post's pixels map
    # onto the background of the right view, 6 px off the post.
    lost = post.copy()
    lost[:10] = lost[28:] = False
    disparity = np.where(lost, BACKGROUND, truth).astype(np.float32)
    fixed, notes = _run(left, right, disparity)
    compare = ~_occluded(post)
    np.testing.assert_array_equal(fixed[compare], truth[compare])
    assert round(notes["changed"] * H * W) == lost.sum()  # 54 pixels, and nothing else
    # Rows 9 and 28 stand out too (their 3x3 mean takes in the lost rows), so the first pass takes
    # candidates from rows 8 and 29, up to 8 px away: it restores rows 10-16 and 21-27. Each
    # further pass re-decides next to what the last one changed, one row further.
    for iterations, still_lost in ((1, [17, 18, 19, 20]), (2, [18, 19])):
        partly, _ = _run(left, right, disparity, iterations=iterations)
        for column in (40, 41, 42):
            np.testing.assert_array_equal(np.nonzero(partly[:, column] != truth[:, column])[0], still_lost)


def test_a_fattened_rim_returns_to_the_background():
    left, right, truth, square = _pair((10, 30, 30, 50), _texture(H, W + 40, seed=2))
    # The square's disparity spills 2 px over its right edge (foreground fattening).
    fattened = truth.copy()
    fattened[10:30, 50:52] = OBJECT
    fixed, _ = _run(left, right, fattened)
    compare = ~_occluded(square)
    np.testing.assert_array_equal(fixed[compare], truth[compare])


def test_the_margin_decides_how_much_better_a_candidate_must_match():
    left, right, truth, post = _thin_post()
    disparity = np.where(post, BACKGROUND, truth).astype(np.float32)
    # Costs are colour differences capped at 20 grey levels: nothing can beat anything by 20.
    unchanged, notes = _run(left, right, disparity, margin=20.0)
    np.testing.assert_array_equal(unchanged, disparity)
    assert notes["changed"] == 0 and notes["flagged"] > 0


def test_a_correct_map_and_invalid_pixels_are_left_alone():
    left, right, truth, post = _thin_post()
    disparity = truth.copy()
    occluded = _occluded(post)
    disparity[occluded] = INF  # as after an LR check: invalid pixels are neither flagged nor candidates
    fixed, notes = _run(left, right, disparity)
    np.testing.assert_array_equal(fixed, disparity)
    assert notes["flagged"] == 0
    # A plain textured plane matched exactly: no residual, nothing flagged.
    left, right, truth, _ = _pair((0, 0, 0, 0), np.zeros((H, W + 40, 3), np.float32))
    fixed, notes = _run(left, right, truth)
    np.testing.assert_array_equal(fixed, truth)
    assert notes == {"threshold": 10.0, "flagged": 0.0, "changed": 0.0}


def _redecide_reference(left, right, disp, flagged, radius, step, gamma_c, gamma_s, truncation, reach, margin):
    """One pass of :func:`~stereocli.matching.kernels.photo.redecide_flagged`, in numpy, from its docstring."""
    h, w = disp.shape
    offsets = np.arange(-(radius // step) * step, radius + 1, step)
    spatial = np.exp(-np.hypot(offsets[:, None], offsets[None, :]) / gamma_s).astype(np.float32)
    similarity = np.exp(-np.arange(256) / gamma_c).astype(np.float32)

    def shift(d):
        return int(np.floor(d + 0.5))

    def difference(y, x, d):  # largest channel difference from right pixel x - round(d), clamped
        return np.abs(left[y, x] - right[y, min(max(x - shift(d), 0), w - 1)]).max()

    out = disp.copy()
    for y, x in zip(*np.nonzero(flagged)):
        own = disp[y, x]
        candidates = []
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)):
            for k in range(1, reach + 1):
                yy, xx = y + k * dy, x + k * dx
                if not (0 <= yy < h and 0 <= xx < w):
                    break
                if flagged[yy, xx] or not np.isfinite(disp[yy, xx]):
                    continue
                c = disp[yy, xx]
                if (shift(c) != shift(own) and all(shift(c) != shift(o) for o in candidates)
                        and difference(y, x, c) < difference(y, x, own)):
                    candidates.append(c)
                break
        if not candidates:
            continue
        weights = np.zeros((len(offsets), len(offsets)))
        for a, oy in enumerate(offsets):
            for b, ox in enumerate(offsets):
                if 0 <= y + oy < h and 0 <= x + ox < w:
                    largest = np.abs(left[y + oy, x + ox] - left[y, x]).max()
                    weight = spatial[a, b] * similarity[min(int(largest), 255)]
                    weights[a, b] = weight if weight >= 1e-3 else 0.0

        def cost(d):
            total = 0.0
            for a, oy in enumerate(offsets):
                for b, ox in enumerate(offsets):
                    if weights[a, b] > 0:
                        x_right = min(max(x + ox - shift(d), 0), w - 1)
                        diff = np.abs(left[y + oy, x + ox] - right[y + oy, x_right]).max()
                        total += weights[a, b] * min(diff, truncation)
            return total / weights.sum()

        costs = [cost(c) for c in candidates]
        best = int(np.argmin(costs))  # the first on a tie
        if costs[best] < cost(own) - margin:
            out[y, x] = candidates[best]
    return out


def test_the_compiled_pass_equals_its_numpy_definition():
    rng = np.random.default_rng(5)
    h, w = 14, 22
    changed_pixels = 0
    for seed in range(3):
        rng = np.random.default_rng(seed)
        base = rng.uniform(0, 255, (h, w + 6, 3)).astype(np.float32)
        left = np.ascontiguousarray(base[:, :w])
        right = np.ascontiguousarray(base[:, 3:w + 3] + rng.normal(0, 3, (h, w, 3)).astype(np.float32))
        disp = rng.choice(np.float32([1.0, 2.5, 3.0, 3.2, 6.0]), (h, w)).astype(np.float32)
        disp[rng.random((h, w)) < 0.1] = INF
        flagged = (rng.random((h, w)) < 0.4) & np.isfinite(disp)
        active = np.ones((h, w), bool)
        params = dict(radius=3, step=1, gamma_c=20.0, gamma_s=4.0, truncation=60.0, reach=5, margin=1.0)
        expected = _redecide_reference(left, right, disp, flagged, **params)
        results = on_one_and_two_threads(lambda: kp.redecide_flagged(
            left, right, disp, flagged, active, params["radius"], params["step"], params["gamma_c"],
            params["gamma_s"], params["truncation"], params["reach"], params["margin"]))
        for out, changed in results:
            np.testing.assert_array_equal(out, expected)
            np.testing.assert_array_equal(changed, out != disp)
        changed_pixels += int((expected != disp).sum())
    assert changed_pixels > 20  # the comparison covers real decisions


def test_the_residual_and_its_3x3_mean():
    left = np.arange(2 * 5 * 3, dtype=np.float32).reshape(2, 5, 3)
    right = np.zeros((2, 5, 3), np.float32)
    disp = np.array([[0.0, 1.0, 1.4, 1.6, INF], [9.0, 0.0, 0.0, 0.0, -3.0]], np.float32)
    residual = kp.colour_residual(left, right, disp)
    # The largest channel difference, against a black right view: the blue channel where
    # x - round(d) lies in the image; 0 where d is invalid (x = 4) or it does not (x = 0 and 4
    # of the second row, d = 9 and -3).
    inside = np.array([[True, True, True, True, False], [False, True, True, True, False]])
    np.testing.assert_array_equal(residual, np.where(inside, left[..., 2], 0))
    # x = 2, d = 1.4 reads column 1; x = 3, d = 1.6 reads column 1 too.
    right[0, 1] = left[0, 2]
    np.testing.assert_array_equal(kp.colour_residual(left, right, disp)[0, 2:4], [0, 3])
    box = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], np.float32)
    # The residual's 3x3 mean: each pixel's mean over its window clipped at the borders.
    np.testing.assert_allclose(box_mean_image(box, 1, 1), [[3.0, 3.5, 4.0], [3.0, 3.5, 4.0]])
    np.testing.assert_allclose(box_mean_image(box[:, :1].copy(), 1, 1), [[2.5], [2.5]])  # one column
    np.testing.assert_allclose(box_mean_image(box[:1].copy(), 1, 1), [[1.5, 2.0, 2.5]])  # one row


def test_unknown_parameters_are_config_errors():
    from stereocli.errors import ConfigError
    from stereocli.matching.config import build_config

    with pytest.raises(ConfigError, match="photo_consistency"):
        build_config(["quality"], ["refinement.photo_consistency.marginn=2"])
    with pytest.raises(ConfigError, match="photo_consistency"):
        build_config(["quality"], ["refinement.photo_consistency.step=0"])


# --- real data -------------------------------------------------------------------------------


def test_quality_gets_the_tsukuba_lamp_arms_back(shared_data):
    # The lamp's thin arms, given the background by SGM, get theirs back (about 0.4 points; the
    # guard asks for half of it).
    without = v2_bad1(shared_data, "tsukuba", "quality", ("refinement.photo_consistency.margin=20",))
    with_it = v2_bad1(shared_data, "tsukuba", "quality")
    assert with_it <= without - 0.2, (without, with_it)


def test_quality_meets_the_middlebury_v2_targets(shared_data):
    # Targets 2.2 / 0.3 / 4.5 / 2.2 % nonocc bad > 1; measured 1.84 / 0.22 / 3.51 / 2.05 (Tsukuba's
    # views keep their camera's column pattern: no preset runs column_pattern).
    targets = {"tsukuba": 2.2, "venus": 0.3, "teddy": 4.5, "cones": 2.2}
    scores = {scene: v2_bad1(shared_data, scene, "quality") for scene in targets}
    assert all(scores[scene] <= target for scene, target in targets.items()), scores
