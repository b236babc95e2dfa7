"""A tiny synthetic stereo scene with a known piecewise-constant disparity (local-method tests).

A foreground rectangle of random texture at disparity ``d_fg`` in front of a textured
background at ``d_bg``: ``right(x - d) = left(x)`` exactly wherever the point is visible in
both views, so WTA on a good cost must recover the disparity away from borders/occlusions.
"""

from __future__ import annotations

import cv2
import numpy as np


def scene(h: int = 64, w: int = 96, d_bg: int = 3, d_fg: int = 9, *, color: bool = True, seed: int = 0):
    """Returns ``left, right`` float32 in [0, 255], ``gt`` (H, W) px and ``mask`` (H, W) bool of
    the pixels to score (visible in both views, away from borders and depth edges)."""
    rng = np.random.default_rng(seed)
    nc = 3 if color else 1

    def texture(level):
        t = rng.uniform(0, 255, (h, w + 40, nc)).astype(np.float32)
        t = cv2.GaussianBlur(t, (0, 0), 1.0).reshape(h, w + 40, nc)
        return np.clip((t - t.mean()) * 3 + 128 + level, 0, 255)

    left, right, gt, (y0, y1, x0, x1) = render(texture(-30), texture(30), h, w, d_bg, d_fg)
    mask = np.zeros((h, w), bool)
    mask[8:-8, 16:-8] = True
    # leave out 4 px around the depth edges (windows straddle them) and the occluded band
    mask[y0 - 4:y1 + 4, x0 - 4 - (d_fg - d_bg):x0 + 4] = False
    mask[y0 - 4:y1 + 4, x1 - 4:x1 + 4] = False
    mask[y0 - 4:y0 + 4, x0:x1] = False
    mask[y1 - 4:y1 + 4, x0:x1] = False
    if not color:
        left, right = left[..., 0], right[..., 0]
    return np.ascontiguousarray(left, np.float32), np.ascontiguousarray(right, np.float32), gt, mask


def render(back: np.ndarray, front: np.ndarray, h: int, w: int, d_bg: int, d_fg: int,
           rect: tuple[int, int, int, int] | None = None):
    """Both views of a rectangle cut from ``front`` (rows ``y0:y1``, columns ``x0:x1`` of ``rect``;
    by default the middle third of the width, half of the height) at disparity ``d_fg`` before
    ``back`` at ``d_bg`` (both (h, w + 40, C) textures): ``left, right, gt, (y0, y1, x0, x1)``."""
    y0, y1, x0, x1 = rect if rect is not None else (h // 4, 3 * h // 4, w // 3, 2 * w // 3)
    xs = np.arange(w)
    left = back[:, :w].copy()
    left[y0:y1, x0:x1] = front[y0:y1, x0:x1]
    right = back[:, xs + d_bg].copy()
    inside = (xs + d_fg >= x0) & (xs + d_fg < x1)
    right[y0:y1][:, inside] = front[y0:y1][:, (xs + d_fg)[inside]]
    gt = np.full((h, w), d_bg, np.float32)
    gt[y0:y1, x0:x1] = d_fg
    return left, right, gt, (y0, y1, x0, x1)


def two_colour_scene(h: int = 48, w: int = 96, d_bg: int = 3, d_fg: int = 10, seed: int = 0):
    """A reddish object (disparity ``d_fg``) before a greenish background (``d_bg``), each with a
    weak texture of its own (±12 grey levels): ``left, right, gt, (y0, y1, x0, x1)``."""
    rng = np.random.default_rng(seed)

    def texture(base):
        t = cv2.GaussianBlur(rng.normal(0, 1, (h, w + 40)).astype(np.float32), (0, 0), 1.0)
        return np.clip(np.asarray(base, np.float32) + (t / t.std() * 12.0)[..., None], 0, 255)

    left, right, gt, rect = render(texture((70, 110, 60)), texture((190, 90, 80)), h, w, d_bg, d_fg)
    return np.ascontiguousarray(left), np.ascontiguousarray(right), gt, rect


def run_stages(left, right, ndisp, stages, min_disp=0):
    """Run ``[(kind, name, params dict), ...]`` on a MatchState; returns the state."""
    from stereocli import registry
    from stereocli.matching.state import MatchState

    state = MatchState(left.copy(), right.copy(), min_disp, ndisp)
    for kind, name, values in stages:
        stage = registry.get(kind, name)
        stage.func(state, stage.make_params(values))
    return state


def wta(state):
    from stereocli.matching.kernels.winners import wta_left

    return wta_left(state.cost, state.min_disp, state.cost_max)[0]
