"""Sparse point matches between the two views: distinctive ORB features, refined to sub-pixel.

ORB corners (Rublee et al. 2011; ``method="orb"``, the default: fast; detected at one scale, as
the two views of a stereo pair share theirs, which finds more matches in less time than a
pyramid) or SIFT blobs (Lowe 2004;
``method="sift"``: slower, more and steadier matches under rotation and scale, used to
estimate epipolar geometry) are matched by their descriptors; a match is kept when
it is mutual (each point is the other's best) and distinctive (Lowe's ratio test: clearly
better than the second best), which rejects most of what repeated texture, such as a
calibration board, offers. Each kept match is then refined by Lucas–Kanade on an 11×11 window
(OpenCV), so the positions are sub-pixel: the vertical component measures row alignment to a
tenth of a pixel. The matches need no disparity range.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from ..io.images import grey_uint8
from ..runtime import side_by_side

#: Largest descriptor distance ratio best / second best of a kept match.
RATIO = 0.8
#: A refined position may move this far (px) from the descriptor match; further means the
#: refinement slid off the feature.
MAX_REFINE_SHIFT = 2.0


@dataclass(frozen=True)
class PointMatches:
    """Matched points, ``(N, 2)`` float32 ``(x, y)`` pixels in each view."""

    left: np.ndarray
    right: np.ndarray
    features: int  # features detected in the left image

    @property
    def dx(self) -> np.ndarray:
        """Horizontal disparity ``x_left − x_right`` per match, px."""
        return self.left[:, 0] - self.right[:, 0]

    @property
    def dy(self) -> np.ndarray:
        """Vertical disparity ``y_left − y_right`` per match, px (0 for a rectified pair)."""
        return self.left[:, 1] - self.right[:, 1]

    def __len__(self) -> int:
        return len(self.left)


def _mask(valid: np.ndarray | None) -> np.ndarray | None:
    # Features only well inside the valid area: rectification borders are not scene texture.
    if valid is None:
        return None
    return cv2.erode((np.asarray(valid) > 0).astype(np.uint8) * 255, np.ones((15, 15), np.uint8))


#: Feature detectors of :func:`match_points`: (constructor, descriptor norm).
METHODS = {
    "orb": (lambda n: cv2.ORB_create(nfeatures=n, nlevels=1, fastThreshold=10), cv2.NORM_HAMMING),
    "sift": (lambda n: cv2.SIFT_create(nfeatures=n), cv2.NORM_L2),
}


def match_points(left: np.ndarray, right: np.ndarray, *, left_valid: np.ndarray | None = None,
                 right_valid: np.ndarray | None = None, max_features: int = 1000,
                 method: Literal["orb", "sift"] = "orb") -> PointMatches:
    """Mutual, distinctive, sub-pixel matches of ``left`` features in ``right``.

    ``left``, ``right``: images of the same size (any layout :func:`grey_uint8` takes);
    ``left_valid``/``right_valid``: optional (H, W) masks of the pixels that hold the scene;
    ``method``: ``orb`` or ``sift`` (see the module docstring).
    """
    if method not in METHODS:
        raise ValueError(f"unknown feature method {method!r}; valid: {', '.join(METHODS)}")
    create, norm = METHODS[method]
    a, b = grey_uint8(left), grey_uint8(right)
    # The two views' features side by side (OpenCV releases the GIL; the same either way).
    (keys_a, desc_a), (keys_b, desc_b) = side_by_side(
        lambda: create(max_features).detectAndCompute(a, _mask(left_valid)),
        lambda: create(max_features).detectAndCompute(b, _mask(right_valid)))
    empty = np.zeros((0, 2), np.float32)
    if desc_a is None or desc_b is None or len(keys_b) < 2:
        return PointMatches(empty, empty, len(keys_a))
    nearest_ab, best, second = _nearest(desc_a, desc_b, norm, second=True)
    nearest_ba, _, _ = _nearest(desc_b, desc_a, norm, second=False)
    query = np.arange(len(desc_a))
    good = (best < RATIO * second) & (nearest_ba[nearest_ab] == query)  # distinctive and mutual
    if not good.any():
        return PointMatches(empty, empty, len(keys_a))
    pa = np.array([keys_a[i].pt for i in query[good]], np.float32).reshape(-1, 1, 2)
    pb = np.array([keys_b[j].pt for j in nearest_ab[good]], np.float32).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01)
    refined, found, _ = cv2.calcOpticalFlowPyrLK(a, b, pa, pb.copy(), winSize=(11, 11), maxLevel=1,
                                                 criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    keep = (found.ravel() == 1) & (np.linalg.norm((refined - pb).reshape(-1, 2), axis=1) < MAX_REFINE_SHIFT)
    return PointMatches(pa.reshape(-1, 2)[keep], refined.reshape(-1, 2)[keep], len(keys_a))


def _nearest(queries: np.ndarray, candidates: np.ndarray, norm: int, *, second: bool
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each query descriptor's nearest candidate: ``(index, distance, second distance)``, (N,)
    arrays (the second distance only if ``second``; ``candidates`` has at least two rows).
    Binary descriptors (``NORM_HAMMING``) by a compiled kernel (popcounts of 64-bit words, no
    Python object per match as OpenCV's brute-force matcher builds); others by that matcher."""
    if norm == cv2.NORM_HAMMING:
        from ..matching.kernels.census import nearest_bit_strings

        return nearest_bit_strings(queries, candidates)
    pairs = cv2.BFMatcher(norm).knnMatch(queries, candidates, k=2 if second else 1)
    index = np.array([pair[0].trainIdx for pair in pairs], np.int64)
    best = np.array([pair[0].distance for pair in pairs], np.float64)
    runner_up = np.array([pair[1].distance for pair in pairs], np.float64) if second else best
    return index, best, runner_up
