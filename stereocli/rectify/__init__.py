"""Rectification: maps from a calibration, rectified pairs, valid masks, calib.txt, check images."""

from .maps import RectifyMaps, Rectification, build_maps, rectify_images, stereo_rectify

__all__ = ["RectifyMaps", "Rectification", "build_maps", "rectify_images", "stereo_rectify"]
