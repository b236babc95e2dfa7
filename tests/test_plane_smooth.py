"""The ``plane_smooth`` refinement: edge-aware sub-pixel smoothing by local line fits (rows,
then columns), checked against a pure-numpy reference and on maps with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.kernels import refine as kr
from stereocli.matching.state import MatchState

INF = np.float32(np.inf)


def line_fit_reference(disp, image, radius, sigma_space, color_range, gate, vertical, clamp=True, step=1):
    """One pass of the kernel, pixel by pixel in float64: a weighted least-squares line through
    the gated neighbours on the row (or column) at offsets that are multiples of ``step``,
    evaluated at the centre."""
    h, w = disp.shape
    out = disp.copy()
    for y in range(h):
        for x in range(w):
            d0 = disp[y, x]
            if not np.isfinite(d0):
                continue
            ts, vs, ws = [], [], []
            for t in range(-radius, radius + 1):
                if t % step:
                    continue
                yy, xx = (y + t, x) if vertical else (y, x + t)
                if not (0 <= yy < h and 0 <= xx < w):
                    continue
                v = float(disp[yy, xx]) - float(d0)
                if not abs(v) <= gate:
                    continue
                dist2 = float(((image[yy, xx] - image[y, x]) ** 2).sum())
                cw = max(0.0, 1.0 - dist2 / color_range**2)
                ts.append(t)
                vs.append(v)
                ws.append(np.exp(-0.5 * t * t / sigma_space**2) * cw * cw)
            t, v, wt = np.array(ts, float), np.array(vs, float), np.array(ws, float)
            s, st, stt, sv, stv = wt.sum(), (wt * t).sum(), (wt * t * t).sum(), (wt * v).sum(), (wt * t * v).sum()
            det = s * stt - st * st
            corr = (stt * sv - st * stv) / det if det > 1e-4 * s * s else sv / s
            out[y, x] = d0 + (np.clip(corr, -gate, gate) if clamp else corr)
    return out


def run(disp, image, **params):
    stage = registry.get("refinement", "plane_smooth")
    state = MatchState(image, image, 0, 64)
    state.disparity = np.asarray(disp, np.float32)
    stage.func(state, stage.make_params(params))
    return state.disparity


def test_kernel_matches_numpy_reference_with_holes_edges_and_colour():
    rng = np.random.default_rng(3)
    h, w = 14, 19
    image = rng.uniform(0, 60, (h, w, 3)).astype(np.float32)
    disp = (rng.uniform(4, 6, (h, w)) + np.where(np.arange(w) > 9, 3.0, 0.0)).astype(np.float32)
    disp[rng.random((h, w)) < 0.15] = INF
    args = (4, 3.0, 50.0, 1.0)
    want = line_fit_reference(line_fit_reference(disp, image, *args, False), image, *args, True)
    got = kr.plane_smooth(disp, image, *args)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(disp))
    finite = np.isfinite(disp)
    np.testing.assert_allclose(got[finite], want[finite], rtol=0, atol=2e-4)


@pytest.mark.parametrize("radius", [4, 5])
def test_every_second_neighbour_matches_the_reference(radius):
    rng = np.random.default_rng(4)
    h, w = 14, 19
    image = rng.uniform(0, 60, (h, w, 3)).astype(np.float32)
    disp = (rng.uniform(4, 6, (h, w)) + np.where(np.arange(w) > 9, 3.0, 0.0)).astype(np.float32)
    disp[rng.random((h, w)) < 0.15] = INF
    args = (radius, 3.0, 50.0, 1.0)
    want = line_fit_reference(line_fit_reference(disp, image, *args, False, step=2), image, *args, True, step=2)
    got = kr.plane_smooth(disp, image, *args, step=2)
    finite = np.isfinite(disp)
    np.testing.assert_allclose(got[finite], want[finite], rtol=0, atol=2e-4)
    every = kr.plane_smooth(disp, image, *args)
    assert np.abs(got[finite] - every[finite]).max() > 0.01  # the skipped neighbours did count before


def test_recovers_a_slanted_plane_from_staircased_disparities():
    # A plane d = 20 + 0.13·x − 0.07·y seen through pixel-locked sub-pixel estimates: each value
    # pulled halfway towards its nearest integer (errors up to ±0.25 px, as on SGM sums).
    h, w = 40, 60
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = 20 + 0.13 * xx - 0.07 * yy
    locked = (0.5 * truth + 0.5 * np.round(truth)).astype(np.float32)
    image = np.full((h, w), 100.0, np.float32)
    out = run(locked, image, radius=8, sigma_space=8.0)
    inner = (slice(8, -8), slice(8, -8))
    assert np.abs(locked - truth)[inner].max() > 0.2
    assert np.abs(out - truth)[inner].max() < 0.02
    # Every second neighbour (the `fast` preset's setting) fits the same plane.
    out = run(locked, image, radius=8, sigma_space=8.0, step=2)
    assert np.abs(out - truth)[inner].max() < 0.05


def test_depth_edges_are_kept_by_the_gate():
    # Two fronto-parallel surfaces 4 px apart with the same colour: no smoothing across.
    disp = np.where(np.arange(30) < 15, 10.0, 14.0).astype(np.float32)[None, :].repeat(12, 0)
    out = run(disp, np.full(disp.shape, 80.0, np.float32), radius=6, gate=1.0)
    np.testing.assert_array_equal(out, disp)


def test_colour_edges_stop_the_fit_within_the_gate():
    # Surfaces at 10.0 and 10.6 px (within the gate) but of very different colours: each keeps
    # its own value because the colour weight is 0 beyond color_range.
    disp = np.where(np.arange(30) < 15, 10.0, 10.6).astype(np.float32)[None, :].repeat(12, 0)
    image = np.where(np.arange(30) < 15, 40.0, 200.0).astype(np.float32)[None, :].repeat(12, 0)
    out = run(disp, image, radius=6, gate=1.0, color_range=20.0)
    np.testing.assert_allclose(out, disp, atol=1e-5)
    blurred = run(disp, np.full(disp.shape, 80.0, np.float32), radius=6, gate=1.0)
    assert not np.allclose(blurred, disp, atol=1e-3)  # the same map with one colour is mixed


def test_one_sided_fit_moves_a_pixel_by_at_most_the_gate():
    # The last valid pixel of a row with eleven neighbours on one side, all within the 1 px gate:
    # far ones 0.99 below, near ones 0.99 above. The least-squares line, evaluated at the end
    # of the data, passes more than the gate above the pixel (leverage), so the correction
    # stops at the gate instead of extrapolating.
    d0 = 5.0
    t = np.arange(-10, 1)
    disp = np.full((1, 16), INF, np.float32)
    disp[0, :11] = d0 + np.where(t <= -8, -0.99, 0.99)
    disp[0, 10] = d0
    image = np.zeros((1, 16, 1), np.float32)
    unclamped = line_fit_reference(disp, image, 10, 1000.0, 20.0, 1.0, False, clamp=False)[0, 10] - d0
    assert unclamped > 1.1  # the case really exercises the limit
    out = kr.plane_smooth(disp, image, 10, 1000.0, 20.0, 1.0)
    assert out[0, 10] == pytest.approx(d0 + 1.0, abs=1e-5)


def test_holes_stay_holes_and_do_not_vote():
    disp = np.full((9, 9), 7.0, np.float32)
    disp[4, 4] = INF
    disp[2, 2] = INF
    out = run(disp, np.zeros((9, 9), np.float32), radius=3)
    assert np.isinf(out[4, 4]) and np.isinf(out[2, 2])
    np.testing.assert_array_equal(out[np.isfinite(disp)], 7.0)


@pytest.mark.parametrize("bad", [{"radius": 0}, {"gate": -1.0}, {"color_range": 0.0}, {"sigma": 3.0}])
def test_invalid_parameters_are_config_errors(bad):
    with pytest.raises(ConfigError):
        registry.get("refinement", "plane_smooth").make_params(bad)


def test_color_false_weighs_by_the_grey_image():
    # Two colours of equal luma: the colour distance (60) cuts the weight off beyond
    # color_range, the grey distance (0) does not, so only the grey guide averages across.
    h, w = 1, 12
    image = np.zeros((h, w, 3), np.float32)
    image[:, :6] = (100.0, 100.0, 100.0)
    image[:, 6:] = (160.0, 100.0 - 60.0 * 0.299 / 0.587, 100.0)  # +60 red, green lowered to keep the luma
    grey = np.ascontiguousarray(MatchState(image, image, 0, 64).gray("left"))
    assert abs(grey[0, 0] - grey[0, 11]) < 0.5  # the two halves have (almost) the same luma
    disp = np.where(np.arange(w) < 6, 5.0, 5.6).astype(np.float32)[None, :]
    colour = run(disp, image, radius=3, color_range=20.0, gate=1.0)
    by_grey = run(disp, image, radius=3, color_range=20.0, gate=1.0, color=False)
    np.testing.assert_allclose(colour[0, :3], 5.0, atol=1e-6)  # no weight across the colour edge
    assert by_grey[0, 5] > 5.05 and by_grey[0, 6] < 5.55  # the grey guide mixes the two sides
    # On a grey image both settings are the same computation.
    g = image[..., 0].copy()
    np.testing.assert_array_equal(run(disp, g, radius=3), run(disp, g, radius=3, color=False))
