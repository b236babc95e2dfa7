"""Row alignment of a pair, measured from sparse matches: is the pair rectified?

In a rectified pair a point has the same row in both views, so the vertical disparity
``y_left − y_right`` of every match is zero up to the matching noise (a few tenths of a pixel
on real rectified data). A vertical shift between the views shows as a constant offset, a
small rotation or scale difference as a vertical disparity that varies linearly across the
image. So a robust plane ``dy = a + b·x + c·y`` is fitted to the matches, and the pair counts
as misaligned when that plane departs from zero by more than ``threshold`` px at one of the
matches it holds (``max_offset``; evaluated where there are matches, never extrapolated). The
plane is found by RANSAC (the largest set of matches within :data:`INLIER_PX` of a plane through
three of them), so scattered mismatches do not tilt it.
Repeated texture (a calibration board filling the view) can still pair many points one period
apart, consistently enough to form a plane of their own; so when the matches on the rows
(|dy| ≤ :data:`INLIER_PX`) are at least half as many as those on the best plane, the plane is
fitted to them instead.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .points import PointMatches

#: Vertical disparity (px) above which a pair counts as misaligned. Rectified data stays well below:
#: MiddEval3, Middlebury 2001/2003 and this project's own rectification measure at most 1.3 px.
DEFAULT_THRESHOLD = 2.0
#: Matches needed to judge the alignment at all.
MIN_MATCHES = 12
#: Largest distance (px) of a match from the plane that still counts it as an inlier.
INLIER_PX = 1.0
#: RANSAC draws (fixed seed: the same pair always gives the same answer).
DRAWS = 200


@dataclass(frozen=True)
class RowAlignment:
    """Vertical disparity statistics of a pair's matches (px)."""

    matches: int
    on_rows: int  # matches within INLIER_PX of dy = 0
    on_plane: int  # matches within INLIER_PX of the fitted plane
    median_dy: float | None  # median of y_left − y_right
    spread_dy: float | None  # 90th percentile of |dy − median|
    max_offset: float | None  # largest |dy| of the fitted plane over the image (None: too few matches)
    threshold: float

    @property
    def measured(self) -> bool:
        return self.max_offset is not None

    @property
    def aligned(self) -> bool:
        """True unless the measurement shows rows out of line (unmeasured counts as aligned)."""
        return self.max_offset is None or self.max_offset <= self.threshold

    def describe(self) -> str:
        if not self.measured:
            return f"row alignment not measured ({self.matches} matches)"
        return (f"vertical disparity up to {self.max_offset:.1f} px (median {self.median_dy:+.2f} px, "
                f"spread {self.spread_dy:.2f} px over {self.matches} matches)")

    def as_dict(self) -> dict:
        out = asdict(self)
        out["aligned"] = self.aligned
        return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in out.items()}


def row_alignment(matches: PointMatches, *, threshold: float = DEFAULT_THRESHOLD) -> RowAlignment:
    """Measure the vertical disparity of ``matches``."""
    n = len(matches)
    if n < MIN_MATCHES:
        return RowAlignment(n, 0, 0, None, None, None, threshold)
    dy = matches.dy.astype(np.float64)
    median = _quantile(dy, 0.5)
    spread = _quantile(np.abs(dy - median), 0.9)
    points = matches.left.astype(np.float64)
    design = np.column_stack([points, np.ones(n)])
    plane = _ransac_plane(points, dy)
    on_plane = int(np.count_nonzero(np.abs(design @ plane - dy) <= INLIER_PX))
    rows = np.abs(dy) <= INLIER_PX
    on_rows = int(np.count_nonzero(rows))
    if 2 * on_rows >= on_plane and on_rows >= 3:
        plane, *_ = np.linalg.lstsq(design[rows], dy[rows], rcond=None)
        on_plane = int(np.count_nonzero(np.abs(design @ plane - dy) <= INLIER_PX))
    fitted = design @ plane
    held = np.abs(fitted - dy) <= INLIER_PX
    max_offset = float(np.max(np.abs(fitted[held]))) if held.any() else float(np.max(np.abs(fitted)))
    return RowAlignment(n, on_rows, on_plane, median, spread, max_offset, threshold)


def _quantile(values: np.ndarray, q: float) -> float:
    """``np.quantile(values, q)`` (linear interpolation) of a non-empty 1-D array. Written out
    because NumPy's median and quantiles import ``numpy.ma``, which every process would then load."""
    ordered = np.sort(values)
    position = q * (len(ordered) - 1)
    below = int(np.floor(position))
    above = min(below + 1, len(ordered) - 1)
    return float(ordered[below] + (position - below) * (ordered[above] - ordered[below]))


def _ransac_plane(points: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """``(b, c, a)`` of ``dy ≈ b·x + c·y + a``: the plane through three matches with the most
    matches within :data:`INLIER_PX`, refitted by least squares on those inliers."""
    # Normalised coordinates keep the fit well conditioned on large images.
    scale = np.array([max(1.0, np.abs(points[:, 0]).max()), max(1.0, np.abs(points[:, 1]).max()), 1.0])
    design = np.column_stack([points, np.ones(len(points))]) / scale
    rng = np.random.default_rng(0)
    samples = _distinct_triples(rng, len(dy), DRAWS)
    # Every draw's plane at once (a stack of 3x3 systems); with a degenerate draw (three
    # collinear points: no plane) among them, draw by draw, skipping those.
    try:
        coefs = np.linalg.solve(design[samples], dy[samples][..., None])[..., 0]
        usable = np.ones(len(samples), bool)
    except np.linalg.LinAlgError:
        coefs, usable = np.zeros((len(samples), 3)), np.zeros(len(samples), bool)
        for i, sample in enumerate(samples):
            try:
                coefs[i], usable[i] = np.linalg.solve(design[sample], dy[sample]), True
            except np.linalg.LinAlgError:
                pass
    counts = np.count_nonzero(np.abs(design @ coefs.T - dy[:, None]) <= INLIER_PX, axis=0)
    counts[~usable] = -1
    best = coefs[int(np.argmax(counts))] if usable.any() else np.zeros(3)  # the first of the most
    inliers = np.abs(design @ best - dy) <= INLIER_PX
    if inliers.sum() >= 3:
        best, *_ = np.linalg.lstsq(design[inliers], dy[inliers], rcond=None)
    return best / scale


def _distinct_triples(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """(count, 3) int64: ``count`` draws of three distinct indices in ``[0, n)`` (n ≥ 3), each
    triple uniform. The second index is drawn from the n − 1 others and the third from the
    n − 2 left, each shifted past the ones taken: all draws at once, not one call per draw."""
    first = rng.integers(0, n, count)
    second = rng.integers(0, n - 1, count)
    second += second >= first
    low, high = np.minimum(first, second), np.maximum(first, second)
    third = rng.integers(0, n - 2, count)
    third += third >= low
    third += third >= high
    return np.stack([first, second, third], axis=1)
