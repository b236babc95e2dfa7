"""The ``sgm`` optimizer and ``hmi`` cost end to end on synthetic pairs with known disparity."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereocli.errors import MemoryBudgetError
from stereocli.matching.config import build_config
from stereocli.matching.pipeline import match_pair

MARGIN = 6  # window half-sizes and path start-up at the borders


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Random texture with some spatial correlation (like a real image), float32 in [0, 255]."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.0)
    img -= img.min()
    return (img * (255.0 / img.max())).astype(np.float32)


def warp_pair(disp: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Left/right pair whose left-referenced disparity is ``disp``: left(x) = right(x − d)."""
    h, w = disp.shape
    right = texture(h, w + 64, seed)
    xs = np.arange(w, dtype=np.float32)[None, :] - disp + 32
    left = cv2.remap(right, xs.astype(np.float32), np.repeat(np.arange(h, dtype=np.float32)[:, None], w, 1),
                     cv2.INTER_LINEAR)
    return left, np.ascontiguousarray(right[:, 32:32 + w])


def bad(est: np.ndarray, gt: np.ndarray, x0: int, thr: float = 1.0) -> float:
    e, g = est[MARGIN:-MARGIN, x0:-MARGIN], gt[MARGIN:-MARGIN, x0:-MARGIN]
    return float(np.mean(~np.isfinite(e) | (np.abs(np.where(np.isfinite(e), e, 0) - g) > thr)))


def run(left, right, sets, min_disp=0, ndisp=16, **kw):
    cfg = build_config([], sets)  # the default preset (the SGM pipeline) plus overrides
    return match_pair(left, right, cfg, min_disp=min_disp, ndisp=ndisp, **kw)


@pytest.mark.parametrize("coarse", ["true", "false"])
@pytest.mark.parametrize("paths", [2, 4, 8, 16])
def test_fronto_parallel_plane_each_path_count(paths, coarse):
    gt = np.full((48, 80), 5.0, np.float32)
    left, right = warp_pair(gt)
    # The default preset searches ranges of 16 and small volumes at full range: both limits off.
    res = run(left, right, [f"optimizer.paths={paths}", f"optimizer.coarse={coarse}", "optimizer.coarse_min_ndisp=0",
                            "optimizer.coarse_min_volume=0"], ndisp=16)
    assert bad(res.disparity, gt, 16) < 0.01
    assert res.disparity.dtype == np.float32 and np.all(np.isfinite(res.disparity))


def test_slanted_plane_subpixel():
    gt = np.tile(np.linspace(4.0, 12.0, 96, dtype=np.float32), (48, 1))
    left, right = warp_pair(gt, seed=3)
    res = run(left, right, [], ndisp=20)
    assert bad(res.disparity, gt, 20, 1.0) < 0.01
    assert bad(res.disparity, gt, 20, 0.5) < 0.10  # sub-pixel, not integer steps


COSTS = ["census", "hmi", "ad_census", "bt"]


@pytest.mark.parametrize("cost", COSTS)
def test_each_cost_on_plane(cost):
    gt = np.full((64, 96), 7.0, np.float32)
    left, right = warp_pair(gt, seed=1)
    res = run(left, right, [f"cost.name={cost}"], ndisp=16)
    assert bad(res.disparity, gt, 16) < 0.02


def test_hmi_handles_inverted_intensities():
    # MI models any intensity mapping: an inverted right image still matches.
    gt = np.full((64, 96), 6.0, np.float32)
    left, right = warp_pair(gt, seed=2)
    res = run(left, 255.0 - right, ["cost.name=hmi"], ndisp=16)
    assert bad(res.disparity, gt, 16) < 0.05


def test_negative_min_disp_and_odd_ndisp():
    gt = np.full((48, 80), -3.0, np.float32)
    left, right = warp_pair(gt, seed=4)
    res = run(left, right, [], min_disp=-9, ndisp=13)
    e = res.disparity[MARGIN:-MARGIN, MARGIN:-16]
    assert np.mean(np.abs(e - gt[MARGIN:-MARGIN, MARGIN:-16]) > 1) < 0.01


def test_keep_invalid_skips_filling_stages():
    gt = np.full((48, 80), 5.0, np.float32)
    gt[:, :40] = 10.0  # foreground on the left: background pixels right of it are occluded
    left, right = warp_pair(gt, seed=5)
    dense = run(left, right, [], ndisp=16)
    holes = run(left, right, [], ndisp=16, keep_invalid=True)
    assert np.all(np.isfinite(dense.disparity))
    assert (~np.isfinite(holes.disparity)).sum() > 0


