"""A synthetic stereo rig with known K, D, R, T: checkerboard views and a textured 3-D scene.

Rendering is exact ray casting, not image warping: every (super-sampled) output pixel is
undistorted to a viewing ray (``cv2.undistortPoints`` iterated to 1e-12), the ray hits the
board plane (inverse homography) or the scene planes, and the analytic checker/texture value
there is averaged over ``supersample²`` sub-pixels (box-filter anti-aliasing, so corners are
unbiased to a few hundredths of a pixel). A light Gaussian blur (σ = 0.5 px) stands in for
optics.

Conventions follow OpenCV: ``X_right = R · X_left + T``; the left camera frame is x right,
y down, z forward; lengths in metres.

Functions for the lead / tests:

* :func:`default_rig` – the true rig (640x480, mild distortion, 0.12 m baseline).
* :func:`render_rig` – write ``left/NN.png``, ``right/NN.png`` and ``truth.yml``.
* :func:`render_scene` – an unrectified pair of a textured multi-plane scene plus its true
  depth map (Z in the left camera) and a :class:`SyntheticScene` for exact ray queries.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..io.calib import StereoCalibration, write_opencv
from ..io.images import write_image


@dataclass
class Rig:
    """True rig: intrinsics, distortion (k1 k2 p1 p2 k3), ``X_right = R·X_left + T`` (metres)."""

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    size: tuple[int, int] = (640, 480)
    units: str = "m"

    def calibration(self) -> StereoCalibration:
        return StereoCalibration(K1=self.K1, D1=self.D1, K2=self.K2, D2=self.D2, R=self.R, T=self.T,
                                 image_size=self.size, units=self.units)


def default_rig(size: tuple[int, int] = (640, 480)) -> Rig:
    """The reference rig: f ≈ 600 px at 640x480, k1 ≈ -0.1, baseline 0.12 m, ~0.8° relative rotation."""
    sx = size[0] / 640.0
    K1 = np.array([[600.0 * sx, 0, 322.5 * sx], [0, 601.0 * sx, 238.0 * sx], [0, 0, 1]])
    K2 = np.array([[606.0 * sx, 0, 317.0 * sx], [0, 605.0 * sx, 243.5 * sx], [0, 0, 1]])
    D1 = np.array([-0.12, 0.06, 0.0006, -0.0004, 0.0])
    D2 = np.array([-0.10, 0.04, -0.0005, 0.0003, 0.0])
    R = cv2.Rodrigues(np.array([0.004, -0.012, 0.003]))[0]
    centre_right = np.array([0.12, 0.0015, -0.002])  # right camera centre in the left frame
    T = -R @ centre_right
    return Rig(K1, D1, K2, D2, R, T, size)


def _pixel_rays(K: np.ndarray, D: np.ndarray, size: tuple[int, int], supersample: int) -> np.ndarray:
    """Undistorted normalised coordinates (H·S, W·S, 2) of the sub-pixel sample positions.

    Exact undistortion (``cv2.undistortPoints`` to 1e-14) on the integer pixel grid, then
    separable linear interpolation to the sub-pixel samples: the distortion field is so
    smooth that this adds < 1e-4 px of error while being ~S² times cheaper.
    """
    w, h = size
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    xs = np.arange(-1, w + 1, dtype=np.float64)
    ys = np.arange(-1, h + 1, dtype=np.float64)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    field = cv2.undistortPoints(grid, K, D, criteria=crit).reshape(ys.size, xs.size, 2)
    sx = (np.arange(w)[:, None] + offs[None, :]).ravel() + 1.0  # index into xs
    sy = (np.arange(h)[:, None] + offs[None, :]).ravel() + 1.0
    ix, fx = np.floor(sx).astype(np.int64), sx - np.floor(sx)
    iy, fy = np.floor(sy).astype(np.int64), sy - np.floor(sy)
    along_x = field[:, ix] * (1 - fx)[None, :, None] + field[:, ix + 1] * fx[None, :, None]
    return along_x[iy] * (1 - fy)[:, None, None] + along_x[iy + 1] * fy[:, None, None]


def _downsample(img: np.ndarray, s: int) -> np.ndarray:
    h, w = img.shape[0] // s, img.shape[1] // s
    return img.reshape(h, s, w, s, *img.shape[2:]).mean(axis=(1, 3))


def _finish(img: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.5)
    if noise > 0:
        img = img + rng.normal(0, noise, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Board:
    """Checkerboard with ``cols x rows`` inner corners, square side ``square`` (m), white margin."""

    cols: int = 9
    rows: int = 6
    square: float = 0.04
    margin: float = 0.5  # in squares

    def outline(self) -> np.ndarray:
        m = (1 + self.margin) * self.square
        x0, x1 = -m, (self.cols - 1) * self.square + m
        y0, y1 = -m, (self.rows - 1) * self.square + m
        return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)

    def shade(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Grey level at board coordinates (s, t) (H, W): anti-aliased checker, white margin, grey outside.

        The checker is the product of two square waves; each wave is replaced by a linear ramp
        one sample wide across its edges (distance to the edge measured in samples through the
        local Jacobian), which is the box-filtered edge: corners stay unbiased at any pose.
        """
        sq = self.square

        def wave(c: np.ndarray) -> np.ndarray:
            gy, gx = np.gradient(c)
            scale = np.sqrt(gx * gx + gy * gy) + 1e-12  # board units per sample
            frac = c / sq - np.floor(c / sq)  # position inside the square, [0, 1)
            dist = np.minimum(frac, 1.0 - frac) * sq / scale  # samples to the nearest grid line
            sign = np.where(np.floor(c / sq).astype(np.int64) & 1, -1.0, 1.0)
            return sign * np.clip(2.0 * dist, 0.0, 1.0)

        checker = 125.0 - 100.0 * wave(s) * wave(t)
        inner = (s >= -sq) & (s < self.cols * sq) & (t >= -sq) & (t < self.rows * sq)
        o = self.outline()
        on_board = (s >= o[0, 0]) & (s <= o[1, 0]) & (t >= o[0, 1]) & (t <= o[2, 1])
        value = np.where(inner, checker, 225.0)
        return np.where(on_board, value, 110.0)


