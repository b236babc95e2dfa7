"""Preprocessing stages: filters applied to both images before the matching cost."""

from __future__ import annotations

from ..registry import register
from .state import MatchState


@register("preprocess", "none")
def no_preprocess(state: MatchState, params) -> None:
    """Leave the images unchanged."""
