"""The stage catalogue: every built-in stage and the module that registers it.

Nothing is imported here: :func:`stereocli.registry.declare` records the table, and the
registry imports a module the first time one of its stages is asked for, so a run loads only
the stage modules (and their compiled kernels) its config names; listing the stages
(``stereocli stages``) imports them all. ``tests/test_config.py`` checks that the table and the
registrations agree. Add your stage here when you add one.
"""

from __future__ import annotations

from .. import registry

#: module -> {kind: stage names it registers}
CATALOGUE: dict[str, dict[str, tuple[str, ...]]] = {
    "stereocli.matching.preprocess": {"preprocess": ("none", "log", "mean_removal", "bilateral_subtraction", "xsobel",
                                                  "histogram_matching", "column_pattern", "row_align")},
    "stereocli.matching.cost": {"cost": ("ad", "tad", "sd", "sad", "stad", "ssd", "ncc", "zncc", "gradient",
                                      "color_gradient", "bt", "census", "rank", "ad_census", "ordinal")},
    "stereocli.matching.cost_mi": {"cost": ("hmi",)},
    "stereocli.matching.aggregate": {"aggregation": ("none", "box", "shiftable", "multiple_windows", "variable_window",
                                                  "cross", "adaptive_weights", "segment_support", "fast_bilateral",
                                                  "locally_consistent", "guided_filter")},
    "stereocli.matching.optimize.wta": {"optimizer": ("wta",)},
    "stereocli.matching.optimize.sgm": {"optimizer": ("sgm",)},
    "stereocli.matching.optimize.dp": {"optimizer": ("dp",)},
    "stereocli.matching.optimize.so": {"optimizer": ("so",)},
    "stereocli.matching.optimize.bp": {"optimizer": ("bp",)},
    "stereocli.matching.optimize.gc": {"optimizer": ("gc",)},
    "stereocli.matching.optimize.coop": {"optimizer": ("coop",)},
    "stereocli.matching.refine": {"refinement": ("subpixel", "lr_check", "median", "fill", "uniqueness", "confidence",
                                              "speckle", "interpolate", "bilateral", "plane_smooth")},
    "stereocli.matching.refine_segment": {"refinement": ("local_consistency", "geodesic_vote", "plane_fit")},
    "stereocli.matching.refine_local": {"refinement": ("single_matching_phase", "texture", "fill_weighted_median")},
    "stereocli.matching.refine_voting": {"refinement": ("region_voting", "proper_interpolation")},
    "stereocli.matching.refine_slanted": {"refinement": ("slanted_patchmatch",)},
    "stereocli.matching.refine_fusion": {"refinement": ("mirror_fusion",)},
    "stereocli.matching.refine_photo": {"refinement": ("photo_consistency",)},
}

for _module, _kinds in CATALOGUE.items():
    for _kind, _names in _kinds.items():
        registry.declare(_module, _kind, _names)
