"""Rectification: maps from a calibration, rectified pairs, valid masks, calib.txt, check images."""

from .maps import RectifyMaps, Rectification, build_maps, rectified_calibration, rectify_images, stereo_rectify

__all__ = ["RectifyMaps", "Rectification", "build_maps", "rectified_calibration", "rectify_images",
           "stereo_rectify"]