def _render_board(rays: np.ndarray, Rb: np.ndarray, tb: np.ndarray, board: Board, s: int) -> np.ndarray:
    # Board point (a, b, 0) → camera Rb[:, :2]·(a, b) + tb, i.e. ray (x, y, 1) ~ H·(a, b, 1).
    H = np.column_stack([Rb[:, 0], Rb[:, 1], tb])
    Hinv = np.linalg.inv(H)
    x, y = rays[..., 0], rays[..., 1]
    a = Hinv[0, 0] * x + Hinv[0, 1] * y + Hinv[0, 2]
    b = Hinv[1, 0] * x + Hinv[1, 1] * y + Hinv[1, 2]
    c = Hinv[2, 0] * x + Hinv[2, 1] * y + Hinv[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        sa, sb = a / c, b / c
    with np.errstate(invalid="ignore"):
        value = board.shade(np.where(c > 0, sa, -1e3), np.where(c > 0, sb, -1e3))  # behind the camera: background
    return _downsample(value, s)


def _visible(rig: Rig, Rb: np.ndarray, tb: np.ndarray, board: Board, border: float) -> bool:
    pts = board.outline()
    w, h = rig.size
    for K, D, Rc, Tc in ((rig.K1, rig.D1, np.eye(3), np.zeros(3)), (rig.K2, rig.D2, rig.R, rig.T)):
        cam = (Rc @ (Rb @ pts.T + tb[:, None])).T + Tc
        if np.any(cam[:, 2] <= 0.1):
            return False
        proj, _ = cv2.projectPoints(cam, np.zeros(3), np.zeros(3), K, D)
        proj = proj.reshape(-1, 2)
        if np.any(proj < border) or np.any(proj[:, 0] > w - 1 - border) or np.any(proj[:, 1] > h - 1 - border):
            return False
        # Keep the board facing the camera well enough for the detector.
        normal = Rc @ Rb[:, 2]
        centre = Rc @ (Rb @ pts.mean(axis=0) + tb) + Tc
        if abs(normal @ centre) / np.linalg.norm(centre) < 0.5:
            return False
    return True


def board_poses(rig: Rig, board: Board, n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` varied, fully visible board poses (Rb, tb) in the left camera frame."""
    rng = np.random.default_rng(seed)
    centre = np.array([(board.cols - 1) * board.square / 2, (board.rows - 1) * board.square / 2, 0.0])
    poses: list[tuple[np.ndarray, np.ndarray]] = []
    attempts = last_ok = 0
    while len(poses) < n:
        attempts += 1
        if attempts > 20000:
            raise RuntimeError("could not place the synthetic board; the rig or board is unusual")
        k = len(poses)
        # Cycle tilt directions so the set constrains focal length and distortion well.
        tilt = np.deg2rad(np.array([rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-20, 20)]))
        if k % 4 == 3:
            tilt[:2] *= 0.4
        Rb = cv2.Rodrigues(tilt)[0]
        # Stratify the board centre over a 3x3 grid of image cells (corners matter for
        # distortion), drawing back towards the centre after failed attempts.
        cell = k % 9
        shrink = max(0.3, 1.0 - 0.002 * attempts_here) if (attempts_here := attempts - last_ok) else 1.0
        u = ((cell % 3) + rng.uniform(0.1, 0.9)) / 3 * 2 - 1
        v = ((cell // 3) + rng.uniform(0.1, 0.9)) / 3 * 2 - 1
        z = rng.uniform(0.45, 0.85)
        w, h = rig.size
        fx = rig.K1[0, 0]
        pos = np.array([u * shrink * (w / 2) / fx * z + 0.06, v * shrink * (h / 2) / fx * z, z])
        tb = pos - Rb @ centre
        if _visible(rig, Rb, tb, board, border=6.0):
            poses.append((Rb, tb))
            last_ok = attempts
    return poses


def render_rig(out_dir: str | os.PathLike, *, n_pairs: int = 12, rig: Rig | None = None, board: Board | None = None,
               seed: int = 0, supersample: int = 2, noise: float = 0.0) -> dict:
    """Render ``n_pairs`` checkerboard stereo pairs and the truth file.

    Writes ``out_dir/left/NN.png``, ``out_dir/right/NN.png`` (8-bit grey) and
    ``out_dir/truth.yml`` (OpenCV FileStorage, readable by ``load_calibration``: M1 D1 M2 D2
    R T, image size, units ``m``, plus ``pattern_cols``, ``pattern_rows``, ``pattern_type``,
    ``square_size``). Returns ``{"rig", "board", "poses", "left", "right", "truth"}``.
    """
    rig = rig or default_rig()
    board = board or Board()
    out = Path(out_dir)
    rng = np.random.default_rng(seed + 1)
    rays1 = _pixel_rays(rig.K1, rig.D1, rig.size, supersample)
    rays2 = _pixel_rays(rig.K2, rig.D2, rig.size, supersample)
    poses = board_poses(rig, board, n_pairs, seed)
    lefts, rights = [], []
    for k, (Rb, tb) in enumerate(poses):
        left = _finish(_render_board(rays1, Rb, tb, board, supersample), rng, noise)
        right = _finish(_render_board(rays2, rig.R @ Rb, rig.R @ tb + rig.T, board, supersample), rng, noise)
        lp, rp = out / "left" / f"{k + 1:02d}.png", out / "right" / f"{k + 1:02d}.png"
        write_image(lp, left)
        write_image(rp, right)
        lefts.append(str(lp))
        rights.append(str(rp))
    calib = rig.calibration()
    calib.extra.update({"pattern_type": "chessboard", "pattern_cols": board.cols, "pattern_rows": board.rows,
                        "square_size": float(board.square)})
    truth = out / "truth.yml"
    write_opencv(truth, calib)
    return {"rig": rig, "board": board, "poses": poses, "left": lefts, "right": rights, "truth": str(truth)}


# --------------------------------------------------------------------------- textured 3-D scene

@dataclass
class Plane:
    """A textured rectangle: ``origin + u·axis_u + v·axis_v`` for u in [0, width], v in [0, height] (m)."""

    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    width: float
    height: float
    texture: np.ndarray  # (th, tw) float32 grey levels
    texel: float  # metres per texture pixel

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.axis_u, self.axis_v)
        return n / np.linalg.norm(n)


@dataclass
class SyntheticScene:
    """Planes in the left camera frame (metres); nearest hit wins."""

    planes: list[Plane] = field(default_factory=list)
    background: float = 60.0

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ray parameters t (inf = miss), plane index, and (u, v) texture coordinates.

        ``origins`` (3,) or (..., 3) and ``dirs`` (..., 3) in the left camera frame.
        """
        shape = dirs.shape[:-1]
        best = np.full(shape, np.inf)
        index = np.full(shape, -1, dtype=np.int64)
        uu = np.zeros(shape)
        vv = np.zeros(shape)
        for k, p in enumerate(self.planes):
            n = p.normal
            denom = dirs @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((p.origin - origins) @ n) / denom if np.ndim(origins) == 1 else \
                    np.sum((p.origin - origins) * n, axis=-1) / denom
            hit = origins + t[..., None] * dirs
            rel = hit - p.origin
            u, v = rel @ p.axis_u, rel @ p.axis_v
            ok = (t > 0) & (u >= 0) & (u <= p.width) & (v >= 0) & (v <= p.height) & (t < best)
            best = np.where(ok, t, best)
            index = np.where(ok, k, index)
            uu = np.where(ok, u, uu)
            vv = np.where(ok, v, vv)
        return best, index, uu, vv

    def depth_along(self, directions: np.ndarray) -> np.ndarray:
        """Distance (m) from the left camera centre to the scene along each direction (..., 3)."""
        d = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
        t, _, _, _ = self.intersect(np.zeros(3), d)
        return t

    def shade(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t, index, u, v = self.intersect(origins, dirs)
        value = np.full(t.shape, self.background, dtype=np.float32)
        for k, p in enumerate(self.planes):
            sel = index == k
            if not sel.any():
                continue
            value[sel] = _bilinear(p.texture, u[sel] / p.texel, v[sel] / p.texel)
        return value, t


def _bilinear(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = tex.shape
    x = np.clip(x, 0, w - 1.001)
    y = np.clip(y, 0, h - 1.001)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    top = tex[y0, x0] * (1 - fx) + tex[y0, x0 + 1] * fx
    bottom = tex[y0 + 1, x0] * (1 - fx) + tex[y0 + 1, x0 + 1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def _texture(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    # Multi-scale random texture: strong enough for any matcher at every scale.
    tex = np.zeros(shape, dtype=np.float32)
    for sigma, weight in ((1.0, 1.0), (3.0, 0.7), (8.0, 0.5)):
        layer = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma)
        tex += weight * layer / layer.std()
    tex = (tex - tex.mean()) / tex.std()
    return np.clip(128 + 45 * tex, 5, 250).astype(np.float32)


def default_scene(seed: int = 0) -> SyntheticScene:
    """A slanted back wall at ~1.6 m, a tilted board at ~0.9 m and a small box face at ~1.2 m."""
    rng = np.random.default_rng(seed)

    def plane(centre, yaw, pitch, width, height, texel):
        Ry = cv2.Rodrigues(np.array([0.0, np.deg2rad(yaw), 0.0]))[0]
        Rx = cv2.Rodrigues(np.array([np.deg2rad(pitch), 0.0, 0.0]))[0]
        Rm = Ry @ Rx
        au, av = Rm[:, 0], Rm[:, 1]
        origin = np.asarray(centre, dtype=np.float64) - au * width / 2 - av * height / 2
        tex = _texture(rng, (int(height / texel) + 2, int(width / texel) + 2))
        return Plane(origin, au, av, width, height, tex, texel)

    return SyntheticScene([
        plane([0.0, 0.0, 1.7], 12, -5, 4.0, 3.0, 0.004),
        plane([-0.12, 0.05, 0.95], -20, 10, 0.45, 0.40, 0.0025),
        plane([0.25, -0.12, 1.25], 25, 0, 0.30, 0.25, 0.003),
    ])


def render_scene(rig: Rig | None = None, scene: SyntheticScene | None = None, *, seed: int = 0,
                 supersample: int = 2, noise: float = 0.0, out_dir: str | os.PathLike | None = None) -> dict:
    """Render the unrectified pair of ``scene`` seen by ``rig`` and the true left depth.

    Returns ``{"left", "right"}`` uint8 (H, W) images, ``"depth"`` float32 (H, W) Z in the left
    camera frame (metres, +inf where no surface) at pixel centres, ``"scene"`` and ``"rig"``.
    With ``out_dir``, also writes ``left.png``, ``right.png`` and ``depth.npy`` there.
    """
    rig = rig or default_rig()
    scene = scene or default_scene(seed)
    rng = np.random.default_rng(seed + 7)
    images = []
    for K, D, cam in ((rig.K1, rig.D1, 1), (rig.K2, rig.D2, 2)):
        rays = _pixel_rays(K, D, rig.size, supersample)
        dirs = np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], axis=-1)
        if cam == 1:
            origin = np.zeros(3)
        else:  # X_left = Rᵀ(X_right − T)
            origin = -rig.R.T @ rig.T
            dirs = dirs @ rig.R  # row-vector form of Rᵀ·d
        value, _ = scene.shade(origin, dirs)
        images.append(_finish(_downsample(value, supersample), rng, noise))
    rays = _pixel_rays(rig.K1, rig.D1, rig.size, 1)
    dirs = np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], axis=-1)
    t, _, _, _ = scene.intersect(np.zeros(3), dirs)
    depth = t.astype(np.float32)  # dirs have z = 1, so t is Z
    result = {"left": images[0], "right": images[1], "depth": depth, "scene": scene, "rig": rig}
    if out_dir is not None:
        out = Path(out_dir)
        write_image(out / "left.png", images[0])
        write_image(out / "right.png", images[1])
        np.save(out / "depth.npy", depth)
    return result
