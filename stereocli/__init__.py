"""stereocli: stereo vision on image folders (calibrate, rectify, match, triangulate, eval).

In Python, the five subcommands are five functions (loaded on first use, so ``import
stereocli`` stays light)::

    import stereocli
    left = stereocli.read_image("im0.png")      # RGB
    right = stereocli.read_image("im1.png")
    result = stereocli.match(left, right)       # range estimated, as `stereocli match` does
    result.disparity                            # (H, W) float32 px, +inf invalid

:func:`calibrate`, :func:`rectify`, :func:`match`, :func:`triangulate`, :func:`evaluate` and
:func:`read_image` live in :mod:`stereocli.api`.

Conventions used everywhere in the package:

* Images are ``numpy.ndarray`` of shape ``(H, W)`` or ``(H, W, 3)`` (RGB order), float32 in
  [0, 255] inside the matching pipeline.
* Disparity is ``(H, W)`` float32 in pixels, referenced to the left image,
  ``x_right = x_left - d``; invalid / unknown pixels are ``+inf`` (never a sentinel).
* Cost volumes are ``(H, W, D)`` C-contiguous float32, ``D = ndisp``, index ``k`` is disparity
  ``min_disp + k``, lower is better; entries whose right pixel falls outside the image hold the
  cost stage's maximum cost.
"""

from __future__ import annotations

from .lazy import lazy_exports

__version__ = "0.1.0"

#: Public name -> the module that defines it (imported when the name is first used).
_LAZY = {
    "calibrate": "stereocli.api", "rectify": "stereocli.api", "match": "stereocli.api",
    "triangulate": "stereocli.api", "evaluate": "stereocli.api", "read_image": "stereocli.api",
    "MatchResult": "stereocli.api", "MatchRange": "stereocli.api", "RectifyResult": "stereocli.api",
    "TriangulationResult": "stereocli.api", "CalibrationResult": "stereocli.calib.stereo",
    "EvalReport": "stereocli.evaluation.api", "match_sequence": "stereocli.sequence",
    "SequenceMatcher": "stereocli.sequence",
}

__all__ = ["CalibrationResult", "EvalReport", "MatchRange", "MatchResult", "RectifyResult", "SequenceMatcher",
           "TriangulationResult", "__version__", "calibrate", "evaluate", "match", "match_sequence", "read_image",
           "rectify", "triangulate"]

TYPE_CHECKING = False  # (typing.TYPE_CHECKING without importing typing: type checkers read it as True)
if TYPE_CHECKING:
    from .api import (
        MatchRange,
        MatchResult,
        RectifyResult,
        TriangulationResult,
        calibrate,
        evaluate,
        match,
        read_image,
        rectify,
        triangulate,
    )
    from .calib.stereo import CalibrationResult
    from .evaluation.api import EvalReport
    from .sequence import SequenceMatcher, match_sequence


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
