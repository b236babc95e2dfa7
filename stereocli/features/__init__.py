"""What a pair's images say before dense matching: sparse point matches, how well the rows are
aligned, and the disparity range the scene spans (for pairs without a known range).

The vertical offset of the rows, which the ``row_align`` stage measures and undoes, lives with
that stage (:mod:`stereocli.matching.vertical_offset`); it is exported here too.
"""

from ..lazy import lazy_exports

#: Public name -> the module that defines it, relative to this package (imported on first use).
_EXPORTS = {
    "PointMatches": ".points", "match_points": ".points",
    "RowAlignment": ".alignment", "row_alignment": ".alignment",
    "DisparityRange": ".disparity_range", "estimate_range": ".disparity_range",
    "VerticalOffset": "..matching.vertical_offset", "track_rows": "..matching.vertical_offset",
    "fit_vertical_offset": "..matching.vertical_offset",
    "survey_pair": ".survey",
}
__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
