"""The hostile corpus, second round: inputs and settings that produced a wrong or unreadable
outcome, each with its exit code and the one-line message we wrote.

Kinds: image pixels no convention fixes (NaN, float, signed, EXIF orientation), a NaN map that
must never be written, interrupts outside the batch runner (``eval``, ``calibrate``), ROS units,
values echoed whole, raw library messages that name no file, and misleading or missing notes.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from conftest import REPO, assert_clean, two_scenes
from stereocli.io.images import write_disparity_png16, write_image
from stereocli.io.pfm import encode_pfm, write_pfm

FAST = ("-c", "fast")


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    return two_scenes(tmp_path_factory.mktemp("scenes"), 128, 96)


def _tiff_pair(folder: Path, scenes: Path, dtype, nan_patch: bool = False) -> Path:
    """The ``planes`` views saved as TIFFs of ``dtype`` (a 30 x 40 NaN patch on the left)."""
    import cv2

    folder.mkdir(parents=True)
    for side, name in (("left", "im0"), ("right", "im1")):
        image = cv2.imread(str(scenes / "planes" / f"{name}.png"), cv2.IMREAD_UNCHANGED).astype(dtype)
        if nan_patch and side == "left":
            image[10:40, 10:50] = np.nan
        assert cv2.imwrite(str(folder / f"{side}.tif"), image)
    return folder


def _tiff_match(dtype, nan_patch=False):
    def build(tmp, scenes):
        pair = _tiff_pair(tmp / "in", scenes, dtype, nan_patch)
        return ["match", pair / "left.tif", pair / "right.tif", "-o", tmp / "out", "--ndisp", "32", *FAST], tmp / "out"

    return build


def _calib_line(key: str, value: str) -> Callable[[Path, Path], Path]:
    def inputs(tmp: Path, scenes: Path) -> Path:
        folder = tmp / "in" / "planes"
        folder.mkdir(parents=True)
        for name in ("im0.png", "im1.png"):
            (folder / name).write_bytes((scenes / "planes" / name).read_bytes())
        lines = [ln for ln in (scenes / "planes" / "calib.txt").read_text().splitlines()
                 if not ln.startswith(f"{key}=")]
        (folder / "calib.txt").write_text("\n".join(lines + [f"{key}={value}"]) + "\n")
        return folder

    return inputs


def _thin_pair(tmp: Path, rows: int, width: int) -> list[Path]:
    image = np.random.default_rng(0).integers(0, 256, (rows, width), dtype=np.uint8)
    write_image(tmp / "thin_l.png", image)
    write_image(tmp / "thin_r.png", np.roll(image, -3, axis=1))
    return [tmp / "thin_l.png", tmp / "thin_r.png"]


def _tiny_calibration_photos(tmp: Path) -> Path:
    for side in ("left", "right"):
        (tmp / "cal" / side).mkdir(parents=True)
        for i in range(3):
            write_image(tmp / "cal" / side / f"{i:02d}.png", np.zeros((1, 1), np.uint8))
    return tmp / "cal"


def _rig_file(tmp: Path, units: str = "m", scale: float = 1.0) -> Path:
    from stereocli.io.calib import save_calibration
    from stereocli.synth.rig import default_rig

    calib = default_rig().calibration()
    calib.T, calib.units = calib.T * scale, units
    save_calibration(tmp / "rig.yml", calib)
    return tmp / "rig.yml"


def _pfm_scale_e(tmp: Path) -> Path:
    (tmp / "e.pfm").write_bytes(b"Pf\n2 2\ne\n" + bytes(16))
    return tmp / "e.pfm"


def _kitti_with_small_obj_map(tmp: Path) -> tuple[Path, Path]:
    gt, res = tmp / "kitti", tmp / "res"
    write_disparity_png16(gt / "disp_occ_0" / "000000_10.png", np.full((4, 6), 20.0, np.float32))
    write_image(gt / "obj_map" / "000000_10.png", np.zeros((3, 6), np.uint8))
    write_disparity_png16(res / "000000_10.png", np.full((4, 6), 20.0, np.float32))
    return res, gt


def _calib_txt(tmp: Path, scenes: Path) -> Path:
    (tmp / "calib.txt").write_text((scenes / "planes" / "calib.txt").read_text())
    return tmp / "calib.txt"


def _negative_disparity(tmp: Path) -> Path:
    write_pfm(tmp / "neg.pfm", np.full((96, 128), -5.0, np.float32))
    return tmp / "neg.pfm"


def _nan_confidence(tmp: Path) -> Path:
    (tmp / "conf.pfm").write_bytes(encode_pfm(np.full((96, 128), np.nan, np.float32)))
    return tmp / "conf.pfm"


@dataclass
class Case:
    """``build(tmp, scenes) -> (argv, output folder)``; ``absent`` must not appear in stderr."""

    id: str
    kind: str
    build: Callable
    code: int
    message: str
    absent: str = ""


CASES = [
    # -- pixels no convention fixes: refused, naming the file (never NaN in disp0.pfm with exit 0)
    Case("float32-tiff-nan-patch", "image pixels", _tiff_match(np.float32, nan_patch=True), 1,
         "left.tif: float32 pixels, 1200 of them NaN or infinite; stereocli reads 8- or 16-bit unsigned images"),
    Case("float32-tiff", "image pixels", _tiff_match(np.float32), 1, "left.tif: float32 pixels; "),
    Case("int16-tiff", "image pixels", _tiff_match(np.int16), 1, "left.tif: int16 pixels; "),
    # -- values echoed whole
    Case("set-huge-string", "echoed values", lambda t, s: (["config", "show", "--set", "cost.window=" + "x" * 100_000],
                                                           t / "out"), 2, "cost.window"),
    Case("set-huge-key", "echoed values", lambda t, s: (["config", "show", "--set", "cost." + "k" * 100_000 + "=1"],
                                                        t / "out"), 2, "unknown parameter"),
    Case("set-long-list", "echoed values",
         lambda t, s: (["config", "show", "--set", "cost.window=[" + "1," * 15_000 + "1]"], t / "out"), 2,
         "expected a pair like [7, 9]"),
    Case("ndisp-huge", "echoed values", lambda t, s: (["match", s, "-o", t / "out", "--ndisp", "9" * 100_000],
                                                      t / "out"), 2, "--ndisp"),
    Case("config-name-huge", "echoed values", lambda t, s: (["config", "show", "-c", "p" * 100_000], t / "out"), 2,
         "no such config file or preset"),
    Case("calib-vmin-huge", "echoed values",
         lambda t, s: (["match", _calib_line("vmin", "v" * 100_000)(t, s), "-o", t / "out", "--viz", *FAST],
                       t / "out"), 1, "is not a number"),
    Case("scheduler-huge", "echoed values",
         lambda t, s: (["match", s, "-o", t / "out", "--scheduler", "tcp://" + "h" * 100_000 + ":8786", *FAST],
                       t / "out"), 2, "--scheduler tcp://hhh"),
    # -- raw library messages that named no file
    Case("ndisp-auto-one-row", "library messages",
         lambda t, s: (["match", *_thin_pair(t, 1, 640), "-o", t / "out", "--ndisp", "auto"], t / "out"), 1,
         "thin_l: cannot estimate the disparity range of a 640x1 px pair"),
    Case("ndisp-auto-two-rows", "library messages",
         lambda t, s: (["match", *_thin_pair(t, 2, 2000), "-o", t / "out", "--ndisp", "auto"], t / "out"), 1,
         "cannot estimate the disparity range of a 2000x2 px pair"),
    Case("calibrate-1x1-images", "library messages",
         lambda t, s: (["calibrate", _tiny_calibration_photos(t), "-o", t / "out" / "rig.yml", "--pattern", "9x6"],
                       t / "out"), 1, "00.png: 1x1 px is too small for a 9x6 target"),
    Case("rectify-size-huge", "library messages",
         lambda t, s: (["rectify", s / "planes" / "im0.png", s / "planes" / "im1.png", "--calib", _rig_file(t),
                        "-o", t / "out", "--size", "100000x100000"], t / "out"), 2,
         "--size 100000x100000: rectification handles at most 32766 px a side"),
    Case("pfm-scale-e", "library messages",
         lambda t, s: (["eval", _pfm_scale_e(t), s / "planes"], t / "out"), 1,
         "e.pfm: not a PFM file (scale 'e' is no number)"),
    Case("kitti-obj-map-size", "library messages",
         lambda t, s: (["eval", *_kitti_with_small_obj_map(t)], t / "out"), 1,
         "obj_map/000000_10.png: 6x3 but the GT is 6x4"),
    # -- misleading or missing messages
    Case("triangulate-no-depth-without-limits", "misleading messages",
         lambda t, s: (["triangulate", _negative_disparity(t), "--calib", _calib_txt(t, s), "-o", t / "out" / "c.ply"],
                       t / "out"), 1, "neg.pfm: no valid depth: every disparity d has d + doffs <= 0", "--min-depth"),
    Case("triangulate-nan-confidence", "misleading messages",
         lambda t, s: (["triangulate", s / "planes" / "disp0GT.pfm", "--calib", _calib_txt(t, s), "--confidence",
                        _nan_confidence(t), "-o", t / "out" / "c.ply"], t / "out"), 1,
         "conf.pfm: confidence contains NaN", "disparity contains NaN"),
    Case("min-disp-outside-the-image", "misleading messages",
         lambda t, s: (["match", s / "planes", "-o", t / "out", "--min-disp", "200", "--ndisp", "16", *FAST],
                       t / "out"), 1,
         "planes: the disparity range 200..215 px lies outside the 128 px wide image"),
    Case("min-disp-far-left", "misleading messages",
         lambda t, s: (["match", s / "planes", "-o", t / "out", "--min-disp", "-400", "--ndisp", "16", *FAST],
                       t / "out"), 1, "the disparity range -400..-385 px lies outside"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_hostile_message(case: Case, run_cli, tmp_path, scenes):
    argv, out = case.build(tmp_path, scenes)
    r = run_cli(*argv)
    assert r.code == case.code, r.err
    assert case.message in (r.out + r.err if argv[0] == "eval" else r.err), r.err  # eval reports scenes on stdout
    assert not case.absent or case.absent not in r.err, r.err
    assert "Traceback" not in r.err and "OpenCV(" not in r.err
    errors = [line for line in r.err.splitlines() if line.startswith("Error")]
    assert errors and all(len(e) < 400 for e in errors), r.err
    assert len(r.err) < 2000, r.err[:2000]  # nothing echoed whole, nothing echoed twice
    if argv[0] in ("match", "rectify", "triangulate"):
        assert_clean(out)
        assert not list(out.rglob("*.pfm"))


# -- a NaN map is never written ------------------------------------------------------------------

def test_a_stage_producing_nan_fails_the_pair_and_writes_nothing(run_cli, tmp_path, scenes, monkeypatch):
    import stereocli.matching.pipeline as pipeline

    real = pipeline.match_pair

    def nan_match(*args, **kwargs):
        result = real(*args, **kwargs)
        if result.disparity.shape[0] > 90:  # the real pair, not the warm-up's
            result.disparity[:2, :3] = np.nan
        return result

    monkeypatch.setattr(pipeline, "match_pair", nan_match)
    r = run_cli("match", scenes / "planes", "-o", tmp_path / "out", *FAST)
    assert r.code == 1, r.err
    assert f"Error: planes: {tmp_path / 'out' / 'planes' / 'disp0.pfm'}: 6 NaN values; not written" in r.err
    assert_clean(tmp_path / "out")


def test_a_float_image_with_nan_is_refused_by_the_library():
    from stereocli.errors import DataError
    from stereocli.matching.config import build_config
    from stereocli.matching.pipeline import match_pair

    left = np.random.default_rng(0).uniform(0, 255, (40, 60)).astype(np.float32)
    right = left.copy()
    right[5, 7], right[6, 7] = np.nan, np.inf
    with pytest.raises(DataError, match="2 NaN or infinite values"):
        match_pair(left, right, build_config(["fast"]), ndisp=8)


def test_writers_refuse_nan(tmp_path):
    from stereocli.errors import DataError
    from stereocli.io.images import write_disparity

    nan = np.zeros((3, 4), np.float32)
    nan[1, 1] = np.nan
    for name in ("d.pfm", "d.npy"):
        with pytest.raises(DataError, match="1 NaN values; not written"):
            write_disparity(tmp_path / name, nan)
    assert not list(tmp_path.iterdir())


# -- EXIF orientation: applied as viewers apply it, in every read, and named --------------------

def _oriented(path: Path, pixels: np.ndarray, orientation: int) -> Path:
    from PIL import Image

    image = Image.fromarray(pixels)
    if path.suffix == ".tif":
        image.save(path, tiffinfo={274: orientation})
    else:
        exif = Image.Exif()
        exif[274] = orientation
        image.save(path, exif=exif.tobytes(), quality=100)
    return path


@pytest.mark.parametrize("suffix", [".jpg", ".tif"])
@pytest.mark.parametrize("orientation,turn", [(3, 2), (6, -1), (8, 1)])
def test_exif_orientation_is_applied_by_every_read(tmp_path, suffix, orientation, turn):
    from stereocli.io.exif import exif_orientation, orientation_note
    from stereocli.io.images import read_image

    pixels = np.zeros((40, 80, 3), np.uint8)
    pixels[:, :10] = 255  # a bright band on the stored image's left
    path = _oriented(tmp_path / f"o{suffix}", pixels, orientation)
    upright = np.rot90(pixels, k=turn)  # what a viewer shows (k=-1: 90 degrees clockwise)
    assert exif_orientation(path) == orientation
    colour, grey = read_image(path), read_image(path, gray=True)
    assert colour.shape == upright.shape and grey.shape == upright.shape[:2]
    assert np.abs(colour.astype(int) - upright).max() <= 8  # JPEG's loss at the band's edge
    assert np.abs(grey.astype(int) - upright[..., 0]).max() <= 8
    assert orientation_note(path).startswith(f"{path}: EXIF orientation {orientation}: read turned")


def test_no_orientation_no_note(tmp_path, scenes):
    from stereocli.io.exif import exif_orientation, orientation_note

    upright = _oriented(tmp_path / "o1.jpg", np.zeros((8, 8, 3), np.uint8), 1)
    assert exif_orientation(upright) == 1 and orientation_note(upright) is None
    assert exif_orientation(scenes / "planes" / "im0.png") is None
    (tmp_path / "bad.jpg").write_bytes(b"\xff\xd8\xff\xe1\x00\x10Exif\x00\x00MM\x00*\xff\xff\xff\xff")
    assert exif_orientation(tmp_path / "bad.jpg") is None  # a broken directory is no orientation


def test_match_warns_naming_each_turned_view(run_cli, tmp_path, scenes):
    from stereocli.io.images import read_image

    folder = tmp_path / "in"
    folder.mkdir()
    for side, name in (("a", "im0"), ("b", "im1")):
        stored = np.rot90(read_image(scenes / "planes" / f"{name}.png"), k=1)  # a camera held on its side
        _oriented(folder / f"cam_{side}.jpg", np.ascontiguousarray(stored), 6)
    r = run_cli("match", folder / "cam_a.jpg", folder / "cam_b.jpg", "-o", tmp_path / "out", "--ndisp", "48", *FAST)
    assert r.code == 0, r.err
    for side in ("a", "b"):
        assert f"Warning: cam_a: {folder}/cam_{side}.jpg: EXIF orientation 6: read turned 90° clockwise" in r.err
    params = json.loads((tmp_path / "out" / "cam_a" / "params.json").read_text())
    assert (params["width"], params["height"]) == (128, 96)  # matched upright, as the scene was rendered


# -- interrupts outside the batch runner ----------------------------------------------------------

SIGNAL_HOOK = """
import multiprocessing, os, signal
where, sig = os.environ.get("SIGNAL_IN"), getattr(signal, os.environ.get("SIGNAL_NAME", "SIGINT"))
def _signal():  # from a pool worker to its parent, else to this process
    os.kill(os.getppid() if multiprocessing.parent_process() else os.getpid(), sig)
