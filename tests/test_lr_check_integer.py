"""``lr_check`` with ``compare: integer``: the check decided on the optimizer's integer winners
(kept by the pipeline before ``subpixel``) and applied to the sub-pixel map."""

from __future__ import annotations

import numpy as np
import pytest

from local_scene import scene
from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.config import validate
from stereocli.matching.kernels.maps import lr_check_onto
from stereocli.matching.pipeline import match_pair, prepare
from stereocli.matching.state import MatchState

INF = np.float32(np.inf)


def lr_reference(left, right, max_diff, target):
    """Pure-numpy LR check: ``target`` with +inf where left pixel x (disparity d) maps to right
    pixel round(x - d) outside the image or to a right disparity more than max_diff away."""
    out = target.copy()
    h, w = left.shape
    for y in range(h):
        for x in range(w):
            d = left[y, x]
            if not np.isfinite(d):
                continue
            xr = int(np.floor(x - d + 0.5))
            if xr < 0 or xr >= w or not np.isfinite(right[y, xr]) or abs(d - right[y, xr]) > max_diff:
                out[y, x] = INF
    return out


def lr_stage(state, **values):
    stage = registry.get("refinement", "lr_check")
    stage.func(state, stage.make_params(values))
    return state.disparity


def test_kernel_matches_the_numpy_reference():
    rng = np.random.default_rng(0)
    left = rng.integers(0, 6, (7, 23)).astype(np.float32)
    right = rng.integers(0, 6, (7, 23)).astype(np.float32)
    left[rng.random(left.shape) < 0.1] = INF
    right[rng.random(right.shape) < 0.1] = INF
    target = np.where(np.isfinite(left), left + rng.uniform(-0.5, 0.5, left.shape), INF).astype(np.float32)
    for max_diff in (0.0, 1.0):
        np.testing.assert_array_equal(lr_check_onto(left, right, max_diff, target),
                                      lr_reference(left, right, max_diff, target))


def _hand_made_state():
    # x = 5: integer winners 3 (left) and 1 (right, at xr = 2) disagree by 2 px, but after the
    #        sub-pixel fits (2.6 and 1.7) they are within 1 px: a wrong winner a final 1 px check keeps.
    # x = 7: integer winners agree (2 and 2 at xr = 5); the fits move them apart (2.45 / 1.55).
    left_int = np.array([[INF, INF, INF, INF, INF, 3, INF, 2]], np.float32)
    right_int = np.array([[INF, INF, 1, INF, INF, 2, INF, INF]], np.float32)
    state = MatchState(np.zeros((1, 8), np.float32), np.zeros((1, 8), np.float32), 0, 4)
    state.disparity = np.array([[INF, INF, INF, INF, INF, 2.6, INF, 2.45]], np.float32)
    state.disparity_right = np.array([[INF, INF, 1.7, INF, INF, 1.55, INF, INF]], np.float32)
    state.integer_disparity, state.integer_disparity_right = left_int, right_int
    return state


def test_integer_check_rejects_winners_the_sub_pixel_fits_pulled_together():
    out = lr_stage(_hand_made_state(), compare="integer", max_diff=0.0)
    assert out[0, 5] == INF  # 3 vs 1 on integers
    assert out[0, 7] == np.float32(2.45)  # integers agree: the sub-pixel value is kept
    final = lr_stage(_hand_made_state(), compare="final", max_diff=1.0)
    assert final[0, 5] == np.float32(2.6)  # 2.6 vs 1.7 passes a 1 px check on the fitted maps
    assert lr_stage(_hand_made_state(), compare="final", max_diff=0.0)[0, 7] == INF


def test_without_kept_maps_the_current_maps_are_compared():
    state = _hand_made_state()
    state.integer_disparity = state.integer_disparity_right = None
    np.testing.assert_array_equal(lr_stage(state, compare="integer", max_diff=1.0),
                                  lr_stage(_hand_made_state(), compare="final", max_diff=1.0))


def _config(refinement, **runtime):
    return validate({"preprocess": [], "cost": {"name": "ad"}, "aggregation": [{"name": "box", "window": [7, 7]}],
                     "optimizer": {"name": "wta"}, "refinement": refinement,
                     "runtime": {"threads": 1, **runtime}}, "<test>")


SUBPIXEL = {"name": "subpixel", "method": "parabola"}
INTEGER_CHECK = {"name": "lr_check", "max_diff": 0.0, "compare": "integer"}


def test_pipeline_checks_the_wta_winners_and_keeps_the_sub_pixel_values():
    left, right, gt, mask = scene(color=True)
    run = lambda refinement, **rt: match_pair(left, right, _config(refinement, **rt), ndisp=16,  # noqa: E731
                                              keep_invalid=True).disparity
    checked = run([SUBPIXEL, INTEGER_CHECK])
    on_integers = run([{"name": "lr_check", "max_diff": 0.0}])  # no sub-pixel step: the maps are the winners
    sub = run([SUBPIXEL])
    # the same pixels are rejected as by an exact check on the integer winners ...
    np.testing.assert_array_equal(np.isfinite(checked), np.isfinite(on_integers))
    # ... and the kept ones hold the sub-pixel values
    keep = np.isfinite(checked)
    np.testing.assert_array_equal(checked[keep], sub[keep])
    assert np.abs(checked - gt)[mask & keep].max() < 0.5 and keep[mask].mean() > 0.95
    # the band occluded in the right view (left of the foreground square) is rejected
    h, w = gt.shape
    assert not keep[h // 4 + 4:3 * h // 4 - 4, w // 3 - 5:w // 3 - 1].any()
    # row strips stitch the kept integer maps like the disparity maps
    np.testing.assert_array_equal(run([SUBPIXEL, INTEGER_CHECK], strip_rows=16, strip_overlap=8), checked)


@pytest.mark.parametrize("compare, kept", [("final", False), ("integer", True)])
def test_pipeline_keeps_integer_maps_only_when_asked(compare, kept):
    left, right, _, _ = scene(h=32, w=48)
    prepared = prepare(left, right, _config([SUBPIXEL, {"name": "lr_check", "compare": compare}]), ndisp=8)
    assert prepared.state.wants.integer_maps is kept


def test_unknown_compare_value_is_a_config_error():
    with pytest.raises(ConfigError, match="compare: 'integr' is not one of final, integer.*did you mean 'integer'"):
        _config([SUBPIXEL, {"name": "lr_check", "compare": "integr"}])
