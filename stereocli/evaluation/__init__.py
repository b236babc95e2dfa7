"""Benchmark-faithful scoring of disparity maps (MiddEval3, Middlebury 2001/2003, KITTI 2015).

Library entry points (no Click here)::

    from stereocli.evaluation import evaluate_folder, evaluate_pair, format_table
    report = evaluate_folder("out", "../shared/data/middlebury2014/trainingQ")
    print(format_table(report, "markdown"))
    report.average["nonocc"]["bad2.0"]
"""

from .api import (
    EvalOptions,
    EvalReport,
    SceneResult,
    evaluate,
    evaluate_folder,
    evaluate_pair,
    rules_text,
    weighted_average,
)
from .datasets import DATASETS, Scene, load_scene
from .metrics import (
    DEFAULT_QUANTILES,
    DEFAULT_THRESHOLDS,
    derive_nonocc_mask,
    kitti_interpolate_background,
    kitti_stats,
    middlebury_stats,
    threshold_key,
)
from .report import FORMATS, format_table

__all__ = [
    "DATASETS", "DEFAULT_QUANTILES", "DEFAULT_THRESHOLDS", "EvalOptions", "EvalReport", "FORMATS", "Scene",
    "SceneResult", "derive_nonocc_mask", "evaluate", "evaluate_folder", "evaluate_pair", "format_table",
    "kitti_interpolate_background", "kitti_stats", "load_scene", "middlebury_stats", "rules_text",
    "threshold_key", "weighted_average",
]
