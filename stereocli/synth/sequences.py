"""Synthetic stereo sequences with exact ground truth per frame (tests and ``benchmarks/sequence.py``).

Three kinds, each a static rig filming a scene of :mod:`.scenes` with sensor noise (Gaussian,
``noise`` grey levels, drawn anew for every frame and view):

* ``still`` — the scene holds still; only the noise changes;
* ``moving`` — a textured fronto-parallel disc in front of the still scene moves across it
  (:func:`paste_object`; its mask per frame in :attr:`SyntheticSequence.moving`);
* ``pan`` — the rig pans slowly: the whole scene shifts ``pan`` px to the left each frame
  (frames cut from one wider rendering, so the ground truth stays exact).

:func:`paste_object` also pastes the moving disc over any rectified pair with ground truth
(e.g. a Middlebury scene), with correct occlusion: the disc is nearer than everything it covers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .scenes import make_texture, render, scene_surfaces

__all__ = ["SEQUENCES", "SyntheticSequence", "make_sequence", "object_path", "paste_object", "sequence_from_pair",
           "with_noise"]

#: The kinds :func:`make_sequence` makes.
SEQUENCES = ("still", "moving", "pan")


@dataclass
class SyntheticSequence:
    """Frames of a synthetic sequence and their ground truth.

    ``left``, ``right``: lists of (H, W, 3) uint8 RGB frames; ``disparity``: (H, W) float32 ground
    truth per frame, px (+inf where unknown); ``moving``: (H, W) bool per frame, the moving
    object's pixels in the left view (all False without one); ``ndisp``: a range that holds the
    whole sequence, ``[0, ndisp)``.
    """

    kind: str
    left: list[np.ndarray] = field(default_factory=list)
    right: list[np.ndarray] = field(default_factory=list)
    disparity: list[np.ndarray] = field(default_factory=list)
    moving: list[np.ndarray] = field(default_factory=list)
    ndisp: int = 0

    def __len__(self) -> int:
        return len(self.left)

    def pairs(self):
        """The ``(left, right)`` frames in order, as :func:`stereocli.match_sequence` takes them."""
        return zip(self.left, self.right)


def with_noise(image: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``image`` (float or uint8) plus Gaussian noise of ``sigma`` grey levels, as uint8."""
    noisy = np.asarray(image, np.float32)
    if sigma > 0:
        noisy = noisy + rng.normal(0.0, sigma, noisy.shape).astype(np.float32)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def _disc_coverage(x0: float, y0: float, radius: float, shape: tuple[int, int], supersample: int = 4) -> np.ndarray:
    """Share of each pixel (centres at integer coordinates) inside the disc of ``radius`` px
    centred at (x0, y0): (H, W) float32 in [0, 1], anti-aliased like :func:`.scenes.render`."""
    h, w = shape
    cover = np.zeros(shape, np.float32)
    top, bottom = max(int(np.floor(y0 - radius - 1)), 0), min(int(np.ceil(y0 + radius + 2)), h)
    first, last = max(int(np.floor(x0 - radius - 1)), 0), min(int(np.ceil(x0 + radius + 2)), w)
    if top >= bottom or first >= last:
        return cover
    ys, xs = np.mgrid[top:bottom, first:last].astype(np.float64)
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    inside = np.zeros(ys.shape, np.float64)
    for oy in offsets:
        for ox in offsets:
            inside += (xs + ox - x0) ** 2 + (ys + oy - y0) ** 2 < radius**2
    cover[top:bottom, first:last] = inside / supersample**2
    return cover


