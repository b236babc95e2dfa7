"""Synthetic rectified stereo scenes with exact ground truth, in Middlebury 2014 layout.

A scene is a stack of surfaces seen from the left camera. Each surface has a footprint in
left-image coordinates, a disparity function ``d(x, y)`` and a texture painted on it as seen
from the left camera (so the left image is the texture itself and the right image sees it
shifted, stretched and occluded). Rendering is exact up to supersampling:

* left pixel (x, y) shows the surface with the largest disparity among those whose footprint
  contains (x, y);
* right pixel (xr, y) shows, for each surface, the left point x solving ``x - d(x, y) = xr``
  (fixed-point iteration; converges since |∂d/∂x| < 1), and keeps the nearest (largest d);
* ground truth ``disp0GT.pfm`` is ``d`` at left pixel centres; ``mask0nocc.png`` is 255
  where the same surface point is visible in the right view, 128 where it is occluded
  (Middlebury's convention; every pixel has GT here).

Pixel centres are at integer coordinates. Images are averaged over ``supersample²``
sub-pixel samples, so edges are anti-aliased like a real camera's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..io.images import write_image
from ..io.middlebury import MiddleburyCalib, write_calib_txt
from ..io.pfm import write_pfm


@dataclass
class Surface:
    """One surface: footprint mask, disparity and texture as functions of left coordinates."""

    disparity: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (x, y) -> d, px
    footprint: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (x, y) -> bool
    texture: np.ndarray  # (Ht, Wt, 3) float32 texture sampled at (x, y) * texture_scale
    texture_scale: float = 2.0


def make_texture(rng: np.random.Generator, shape: tuple[int, int], *, contrast: float = 1.0,
                 base: tuple[float, float, float] = (128, 128, 128), blur: float = 1.2) -> np.ndarray:
    """Band-limited random colour texture, float32 (H, W, 3) in [0, 255].

    Multi-scale noise gives texture at several frequencies (like real scenes); ``contrast``
    near 0 makes a low-texture surface.
    """
    h, w = shape
    tex = np.zeros((h, w, 3), np.float32)
    for scale, weight in ((1, 0.4), (4, 0.35), (16, 0.25)):
        size = ((h + scale - 1) // scale + 1, (w + scale - 1) // scale + 1)
        # Mostly luminance with a weaker colour component, like natural surfaces.
        small = rng.normal(0, 1, size + (1,)) + 0.35 * rng.normal(0, 1, size + (3,))
        up = cv2.resize(small.astype(np.float32), None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)[:h, :w]
        tex += weight * up
    tex = cv2.GaussianBlur(tex, (0, 0), blur)
    tex /= tex.std() + 1e-6
    out = np.asarray(base, np.float32) + 45.0 * contrast * tex
    return np.clip(out, 5, 250).astype(np.float32)


def _sample(texture: np.ndarray, x: np.ndarray, y: np.ndarray, scale: float) -> np.ndarray:
    mapx = (x * scale + 8).astype(np.float32)  # +8: footprints may start slightly outside
    mapy = (y * scale + 8).astype(np.float32)
    return cv2.remap(texture, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def _visible(surfaces: list[Surface], x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index and disparity of the nearest surface at left coordinates (x, y)."""
    best_d = np.full(x.shape, -np.inf)
    best_s = np.full(x.shape, -1, np.int32)
    for i, s in enumerate(surfaces):
        d = s.disparity(x, y)
        take = s.footprint(x, y) & (d > best_d)
        best_d = np.where(take, d, best_d)
        best_s = np.where(take, i, best_s)
    return best_s, best_d


def _visible_right(surfaces: list[Surface], xr: np.ndarray, y: np.ndarray):
    """For right coordinates: index, disparity and left x of the nearest surface."""
    best_d = np.full(xr.shape, -np.inf)
    best_s = np.full(xr.shape, -1, np.int32)
    best_x = np.zeros(xr.shape)
    for i, s in enumerate(surfaces):
        x = xr + s.disparity(xr, y)
        for _ in range(40):  # fixed point of x = xr + d(x, y)
            x = xr + s.disparity(x, y)
        d = s.disparity(x, y)
        take = s.footprint(x, y) & (d > best_d)
        best_d = np.where(take, d, best_d)
        best_s = np.where(take, i, best_s)
        best_x = np.where(take, x, best_x)
    return best_s, best_d, best_x


