"""Rectification: maps from a calibration, rectified pairs, valid masks, calib.txt, check images.

Without a calibration, homographies are estimated from the pairs themselves.
"""

from .maps import Rectification, RectifyMaps, build_maps, rectified_calibration, rectify_images, stereo_rectify
from .uncalibrated import UncalibratedRectification, disparity_to_original, estimate_rectification, warp_pair

__all__ = ["RectifyMaps", "Rectification", "UncalibratedRectification", "build_maps", "disparity_to_original",
           "estimate_rectification", "rectified_calibration", "rectify_images", "stereo_rectify", "warp_pair"]