def _texture_at(texture: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``texture`` (Ht, Wt, 3) float32 sampled bilinearly at (x, y) (its own pixel coordinates)."""
    import cv2

    return cv2.remap(texture, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)


def paste_object(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, texture: np.ndarray, *,
                 centre: tuple[float, float], radius: float,
                 object_disparity: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Paste a textured fronto-parallel disc in front of a rectified pair.

    ``left``, ``right``: (H, W, 3) float32 views (noise-free); ``disparity``: (H, W) float32
    left ground truth; ``texture``: (Ht, Wt, 3) float32, painted on the disc (the disc's centre
    shows the texture's centre); ``centre`` (x, y) px in the left view; ``object_disparity`` px,
    larger than every disparity the disc covers (it is nearer). Returns ``(left, right,
    disparity, mask)`` with the disc pasted: anti-aliased edges in both views, the disc's
    disparity where it covers more than half a left pixel, ``mask`` (H, W) bool those pixels.
    """
    h, w = disparity.shape
    cx, cy = centre
    th, tw = texture.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    # The disc's texture moves with it: a scene point at (x, y) of the left view shows the
    # texture at (x - cx, y - cy) from its centre; the right view sees it at xr = x - d.
    out = []
    for view, shift in ((left, 0.0), (right, object_disparity)):
        cover = _disc_coverage(cx - shift, cy, radius, (h, w))[..., None]
        painted = _texture_at(texture, xs - (cx - shift) + tw / 2, ys - cy + th / 2)
        out.append(np.asarray(view, np.float32) * (1.0 - cover) + painted * cover)
    mask = _disc_coverage(cx, cy, radius, (h, w)) > 0.5
    gt = np.where(mask, np.float32(object_disparity), disparity).astype(np.float32)
    return out[0], out[1], gt, mask


def object_path(frame: int, frames: int, width: int, height: int) -> tuple[float, float]:
    """Centre (x, y) px of the moving disc in ``frame`` of ``frames``: left to right across the
    middle of the image with a slight vertical sway, a few px per frame."""
    t = frame / max(frames - 1, 1)
    return 0.25 * width + 0.5 * width * t, 0.5 * height + 0.06 * height * np.sin(2 * np.pi * t)


def make_sequence(kind: str, *, frames: int = 8, width: int = 320, height: int = 240, noise: float = 3.0,
                  seed: int = 0, scene: str = "planes", pan: int = 1, supersample: int = 2) -> SyntheticSequence:
    """Make a synthetic sequence of ``kind`` (``still``, ``moving`` or ``pan``, see the module docstring).

    ``frames`` frames of ``width`` x ``height`` px, sensor noise ``noise`` grey levels; the
    scene is :func:`.scenes.scene_surfaces`' ``scene`` (disparities of about 6..34 px at
    320 px wide; they scale with the width); ``pan``: the pan's shift per frame, px;
    ``supersample``: the rendering's anti-aliasing. Deterministic for a ``seed``.
    """
    if kind not in SEQUENCES:
        raise ValueError(f"unknown synthetic sequence {kind!r}; valid: {', '.join(SEQUENCES)}")
    # A pan's frames are cut from one rendering ``extra`` px wider (the scene goes on to the right).
    extra = pan * (frames - 1) if kind == "pan" else 0
    base = render(_scaled_surfaces(scene, width, height, seed), width + extra, height,
                  supersample=supersample, noise=0.0)
    left, right, gt = (base[k] for k in ("left", "right", "disparity"))
    if kind != "pan":
        return sequence_from_pair(left, right, gt, frames=frames, noise=noise, seed=seed, moving=kind == "moving",
                                  kind=kind)
    rng = np.random.default_rng(seed + 1000)
    seq = SyntheticSequence(kind)
    for i in range(frames):
        cut = slice(i * pan, i * pan + width)
        seq.left.append(with_noise(left[:, cut], noise, rng))
        seq.right.append(with_noise(right[:, cut], noise, rng))
        seq.disparity.append(np.ascontiguousarray(gt[:, cut], dtype=np.float32))
        seq.moving.append(np.zeros((height, width), bool))
    seq.ndisp = _range_of(seq.disparity)
    return seq


def sequence_from_pair(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, *, frames: int = 8,
                       noise: float = 3.0, seed: int = 0, moving: bool = True, kind: str = "moving",
                       radius: float | None = None) -> SyntheticSequence:
    """A static rig filming a rectified pair with ground truth (e.g. a Middlebury scene) for
    ``frames`` frames with sensor noise ``noise``; with ``moving``, a textured disc (``radius``
    px, default 0.14 of the smaller side) nearer than the whole scene moves across it
    (:func:`object_path`, :func:`paste_object`).

    ``left``, ``right``: (H, W, 3) views (uint8 or float), ``disparity``: (H, W) float32 left
    ground truth, +inf where unknown.
    """
    h, w = disparity.shape
    left = np.asarray(left, np.float32)
    right = np.asarray(right, np.float32)
    if left.ndim == 2:
        left, right = (np.repeat(v[..., None], 3, axis=2) for v in (left, right))
    rng = np.random.default_rng(seed + 1000)
    seq = SyntheticSequence(kind)
    radius = 0.14 * min(w, h) if radius is None else radius
    texture = make_texture(np.random.default_rng(seed + 7), (int(4 * radius) + 8, int(4 * radius) + 8),
                           base=(200, 170, 60))
    known = disparity[np.isfinite(disparity)]
    object_disparity = float(np.ceil(known.max() if known.size else 0.0)) + 0.03 * w
    for i in range(frames):
        now_left, now_right, gt, mask = left, right, disparity, np.zeros((h, w), bool)
        if moving:
            now_left, now_right, gt, mask = paste_object(left, right, disparity, texture,
                                                         centre=object_path(i, frames, w, h), radius=radius,
                                                         object_disparity=object_disparity)
        seq.left.append(with_noise(now_left, noise, rng))
        seq.right.append(with_noise(now_right, noise, rng))
        seq.disparity.append(np.ascontiguousarray(gt, dtype=np.float32))
        seq.moving.append(mask)
    seq.ndisp = _range_of(seq.disparity)
    return seq


def _range_of(disparities: list[np.ndarray]) -> int:
    """A range ``[0, ndisp)`` holding every finite disparity, ``ndisp`` a multiple of 16."""
    top = max(float(d[np.isfinite(d)].max(initial=0.0)) for d in disparities)
    return int(np.ceil((top + 2) / 16.0) * 16)


def _scaled_surfaces(scene: str, width: int, height: int, seed: int):
    """The surfaces of ``scene`` laid out for a ``width`` x ``height`` frame, as the scene looks at
    its design size of 320 x 240 px magnified: footprints and textures of the frame's layout,
    disparities ``d(x, y) = s * d320(x / s, y / t)`` with ``s = width / 320``, ``t = height / 240``."""
    from .scenes import Surface

    sx, sy = width / 320.0, height / 240.0
    surfaces = scene_surfaces(scene, width, height, seed)
    if (sx, sy) == (1.0, 1.0):
        return surfaces
    design = scene_surfaces(scene, 320, 240, seed)

    def scaled(f):
        return lambda x, y: sx * f(x / sx, y / sy)

    return [Surface(scaled(d.disparity), s.footprint, s.texture, s.texture_scale) for s, d in zip(surfaces, design)]
