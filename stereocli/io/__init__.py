"""File formats: images, PFM, 16-bit PNG, Middlebury calib.txt, atomic writes, input pairing."""

#: Public name -> the submodule that defines it (imported on first use).
_EXPORTS = {
    "read_image": "images", "write_image": "images", "read_disparity": "images", "write_disparity": "images",
    "to_float_image": "images",
    "read_pfm": "pfm", "write_pfm": "pfm",
    "write_ply": "ply",
    "StereoCalibration": "calib", "load_calibration": "calib", "save_calibration": "calib",
    "to_middlebury": "calib", "from_middlebury": "calib",
    "MiddleburyCalib": "middlebury", "read_calib_txt": "middlebury", "write_calib_txt": "middlebury",
    "StereoInput": "pairs", "discover_pairs": "pairs", "find_calibration_pairs": "pairs",
    "atomic_path": "atomic", "write_bytes": "atomic", "write_text": "atomic",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
