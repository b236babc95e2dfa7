"""``mirror_fusion``: reading a right-referenced map where each left pixel matches, the fusion
rule, and the pipeline's mirrored run (the stages before the fusion on the flipped, swapped
pair) against the same run done by hand."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli.errors import ConfigError
from stereocli.matching.config import build_config
from stereocli.matching.pipeline import match_pair
from stereocli.matching.refine_fusion import fuse_with_mirrored, reassign_contradicted, sample_right_map
from stereocli.synth.scenes import render, scene_surfaces
from test_kernels_sgm import on_one_and_two_threads

INF = np.float32(np.inf)


def test_sample_right_map_interpolates_at_x_minus_d():
    right_map = np.array([[10.0, 20.0, 40.0, 80.0]], np.float32)
    disparity = np.array([[0.0, 0.5, 1.25, 0.0]], np.float32)
    # x - d: 0 -> 10; 0.5 -> 15; 0.75 -> 17.5; 3 (the last column) -> 80.
    np.testing.assert_array_equal(sample_right_map(disparity, right_map), [[10.0, 15.0, 17.5, 80.0]])


def test_sample_right_map_is_invalid_outside_the_image_or_next_to_an_invalid_column():
    right_map = np.array([[5.0, INF, 7.0, 9.0, 11.0]], np.float32)
    disparity = np.array([[0.0, 1.5, 0.5, INF, -0.5]], np.float32)
    # x - d: 0 -> 5; -0.5 outside; 1.5 reads the invalid column 1; d invalid; 4.5 outside.
    np.testing.assert_array_equal(sample_right_map(disparity, right_map), [[5.0, INF, INF, INF, INF]])
    # An integer x - d next to an invalid column still reads the valid one exactly.
    np.testing.assert_array_equal(sample_right_map(np.array([[0.0, 0.0, 0.0, 0.0, 0.0]], np.float32), right_map),
                                  [[5.0, INF, 7.0, 9.0, 11.0]])


def test_fusion_averages_where_the_maps_agree_and_keeps_the_left_value_elsewhere():
    disparity = np.array([[2.0, 2.0, 2.0, INF, 2.0, 2.0]], np.float32)
    right_map = np.array([[1.0, 1.0, 1.2, 4.0, 2.5, 9.0]], np.float32)
    # Pixel x reads right column x - 2: x=2 -> 1.0 (1 px off); x=4 -> 1.2 (0.8 px); x=5 -> 4.0 (2 px).
    expected = {1.0: [2.0, 2.0, 2.0, INF, 0.5 * (2.0 + np.float32(1.2)), 2.0],
                1.5: [2.0, 2.0, 1.5, INF, 0.5 * (2.0 + np.float32(1.2)), 2.0]}
    for tolerance, values in expected.items():
        np.testing.assert_array_equal(fuse_with_mirrored(disparity, right_map, tolerance),
                                      np.array([values], np.float32))


def test_fusing_a_slanted_plane_with_its_own_right_view_changes_nothing():
    # Left map d = 0.05 x + 0.02 y + 3 on a 60 x 40 image; its right view (a point at left column
    # x lands on x - d) is linear in the right column too, so interpolation reads it exactly.
    h, w = 40, 60
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    left_map = 0.05 * xs + 0.02 * ys + 3.0
    # x_r = x - d = 0.95 x - 0.02 y - 3  =>  x = (x_r + 0.02 y + 3) / 0.95.
    right_map = 0.05 * (xs + 0.02 * ys + 3.0) / 0.95 + 0.02 * ys + 3.0
    fused = fuse_with_mirrored(left_map.astype(np.float32), right_map.astype(np.float32), 0.01)
    inside = xs - left_map >= 0
    np.testing.assert_allclose(fused[inside], left_map[inside], atol=1e-5)
    # Read at x + d instead, the same right view is 0.3 px off or more: the sign matters.
    wrong = np.interp(xs[0] + left_map[0], xs[0], right_map[0])
    assert np.abs(wrong - left_map[0])[xs[0] + left_map[0] < w - 1].min() > 0.3


def _scene():
    out = render(scene_surfaces("planes", 96, 64, seed=1), 96, 64, noise=0.8, seed=1)
    return out["left"], out["right"]


BEFORE = "{name: subpixel}, {name: lr_check, max_diff: 1.0}, {name: fill}"


def _config(tmp_path, refinements: str):
    path = tmp_path / f"chain{len(list(tmp_path.iterdir()))}.yaml"
    path.write_text(f"refinement: [{refinements}]\n")
    return build_config([str(path)])


@pytest.mark.parametrize("keep_invalid", [False, True])
def test_the_pipeline_fuses_with_the_stages_before_it_run_on_the_mirrored_pair(tmp_path, keep_invalid):
    left, right = _scene()
    ndisp = 32
    before = _config(tmp_path, BEFORE)
    left_map = match_pair(left, right, before, ndisp=ndisp, keep_invalid=keep_invalid).disparity
    flipped = match_pair(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), before,
                         ndisp=ndisp, keep_invalid=keep_invalid).disparity
    expected = fuse_with_mirrored(left_map, np.ascontiguousarray(flipped[:, ::-1]), 1.0)
    # Most pixels agree within 1 px and move to the mean; the holes stay holes with --keep-invalid.
    assert np.mean(expected != left_map) > 0.5
    assert np.array_equal(np.isinf(expected), np.isinf(left_map))
    assert np.isinf(left_map).any() == keep_invalid

    fusing = _config(tmp_path, BEFORE + ", {name: mirror_fusion, tolerance: 1.0}")
    result = match_pair(left, right, fusing, ndisp=ndisp, keep_invalid=keep_invalid)
    np.testing.assert_array_equal(result.disparity, expected)
    assert result.timings["refinement.mirror_fusion.mirrored_pair"] > 0


def test_a_negative_tolerance_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="tolerance"):
        _config(tmp_path, "{name: mirror_fusion, tolerance: -1.0}")
    with pytest.raises(ConfigError, match="reassign_radius"):
        _config(tmp_path, "{name: mirror_fusion, reassign_above: 3.0, reassign_radius: 0}")


def fuse_reference(disparity, right_map, tolerance):
    """The fusion by its definition, with numpy: the mean where the sampled right map agrees."""
    sampled = sample_right_map(disparity, right_map)
    agree = np.isfinite(sampled)
    agree[agree] = np.abs(sampled[agree] - disparity[agree]) < tolerance
    return np.where(agree, np.float32(0.5) * (disparity + sampled), disparity).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_fusion_equals_its_definition(seed):
    # Random maps with holes, disparities landing on whole columns (weight 0), on the last
    # column and outside the image, on one and two threads.
    rng = np.random.default_rng(seed)
    h, w = 23, 31
    disparity = rng.uniform(-2, 12, (h, w)).astype(np.float32)
    whole = rng.random((h, w)) < 0.2
    disparity[whole] = np.round(disparity[whole])
    disparity[:, -1] = 0.0  # lands on column W - 1 exactly
    disparity[rng.random((h, w)) < 0.1] = INF
    right_map = (disparity + rng.uniform(-1.5, 1.5, (h, w))).astype(np.float32)
    right_map[rng.random((h, w)) < 0.15] = INF
    want = fuse_reference(disparity, right_map, 1.0)

    def run():
        return fuse_with_mirrored(disparity, right_map, 1.0)

    for got in on_one_and_two_threads(run):
        np.testing.assert_array_equal(got, want)
    assert (want != disparity).sum() > 50  # many pixels were averaged


def test_the_compiled_fusion_on_a_one_column_map():
    disparity = np.array([[0.0], [0.5], [INF]], np.float32)
    right_map = np.array([[1.0], [0.0], [0.0]], np.float32)
    np.testing.assert_array_equal(fuse_with_mirrored(disparity, right_map, 2.0),
                                  fuse_reference(disparity, right_map, 2.0))


# --- reassigning pixels the mirrored map contradicts ---------------------------------------


def _fattened_row():
    """One row, 32 px: background at disparity 2, an object at 6 over left columns 10–19, and
    a left map whose census windows carried the object's 6 two columns into the background
    (columns 20, 21). The right-referenced map is exact: the object over right columns 4–13,
    the background elsewhere (right columns 14–17 are seen by the right view only and hold the
    background's 2, as a fill gives them)."""
    truth = np.full(32, 2.0, np.float32)
    truth[10:20] = 6.0
    left_map = truth.copy()
    left_map[20:22] = 6.0
    right_map = np.full(32, 2.0, np.float32)
    right_map[4:14] = 6.0
    return left_map[None], right_map[None], truth[None]


def test_a_fattened_rim_takes_the_disparity_the_mirrored_map_confirms():
    left_map, right_map, truth = _fattened_row()
    # Column 20 at 6 reads right column 14 (2): contradicted by 4 px. Its neighbours 21 and 19
    # offer 6 (read at 14 and 14 again: no), 22 offers 2 (read at 18: 2, confirmed).
    out = reassign_contradicted(left_map, right_map, above=3.0, radius=2, within=1.0)
    np.testing.assert_array_equal(out, truth)
    # The background left of the object (columns 6–9) is hidden from the right view: it reads
    # the object (6) and stays contradicted, but no neighbour's disparity is confirmed there
    # (the object's 6 read at columns 0–3 finds 2), so it keeps the fill's 2.
    assert sample_right_map(truth, right_map)[0, 6:10].tolist() == [6.0] * 4
    # A contradiction of 4 px is not above 4; a radius of 1 reaches only 6s for column 20.
    np.testing.assert_array_equal(reassign_contradicted(left_map, right_map, 4.0, 2, 1.0), left_map)
    only_near = reassign_contradicted(left_map, right_map, 3.0, 1, 1.0)
    assert only_near[0, 20] == 6.0 and only_near[0, 21] == 2.0


def test_a_column_neighbour_is_offered_when_the_row_has_none():
    # Three rows of the fattened row; in the middle one the rim spans columns 20–24, beyond the
    # row radius, and the rows above and below (already right at 2) supply the disparity.
    left_map, right_map, truth = (np.repeat(a, 3, axis=0) for a in _fattened_row())
    left_map[0, 20:22] = truth[0, 20:22]
    left_map[2, 20:22] = truth[2, 20:22]
    left_map[1, 20:25] = 6.0
    out = reassign_contradicted(left_map, right_map, 3.0, 2, 1.0)
    np.testing.assert_array_equal(out, truth)


def reassign_reference(disparity, right_map, above, radius, within):
    """The reassignment by its definition, with numpy: shifted copies of the map as candidates,
    in the kernel's order (row before column, nearer first, the right or lower neighbour
    first), each replacing the choice only if strictly better confirmed."""
    h, w = disparity.shape

    def contradiction(candidates):
        with np.errstate(invalid="ignore"):
            gap = np.abs(sample_right_map(candidates, right_map) - candidates)
        return np.where(np.isfinite(gap), gap, np.float32(np.inf))

    gap = contradiction(disparity)
    contradicted = np.isfinite(gap) & (gap > np.float32(above))
    out, best = disparity.copy(), np.full((h, w), np.inf, np.float32)
    padded = np.pad(disparity, radius, constant_values=np.inf)
    for axis in (1, 0):
        for step in range(1, radius + 1):
            for offset in (step, -step):
                dy, dx = (offset, 0) if axis == 0 else (0, offset)
                candidates = padded[radius + dy:radius + dy + h, radius + dx:radius + dx + w]
                error = contradiction(candidates)
                take = contradicted & (error <= np.float32(within)) & (error < best)
                out = np.where(take, candidates, out)
                best = np.where(take, error, best)
    return out.astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_reassignment_equals_its_definition(seed):
    # Random layered maps with holes and a noisy right map, on one and two threads.
    rng = np.random.default_rng(seed)
    h, w = 29, 41
    disparity = rng.choice(np.array([1.0, 4.0, 9.0], np.float32), (h, w)) + rng.uniform(-0.3, 0.3, (h, w))
    disparity = disparity.astype(np.float32)
    disparity[rng.random((h, w)) < 0.1] = INF
    right_map = rng.choice(np.array([1.0, 4.0, 9.0], np.float32), (h, w)) + rng.uniform(-0.6, 0.6, (h, w))
    right_map = right_map.astype(np.float32)
    right_map[rng.random((h, w)) < 0.1] = INF
    for above, radius, within in ((3.0, 2, 1.0), (1.0, 3, 0.5)):
        want = reassign_reference(disparity, right_map, above, radius, within)

        def run():
            return reassign_contradicted(disparity, right_map, above, radius, within)

        for got in on_one_and_two_threads(run):
            np.testing.assert_array_equal(got, want)
        assert (want != disparity).sum() > 100  # many pixels were reassigned


def test_the_stage_reassigns_after_fusing_when_asked(tmp_path):
    # The mirrored run done by hand, as above; the stage fuses, then reassigns on the fused map.
    left, right = _scene()
    ndisp = 32
    before = _config(tmp_path, BEFORE)
    left_map = match_pair(left, right, before, ndisp=ndisp).disparity
    flipped = match_pair(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), before,
                         ndisp=ndisp).disparity
    right_map = np.ascontiguousarray(flipped[:, ::-1])
    fused = fuse_with_mirrored(left_map, right_map, 1.0)
    expected = reassign_reference(fused, right_map, 1.0, 2, 1.0)
    assert (expected != fused).sum() > 0

    stage = "{name: mirror_fusion, tolerance: 1.0, reassign_above: 1.0}"
    got = match_pair(left, right, _config(tmp_path, BEFORE + ", " + stage), ndisp=ndisp).disparity
    np.testing.assert_array_equal(got, expected)
    # reassign_above 0 (the default) only fuses.
    only_fused = match_pair(left, right, _config(tmp_path, BEFORE + ", {name: mirror_fusion, tolerance: 1.0}"),
                            ndisp=ndisp).disparity
    np.testing.assert_array_equal(only_fused, fused)
