"""File formats: images, PFM, 16-bit PNG, Middlebury calib.txt, atomic writes, input pairing."""

from ..lazy import lazy_exports

#: Public name -> the submodule that defines it (imported on first use).
_EXPORTS = {
    "read_image": ".images", "write_image": ".images", "read_disparity": ".images", "write_disparity": ".images",
    "to_float_image": ".images",
    "read_pfm": ".pfm", "write_pfm": ".pfm",
    "write_ply": ".ply",
    "StereoCalibration": ".calib", "load_calibration": ".calib", "save_calibration": ".calib",
    "to_middlebury": ".calib", "from_middlebury": ".calib",
    "MiddleburyCalib": ".middlebury", "read_calib_txt": ".middlebury", "write_calib_txt": ".middlebury",
    "StereoInput": ".pairs", "discover_pairs": ".pairs", "find_calibration_pairs": ".pairs",
    "atomic_path": ".atomic", "write_bytes": ".atomic", "write_text": ".atomic",
}
__all__ = sorted(_EXPORTS)


__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