def _shade(surfaces: list[Surface], idx: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    out = np.zeros(x.shape + (3,), np.float32)
    for i, s in enumerate(surfaces):
        sel = idx == i
        if sel.any():
            out[sel] = _sample(s.texture, x, y, s.texture_scale)[sel]
    return out


def render(surfaces: list[Surface], width: int, height: int, *, supersample: int = 3,
           noise: float = 0.0, seed: int = 0, right_row_offset: float = 0.0) -> dict[str, np.ndarray]:
    """Render left/right images (uint8 RGB), GT disparity (float32) and nonocc mask (uint8).

    ``right_row_offset`` (px) renders a pair whose rows do not quite meet: a point of left row
    y appears at row y + offset in the right view (the GT and mask stay those of the left view)."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    left: np.ndarray = np.zeros((height, width, 3), np.float32)
    right: np.ndarray = np.zeros((height, width, 3), np.float32)
    for oy in offsets:
        for ox in offsets:
            x, y = xs + ox, ys + oy
            idx, _ = _visible(surfaces, x, y)
            left += _shade(surfaces, idx, x, y)
            ry = y - right_row_offset  # the scene row the right view's row y shows
            ridx, _, rx = _visible_right(surfaces, x, ry)
            right += _shade(surfaces, ridx, rx, ry)
    n = supersample * supersample
    left, right = left / n, right / n
    if noise > 0:
        left += rng.normal(0, noise, left.shape).astype(np.float32)
        right += rng.normal(0, noise, right.shape).astype(np.float32)
    idx, gt = _visible(surfaces, xs, ys)
    # Non-occluded: the right view at x - d shows the same surface at the same disparity.
    ridx, rd, _ = _visible_right(surfaces, xs - gt, ys)
    nonocc = (xs - gt >= -0.5) & (ridx == idx) & (np.abs(rd - gt) < 1e-3)
    mask = np.where(nonocc, 255, 128).astype(np.uint8)

    def to8(im: np.ndarray) -> np.ndarray:
        return np.clip(np.round(im), 0, 255).astype(np.uint8)

    return {"left": to8(left), "right": to8(right), "disparity": gt.astype(np.float32), "mask": mask}


def _plane(a: float, b: float, c: float):
    return lambda x, y: a * x + b * y + c


def _rect(x0: float, y0: float, x1: float, y1: float):
    return lambda x, y: (x >= x0) & (x < x1) & (y >= y0) & (y < y1)


def _everywhere(x, y):
    return np.ones(np.shape(x), bool)


def scene_surfaces(name: str, width: int, height: int, seed: int = 0) -> list[Surface]:
    """The surfaces of a named synthetic scene (``planes`` or ``curved``)."""
    rng = np.random.default_rng(seed)
    tex_shape = (int(height * 2 + 40), int(width * 2 + 40))
    tex = lambda **kw: make_texture(rng, tex_shape, **kw)  # noqa: E731
    if name == "planes":
        return [
            # Background: a slanted plane (floor-like gradient in y, slight yaw in x).
            Surface(_plane(0.03, 0.04, 6.0), _everywhere, tex(base=(120, 110, 100))),
            # Low-texture wall patch: almost uniform, the classic failure case for matching.
            Surface(_plane(0.0, 0.0, 14.0), _rect(0.08 * width, 0.1 * height, 0.33 * width, 0.45 * height),
                    tex(contrast=0.06, base=(170, 170, 175))),
            # A slanted board in the middle distance.
            Surface(_plane(-0.05, 0.02, 30.0), _rect(0.45 * width, 0.2 * height, 0.8 * width, 0.75 * height),
                    tex(base=(90, 130, 150))),
            # A fronto-parallel foreground box that occludes the board and the background.
            Surface(_plane(0.0, 0.0, 34.0), _rect(0.3 * width, 0.55 * height, 0.55 * width, 0.9 * height),
                    tex(base=(150, 90, 80))),
        ]
    if name == "curved":
        r = 0.28 * min(width, height)
        sx, sy = 0.38 * width, 0.5 * height

        def sphere_d(x, y):
            # Disparity of a sphere-like bump: 18 px at the rim rising to 30 px at the centre.
            q = np.clip(1.0 - ((x - sx) ** 2 + (y - sy) ** 2) / r**2, 0.0, 1.0)
            return 18.0 + 12.0 * np.sqrt(q)

        def sphere_fp(x, y):
            return (x - sx) ** 2 + (y - sy) ** 2 < r**2

        def cylinder_d(x, y):
            # A vertical cylinder: disparity varies across x only.
            u = np.clip((x - 0.78 * width) / (0.12 * width), -1.0, 1.0)
            return 20.0 + 8.0 * np.sqrt(1.0 - u**2)

        return [
            Surface(_plane(0.02, -0.03, 12.0), _everywhere, tex(base=(110, 120, 110))),
            Surface(sphere_d, sphere_fp, tex(base=(160, 120, 90))),
            Surface(cylinder_d, _rect(0.66 * width, 0.08 * height, 0.9 * width, 0.92 * height),
                    tex(base=(90, 110, 160))),
            # Low-texture strip near the top.
            Surface(_plane(0.0, 0.0, 9.0), _rect(0.05 * width, 0.03 * height, 0.6 * width, 0.16 * height),
                    tex(contrast=0.05, base=(200, 195, 190))),
        ]
    raise ValueError(f"unknown synthetic scene {name!r}; valid: planes, curved")


SCENES = ("planes", "curved")


def write_scene(folder: str | Path, name: str, *, width: int = 320, height: int = 240, seed: int = 0,
                focal: float = 500.0, baseline_mm: float = 100.0, noise: float = 0.8) -> dict:
    """Render scene ``name`` into ``folder`` in Middlebury 2014 layout; returns the arrays."""
    folder = Path(folder)
    out = render(scene_surfaces(name, width, height, seed), width, height, noise=noise, seed=seed)
    gt = out["disparity"]
    ndisp = int(np.ceil(gt.max() / 16.0) * 16)
    calib = MiddleburyCalib(
        cam0=np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]]),
        cam1=np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]]),
        doffs=0.0, baseline=baseline_mm, width=width, height=height, ndisp=ndisp, isint=0,
        vmin=float(np.floor(gt.min())), vmax=float(np.ceil(gt.max())),
    )
    write_image(folder / "im0.png", out["left"])
    write_image(folder / "im1.png", out["right"])
    write_pfm(folder / "disp0GT.pfm", gt)
    write_image(folder / "mask0nocc.png", out["mask"])
    write_calib_txt(folder / "calib.txt", calib)
    return out


def warp_pair(texture: np.ndarray, disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Right image for a left image and a smooth disparity map by backward sampling.

    For tests: ``right(xr, y) = left(xr + d, y)``, exact for constant disparity. Returns
    ``(left, right)`` float32.
    """
    h, w = disparity.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    right = cv2.remap(texture.astype(np.float32), xs + disparity.astype(np.float32), ys, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REFLECT)
    return texture.astype(np.float32), right