def test_confidence_and_right_view_outputs():
    gt = np.full((40, 72), 5.0, np.float32)
    left, right = warp_pair(gt, seed=6)
    assert run(left, right, [], ndisp=16).confidence is None  # not requested: not computed
    res = run(left, right, [], ndisp=16, want_right=True, want_confidence=True)
    assert res.confidence is not None and res.confidence.dtype == np.float32
    assert 0.0 <= res.confidence.min() and res.confidence.max() <= 1.0
    assert np.median(res.confidence[:, 20:]) > 0.5
    r = res.disparity_right[MARGIN:-MARGIN, MARGIN:-20]
    assert np.mean(np.abs(r - 5.0) > 1) < 0.02


def test_deterministic_across_thread_counts():
    import numba

    gt = np.tile(np.linspace(3.0, 9.0, 80, dtype=np.float32), (40, 1))
    left, right = warp_pair(gt, seed=7)
    one = run(left, right, ["runtime.threads=1"], ndisp=16, want_right=True)
    two = run(left, right, [f"runtime.threads={min(2, numba.config.NUMBA_NUM_THREADS)}"], ndisp=16, want_right=True)
    np.testing.assert_array_equal(one.disparity, two.disparity)
    np.testing.assert_array_equal(one.disparity_right, two.disparity_right)
    np.testing.assert_array_equal(one.confidence, two.confidence)


def test_memory_budget_refused_with_clear_error():
    left = texture(64, 96)
    with pytest.raises(MemoryBudgetError, match="memory_gb"):
        run(left, left, ["runtime.memory_gb=0.1"], ndisp=100000)


def test_row_strips_close_to_whole_image():
    gt = np.tile(np.linspace(4.0, 10.0, 96, dtype=np.float32), (96, 1))
    left, right = warp_pair(gt, seed=8)
    whole = run(left, right, [], ndisp=16)
    strips = run(left, right, ["runtime.strip_rows=32", "runtime.strip_overlap=16"], ndisp=16)
    assert strips.strips == 3 and whole.strips == 1
    assert strips.disparity.shape == whole.disparity.shape
    assert np.mean(np.abs(strips.disparity - whole.disparity) > 0.5) < 0.02


def test_memory_estimate_reported():
    left = texture(32, 48)
    res = run(left, left, [], ndisp=8)
    from stereocli.matching.pipeline import GIB, RUNTIME_BASE

    # Tiny pair: the estimate is the runtime base (interpreter, libraries) plus a few MB.
    assert RUNTIME_BASE / GIB < res.memory_estimate_gb < RUNTIME_BASE / GIB + 0.05


def test_memory_estimate_counts_integer_census_volume_at_its_size(tmp_path):
    # Census Hamming distances go to SGM as uint8 (1 byte per cell) beside the uint16 sums
    # (2 bytes): 3 bytes per cell. A float cost (AD) is 4 bytes plus SGM's uint8 quantised
    # copy while both are alive: 5 bytes per cell. Checked on the per-cell growth of the
    # estimate over 10 000 rows, so image buffers and the runtime base cancel out and SGM's
    # O(W·D) row buffers are negligible.
    from stereocli.matching.config import build_config
    from stereocli.matching.pipeline import estimate_memory

    def bytes_per_cell(sets, files=()):
        config = build_config(list(files), sets)
        return (estimate_memory(config, 10000, 100,
                                200) - estimate_memory(config, 10000, 100, 100)) / (10000 * 100 * 100)

    full_range = ["optimizer.coarse=false"]
    assert bytes_per_cell(full_range) == pytest.approx(3.0, rel=0.01)
    assert bytes_per_cell([*full_range, "cost.name=ad"]) == pytest.approx(5.0, rel=0.01)
    # The coarse-to-fine search holds windows: a wider range widens them only a little.
    assert bytes_per_cell([]) < 0.5
    # Aggregation between cost and SGM needs float costs: no integer shortcut.
    boxed = tmp_path / "boxed.yaml"
    boxed.write_text("aggregation: [{name: box}]\noptimizer: {coarse: false}\n")
    assert bytes_per_cell([], [str(boxed)]) >= 5.0