def _wrap(module, name):
    real = getattr(module, name)
    def wrapper(*args, **kwargs):
        _signal()
        return real(*args, **kwargs)
    setattr(module, name, wrapper)
if where == "eval":
    import stereocli.jobs.evaluate
    _wrap(stereocli.jobs.evaluate, "score_scene")
elif where == "calibrate":
    import stereocli.calib.detect
    _wrap(stereocli.calib.detect, "_detect_one")
"""


@pytest.fixture(scope="module")
def matched(scenes, tmp_path_factory) -> Path:
    res = tmp_path_factory.mktemp("res")
    r = subprocess.run([sys.executable, "-m", "stereocli", "match", scenes, "-o", res, *FAST, "-q"],
                       env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return res


@pytest.mark.parametrize("command,jobs,sig", [
    pytest.param(command, jobs, sig, id=f"{command}-j{jobs}-{sig.name}") for command, jobs, sig in (
        ("eval", "1", signal.SIGINT), ("eval", "1", signal.SIGTERM), ("eval", "2", signal.SIGINT),
        ("eval", "2", signal.SIGTERM), ("calibrate", "1", signal.SIGINT), ("calibrate", "1", signal.SIGTERM))])
def test_eval_and_calibrate_exit_130_or_143_on_interrupt(tmp_path, scenes, matched, command, jobs, sig):
    """The signal arrives while the first scene is scored (in the worker with ``-j 2``) or the
    first image is searched for the target."""
    (tmp_path / "hook").mkdir()
    (tmp_path / "hook" / "sitecustomize.py").write_text(SIGNAL_HOOK)
    if command == "eval":
        argv = ["eval", matched, scenes, "-j", jobs]
    else:
        cal = tmp_path / "cal"
        for side in ("left", "right"):
            (cal / side).mkdir(parents=True)
            for i in range(3):
                write_image(cal / side / f"{i:02d}.png", np.full((60, 80), 128, np.uint8))
        argv = ["calibrate", cal, "-o", tmp_path / "out" / "rig.yml", "--pattern", "9x6", "-j", jobs]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "hook"), str(REPO)]), "SIGNAL_IN": command,
           "SIGNAL_NAME": sig.name}
    r = subprocess.run([sys.executable, "-m", "stereocli", *map(str, argv)], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 128 + sig, r.stderr
    assert f"Interrupted ({sig.name})" in r.stderr and "Aborted" not in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


# -- ROS files carry metres ------------------------------------------------------------------------

def test_ros_export_converts_millimetres_to_metres_and_reads_back_metres(tmp_path):
    from stereocli.io.calib import load_calibration, save_calibration, to_middlebury
    from stereocli.rectification import rectified_calibration

    mm = rectified_calibration(load_calibration(_rig_file(tmp_path, "mm", 1000.0)))
    assert mm.baseline == pytest.approx(120.0, rel=0.01)  # the synthetic rig: 0.12 m
    _, right = save_calibration(tmp_path / "ros.yaml", mm, "ros")
    tx = json.loads(right.read_text().split("projection_matrix:")[1].split("data:")[1].split("\n")[0])[3]
    assert tx == pytest.approx(mm.P2[0, 3] / 1000, rel=1e-12)  # -fx' * B with B in metres
    back = load_calibration(right)
    assert back.units == "m" and back.baseline == pytest.approx(mm.baseline / 1000, rel=1e-9)
    np.testing.assert_allclose(back.T, mm.T / 1000, rtol=1e-9, atol=1e-15)
    assert to_middlebury(back).baseline == pytest.approx(to_middlebury(mm).baseline, rel=1e-9)  # both mm


def test_ros_export_refuses_an_unknown_unit(run_cli, tmp_path):
    r = run_cli("convert-calib", _rig_file(tmp_path, "unit"), tmp_path / "ros", "--to", "ros")
    assert r.code == 1 and "ROS camera_info is in metres, but the calibration's unit is 'unit'" in r.err, r.err
    assert not list(tmp_path.glob("ros*"))
    photos = _tiny_calibration_photos(tmp_path)
    r = run_cli("calibrate", photos, "-o", tmp_path / "out" / "rig", "--to", "ros", "--pattern", "9x6")
    assert r.code == 2 and "--to ros: ROS camera_info is in metres; give --square a length unit" in r.err, r.err
    assert not (tmp_path / "out").exists()  # refused before any detection (no cache either)


# -- YAML nesting in our words, with or without libyaml --------------------------------------------

@pytest.mark.parametrize("libyaml", [True, False], ids=["libyaml", "pure-python"])
def test_deep_nesting_is_reported_in_our_words_by_any_yaml_parser(run_cli, tmp_path, monkeypatch, libyaml):
    import yaml

    if not libyaml:  # the pure-Python parser, as PyYAML without its C extension (and older ones) runs
        monkeypatch.delattr(yaml, "CSafeLoader", raising=False)
    (tmp_path / "deep.yaml").write_text("cost: " + "[" * 100_000 + "]" * 100_000)
    for argv in (["-c", tmp_path / "deep.yaml"], ["--set", "cost.window=" + "{" * 50],
                 ["--set", "cost.window=" + "[" * 100_000]):
        r = run_cli("config", "show", *argv)
        assert r.code == 2 and "line 1: nested deeper than 32 levels; not a config" in r.err, r.err[:500]
        assert len(r.err) < 400
    # Brackets in comments and quoted strings are no nesting: this file is read, its key refused.
    (tmp_path / "quoted.yaml").write_text("cost: {name: census}  # " + "[" * 40 + "\n"
                                          "runtime: {note: '" + "[" * 40 + "'}\n")
    r = run_cli("config", "show", "-c", tmp_path / "quoted.yaml")
    assert r.code == 2 and "runtime.note: unknown parameter" in r.err, r.err


# -- notes and warnings that were missing ----------------------------------------------------------

def test_calib_txt_with_ndisp_zero_says_the_range_is_estimated(run_cli, tmp_path, scenes):
    folder = _calib_line("ndisp", "0")(tmp_path, scenes)
    r = run_cli("match", folder, "-o", tmp_path / "out", *FAST)
    assert r.code == 0, r.err
    assert f"Warning: planes: {folder / 'calib.txt'}: ndisp=0 gives no range; the range is estimated" in r.err
    params = json.loads((tmp_path / "out" / "planes" / "params.json").read_text())
    assert params["range"]["source"] == "estimated" and params["ndisp"] > 0


@pytest.mark.slow
def test_an_unwritable_detection_cache_is_a_warning(run_cli, tmp_path):
    from stereocli.synth.rig import render_rig

    render_rig(tmp_path / "rig", n_pairs=6, seed=0)
    (tmp_path / "file").write_text("not a folder")
    cache = tmp_path / "file" / "cache.json"
    r = run_cli("calibrate", tmp_path / "rig", "-o", tmp_path / "out" / "rig.yml", "--pattern", "9x6", "--square",
                "40mm", "--cache", cache)
    assert r.code == 0, r.err
    warnings = [line for line in r.err.splitlines() if "detection cache not written" in line]
    assert len(warnings) == 1 and warnings[0].startswith(f"Warning: {cache}: ")
    report = json.loads((tmp_path / "out" / "rig.report.json").read_text())
    assert any("detection cache not written" in w for w in report["warnings"])
    assert (tmp_path / "out" / "rig.yml").is_file() and not cache.exists()
