"""What a pair's images say before dense matching: sparse point matches, how well the rows are
aligned, and the disparity range the scene spans (for pairs without a known range).

The vertical offset of the rows, which the ``row_align`` stage measures and undoes, lives with
that stage (:mod:`stereocli.matching.vertical_offset`); it is exported here too.
"""

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


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
