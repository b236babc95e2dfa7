"""Matching-cost stages: build the (H, W, D) float32 cost volume (lower is better).

Every stage sets ``state.cost`` and ``state.cost_max`` (the value held by impossible entries,
e.g. right pixel outside the image). Colour images use all channels where the method allows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..registry import param, register
from .kernels import cost as kc
from .state import MatchState


def _channels(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, C) -> (H, W, C) float32 C-contiguous."""
    image = image if image.ndim == 3 else image[..., None]
    return np.ascontiguousarray(image, dtype=np.float32)


@dataclass(frozen=True)
class ADParams:
    truncate: float = param(255.0, "truncate the absolute difference at this value (255 = no truncation)", unit="grey levels", low=1, high=255)


@register("cost", "ad", ADParams)
def ad_cost(state: MatchState, p: ADParams) -> None:
    """Absolute intensity difference, averaged over colour channels, optionally truncated.

    The simplest pixel-wise cost: fast, sensitive to gain/bias changes between the cameras.
    """
    state.cost_max = float(p.truncate)
    state.cost = kc.absdiff_volume(_channels(state.left), _channels(state.right), state.min_disp,
                                   state.ndisp, state.cost_max, float(p.truncate))


@dataclass(frozen=True)
class CensusParams:
    window: tuple[int, int] = param((7, 9), "census window (height, width), odd; at most 65 pixels", unit="px", low=1, high=15)


@register("cost", "census", CensusParams)
def census_cost(state: MatchState, p: CensusParams) -> None:
    """Hamming distance of census transforms (Zabih & Woodfill 1994) on the grey images.

    Robust to monotonic radiometric changes between the views; the default for SGM.
    """
    wh, ww = p.window
    if wh % 2 == 0 or ww % 2 == 0 or wh * ww > 65:
        from ..errors import ConfigError

        raise ConfigError(f"cost.window: {list(p.window)} must be odd sizes with at most 65 pixels (e.g. [7, 9])")
    left = kc.census_transform(np.ascontiguousarray(state.gray("left")), wh // 2, ww // 2)
    right = kc.census_transform(np.ascontiguousarray(state.gray("right")), wh // 2, ww // 2)
    state.cost_max = float(wh * ww - 1)
    state.cost = kc.hamming_volume(left, right, state.min_disp, state.ndisp, state.cost_max)
