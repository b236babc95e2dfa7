"""The public functions (``stereocli.match`` and its siblings): the command line's numbers bit for
bit, settings that stay with their call, the documentation a user reads (docstrings, doctests,
the README's Python blocks, docs/api.md)."""

from __future__ import annotations

import doctest
import importlib
import inspect
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import stereocli
from conftest import REPO, SAMPLES
from stereocli import api
from stereocli.errors import ConfigError, DataError
from stereocli.io.images import write_image
from stereocli.io.pfm import read_pfm, write_pfm
from stereocli.matching.config import build_config

PUBLIC_FUNCTIONS = ["calibrate", "rectify", "match", "triangulate", "evaluate", "read_image"]
PLANES = SAMPLES / "scenes" / "planes"
CURVED = SAMPLES / "scenes" / "curved"


def _loose_pair(folder: Path, scene: Path = PLANES) -> tuple[Path, Path]:
    """The scene's two views alone in ``folder`` (no calib.txt beside them: the command line
    then estimates the range, as the function does without ``ndisp``)."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(scene / "im0.png", folder / "left.png")
    shutil.copy(scene / "im1.png", folder / "right.png")
    return folder / "left.png", folder / "right.png"


@pytest.mark.parametrize("kwargs, argv", [
    ({}, []),
    ({"ndisp": 64}, ["--ndisp", "64"]),
    ({"ndisp": 48, "min_disp": -4, "preset": "fast", "set": {"optimizer.p2": 1.2, "cost.window": [5, 5]}},
     ["--ndisp", "48", "--min-disp", "-4", "-c", "fast", "--set", "optimizer.p2=1.2", "--set", "cost.window=[5,5]"]),
], ids=["estimated", "ndisp", "fast-set"])
def test_match_on_rgb_arrays_equals_the_command_line_bit_for_bit(tmp_path, run_cli, kwargs, argv):
    left, right = _loose_pair(tmp_path / "pair")
    result = stereocli.match(stereocli.read_image(left), stereocli.read_image(right), **kwargs)
    r = run_cli("match", left, right, "-o", tmp_path / "out", *argv)
    assert r.code == 0, r.err
    cli = read_pfm(tmp_path / "out" / "pair" / "disp0.pfm")
    assert cli.dtype == result.disparity.dtype == np.float32
    np.testing.assert_array_equal(result.disparity, cli)
    assert np.isfinite(cli).mean() > 0.9
    expected_source = "estimated" if "ndisp" not in kwargs else "given"
    assert result.range.source == expected_source
    if "ndisp" in kwargs:
        assert (result.range.min_disp, result.range.ndisp) == (kwargs.get("min_disp", 0), kwargs["ndisp"])


def test_the_estimated_range_and_its_evidence_are_the_command_lines(tmp_path, run_cli):
    import json

    left, right = _loose_pair(tmp_path / "pair")
    result = stereocli.match(stereocli.read_image(left), stereocli.read_image(right))
    assert run_cli("match", left, right, "-o", tmp_path / "out").code == 0
    recorded = json.loads((tmp_path / "out" / "pair" / "params.json").read_text())
    assert recorded["range"] == result.range.as_dict()
    assert recorded["alignment"] == result.alignment and recorded["warnings"] == result.warnings
    assert result.range.evidence["sparse_matches"] > 30


def test_a_calib_txt_gives_the_range():
    left, right = stereocli.read_image(PLANES / "im0.png"), stereocli.read_image(PLANES / "im1.png")
    result = stereocli.match(left, right, calib=PLANES / "calib.txt", preset="realtime")
    assert (result.range.min_disp, result.range.ndisp, result.range.source) == (0, 48, "calib.txt")
    assert result.confidence is None and result.disparity_right is None


def test_confidence_from_a_pipeline_without_it_fails_before_any_work(monkeypatch):
    # The config's traits answer (nothing is matched, nor the range estimated).
    import stereocli.features.survey as survey

    monkeypatch.setattr(survey, "survey_pair", lambda *a, **k: pytest.fail("the pair was surveyed"))
    left = stereocli.read_image(PLANES / "im0.png")
    with pytest.raises(ConfigError, match=r"^p: confidence: the configured pipeline produces no confidence map "
                                          r"\(refinement: subpixel, lr_check, fill, median, plane_smooth\)"):
        stereocli.match(left, left, preset="fast", confidence=True, name="p")


def _sequential_and_concurrent(pairs: list, settings: list[dict]) -> tuple[list, list]:
    sequential = [stereocli.match(*pair, ndisp=48, **kw).disparity for pair, kw in zip(pairs, settings)]
    barrier = threading.Barrier(len(pairs))
    concurrent: list = [None] * len(pairs)
    errors: list = []

    def run(i: int) -> None:
        try:
            barrier.wait()
            for _ in range(2):  # overlapping calls, several times
                concurrent[i] = stereocli.match(*pairs[i], ndisp=48, **settings[i]).disparity
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(pairs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    return sequential, concurrent


def test_two_threads_matching_at_once_with_different_settings_give_the_sequential_maps():
    from stereocli.runtime import get_threads

    pairs = [(stereocli.read_image(s / "im0.png"), stereocli.read_image(s / "im1.png")) for s in (PLANES, CURVED)]
    settings = [{"threads": 1}, {"threads": 2, "set": {"optimizer.p2": 1.2}}]
    before = get_threads()
    sequential, concurrent = _sequential_and_concurrent(pairs, settings)
    for seq, con in zip(sequential, concurrent):
        np.testing.assert_array_equal(con, seq)
    assert not np.array_equal(sequential[0], stereocli.match(*pairs[0], ndisp=48, set={"optimizer.p2": 1.2}).disparity)
    assert get_threads() == before  # the calls left this thread's setting as it was


def test_a_thread_count_set_in_one_thread_stays_in_that_thread():
    from stereocli import runtime

    seen = {}

    def other() -> None:
        runtime.set_threads(1)
        seen["other"] = runtime.kernel_threads()

    runtime.set_threads(0)
    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert seen["other"] == 1 and runtime.get_threads() == 0
    with runtime.threads_for_call(1):
        assert runtime.kernel_threads() == 1
    assert runtime.get_threads() == 0


def test_the_config_being_matched_is_each_threads_own():
    from stereocli.matching import pipeline

    fast, default = build_config(["fast"]), build_config()
    left, right = stereocli.read_image(PLANES / "im0.png"), stereocli.read_image(PLANES / "im1.png")
    seen = []
    prepared = pipeline.prepare(left, right, fast, ndisp=32)  # this thread is matching with fast...
    try:
        t = threading.Thread(target=lambda: seen.append(pipeline.current_config() is fast
                                                        and stereocli.match(left, right, ndisp=32, config=default)))
        t.start()
        t.join()
        assert pipeline.current_config() is fast  # ...and another thread's whole match left it so
    finally:
        pipeline.finish(prepared, pipeline.run_strips(prepared, fast), fast)
    assert seen[0] is not False and pipeline.current_config() is None


@pytest.mark.parametrize("config", ["fast", SAMPLES.parent / "configs" / "fast.yaml", "mapping", "object"])
def test_config_takes_a_preset_a_file_a_mapping_or_a_config_object(config):
    import yaml

    expected = build_config(["fast"], ["optimizer.p2=1.2"]).as_dict()
    if config == "mapping":
        config = yaml.safe_load((REPO / "configs" / "fast.yaml").read_text())
    elif config == "object":
        config = build_config(["fast"])
    assert api.match_config(config=config, set={"optimizer.p2": 1.2}).as_dict() == expected
    assert api.match_config(config=config, set="optimizer.p2=1.2").as_dict() == expected
    assert api.match_config(config=config, set=["optimizer.p2=1.2"]).as_dict() == expected


def test_a_config_object_is_used_as_it_is_and_threads_apply_to_the_call_only():
    config = build_config(["fast"])
    assert api.match_config(config=config) is config
    assert api.match_config(config=config, threads=1).runtime.threads == 1
    assert config.runtime.threads == 0


@pytest.mark.parametrize("kwargs, message", [
    ({"set": {"optimizer.p3": 1}}, "set optimizer.p3=1: optimizer.p3: unknown parameter"),
    ({"set": {"optimizer": 1}}, "set optimizer=1: expected a stage"),
    ({"set": {"p2": 1}}, "set p2=1: expected section.key"),
    ({"preset": "fastest"}, "fastest: no such config file or preset"),
    ({"threads": -1}, "threads must be a whole number >= 0"),
    ({"min_disp": 3}, "min_disp needs ndisp"),
    ({"ndisp": 0}, "ndisp must be a whole number >= 1"),
    ({"preset": "fast", "config": "object"}, "give one or the other"),
])
def test_bad_options_raise_a_config_error_naming_them(kwargs, message):
    if kwargs.get("config") == "object":
        kwargs["config"] = build_config()
    image = np.zeros((32, 48), np.uint8)
    with pytest.raises(ConfigError, match=re.escape(message)):
        stereocli.match(image, image, **kwargs)


@pytest.mark.parametrize("left, right, message", [
    (np.zeros((32, 48), np.uint8), np.zeros((32, 40), np.uint8), "left 48x32 and right 40x32 differ in size"),
    (np.zeros((32, 48), np.int32), np.zeros((32, 48), np.int32), "left image is int32"),
    (np.zeros((32, 48, 2), np.uint8), np.zeros((32, 48, 2), np.uint8), "left image has shape (32, 48, 2)"),
    (np.full((32, 48), np.nan, np.float32), np.zeros((32, 48), np.float32), "left image holds NaN"),
])
def test_unusable_images_raise_a_data_error(left, right, message):
    with pytest.raises(DataError, match=re.escape(message)):
        stereocli.match(left, right, ndisp=16, name="pair")


def test_grey_uint16_and_float_views_are_matched_as_the_command_line_reads_them(tmp_path, run_cli):
    rgb = [stereocli.read_image(PLANES / f"im{i}.png") for i in (0, 1)]
    grey = [(np.asarray(v, np.float32) @ np.float32([0.299, 0.587, 0.114])).round().astype(np.uint8) for v in rgb]
    as_uint16 = [v.astype(np.uint16) * 257 for v in grey]
    for i, view in enumerate(as_uint16):
        write_image(tmp_path / f"v{i}.png", view)
    r = run_cli("match", tmp_path / "v0.png", tmp_path / "v1.png", "-o", tmp_path / "out", "--ndisp", "48")
    assert r.code == 0, r.err
    cli = read_pfm(tmp_path / "out" / "v0" / "disp0.pfm")
    np.testing.assert_array_equal(stereocli.match(*as_uint16, ndisp=48).disparity, cli)
    # 16-bit views are scaled to [0, 255]: the same map as the 8-bit views, and as float views in [0, 255].
    np.testing.assert_array_equal(stereocli.match(*grey, ndisp=48).disparity, cli)
    np.testing.assert_array_equal(stereocli.match(*[v.astype(np.float32) for v in grey], ndisp=48).disparity, cli)


def test_channel_order_is_rgb_and_bgr_input_gives_another_map(tmp_path):
    image = np.zeros((4, 6, 3), np.uint8)
    image[..., 0] = 200  # red
    write_image(tmp_path / "red.png", image)  # written from RGB
    assert stereocli.read_image(tmp_path / "red.png")[0, 0].tolist() == [200, 0, 0]
    left, right = stereocli.read_image(PLANES / "im0.png"), stereocli.read_image(PLANES / "im1.png")
    rgb = stereocli.match(left, right, ndisp=48, preset="quality").disparity
    bgr = stereocli.match(left[..., ::-1], right[..., ::-1], ndisp=48, preset="quality").disparity
    assert not np.array_equal(rgb, bgr)  # colour-weighted stages see the channels
    for name in ("match", "rectify", "triangulate", "read_image"):
        assert "RGB" in inspect.getdoc(getattr(stereocli, name))


def test_triangulate_equals_the_command_lines_depth(tmp_path, run_cli):
    disparity = read_pfm(PLANES / "disp0GT.pfm")
    disparity[:3] = np.inf
    write_pfm(tmp_path / "disp0.pfm", disparity)
    r = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", PLANES / "calib.txt", "--image", PLANES / "im0.png",
                "-o", tmp_path / "cloud.ply", "--depth-format", "pfm", "--units", "m")
    assert r.code == 0, r.err
    result = stereocli.triangulate(disparity, PLANES / "calib.txt", image=stereocli.read_image(PLANES / "im0.png"),
                                   units="m")
    np.testing.assert_array_equal(result.depth, read_pfm(tmp_path / "cloud_depth.pfm"))
    assert result.units == "m" and np.isinf(result.depth[:3]).all()
    assert result.points.shape == (int(np.isfinite(result.depth).sum()), 3) and result.colors.dtype == np.uint8
    from plyfile import PlyData

    vertices = PlyData.read(str(tmp_path / "cloud.ply"))["vertex"]
    np.testing.assert_array_equal(np.stack([vertices["x"], vertices["y"], vertices["z"]], axis=1), result.points)
    np.testing.assert_array_equal(np.stack([vertices["red"], vertices["green"], vertices["blue"]], axis=1),
                                  result.colors)


def test_triangulate_refuses_what_the_command_line_refuses():
    calib = PLANES / "calib.txt"
    with pytest.raises(DataError, match="every disparity is invalid"):
        stereocli.triangulate(np.full((240, 320), np.inf, np.float32), calib)
    with pytest.raises(DataError, match=re.escape("disparity is 100x50 but")):
        stereocli.triangulate(np.ones((50, 100), np.float32), calib)
    with pytest.raises(DataError, match="no point left"):
        stereocli.triangulate(np.ones((240, 320), np.float32), calib, max_depth=1.0)


def test_evaluate_equals_the_command_lines_report(tmp_path, run_cli):
    estimate = read_pfm(PLANES / "disp0GT.pfm") + np.float32(0.75)
    estimate[:20, :30] = np.inf
    (tmp_path / "planes").mkdir()
    write_pfm(tmp_path / "planes" / "disp0.pfm", estimate)
    r = run_cli("eval", tmp_path / "planes" / "disp0.pfm", PLANES, "--format", "json")
    assert r.code == 0, r.err
    report = stereocli.evaluate(estimate, PLANES)
    assert report.to_dict() == r.json()
    bad = report.scenes[0].metrics["nonocc"]
    assert bad["bad2.0"] == r.json()["scenes"][0]["nonocc"]["bad2.0"] and 0 < bad["bad0.5"] <= 100
    assert stereocli.evaluate(tmp_path / "planes" / "disp0.pfm", PLANES).to_dict() == r.json()


def test_format_table_takes_a_report_or_one_scenes_result():
    from stereocli.evaluation import evaluate_pair, format_table

    estimate = read_pfm(PLANES / "disp0GT.pfm")
    text = format_table(evaluate_pair(estimate, PLANES), "text")
    assert text == format_table(stereocli.evaluate(estimate, PLANES), "text")
    assert "planes" in text and "bad2.0" in text
    assert format_table(evaluate_pair(estimate, PLANES), "markdown").startswith("> MiddEval3 rules")


def test_evaluate_picks_a_named_scene_from_a_folder_of_scenes():
    estimate = read_pfm(CURVED / "disp0GT.pfm")
    report = stereocli.evaluate(estimate, SAMPLES / "scenes", name="curved")
    assert report.scenes[0].name == "curved" and report.scenes[0].metrics["nonocc"]["bad0.5"] == 0.0
    with pytest.raises(DataError, match="name the one to score"):
        stereocli.evaluate(estimate, SAMPLES / "scenes")


def test_rectify_equals_the_command_line(tmp_path, run_cli):
    from stereocli.io.middlebury import format_calib_txt

    rig = SAMPLES / "rig"
    r = run_cli("calibrate", rig, "-o", tmp_path / "rig.yml", "--pattern", "9x6", "--square", "40mm", "-q")
    assert r.code == 0, r.err
    r = run_cli("rectify", rig / "left" / "01.png", rig / "right" / "01.png", "--calib", tmp_path / "rig.yml",
                "-o", tmp_path / "rect")
    assert r.code == 0, r.err
    out = tmp_path / "rect" / "01"
    result = stereocli.rectify(rig / "left" / "01.png", rig / "right" / "01.png", tmp_path / "rig.yml")
    np.testing.assert_array_equal(result.left, stereocli.read_image(out / "im0.png"))
    np.testing.assert_array_equal(result.right, stereocli.read_image(out / "im1.png"))
    np.testing.assert_array_equal(result.left_valid, stereocli.read_image(out / "valid0.png") > 0)
    assert format_calib_txt(result.calib_txt) == (out / "calib.txt").read_text()


def test_rectify_without_a_calibration_equals_the_command_line(tmp_path, run_cli):
    import cv2

    from stereocli.io.middlebury import format_calib_txt
    from stereocli.rectification.uncalibrated import UncalibratedRectification

    turned = np.array([[1.0, -0.017, 2.0], [0.017, 1.0, 4.0], [0.0, 0.0, 1.0]])  # right view turned 1 deg, lowered
    left = stereocli.read_image(PLANES / "im0.png")
    right = cv2.warpPerspective(stereocli.read_image(PLANES / "im1.png"), turned, (320, 240))
    for name, image in (("left", left), ("right", right)):
        write_image(tmp_path / "pair" / name / "p.png", image)
    r = run_cli("rectify", tmp_path / "pair", "--uncalibrated", "-o", tmp_path / "rect")
    assert r.code == 0, r.err
    out = tmp_path / "rect" / "p"
    result = stereocli.rectify(left, right)
    np.testing.assert_array_equal(result.left, stereocli.read_image(out / "im0.png"))
    np.testing.assert_array_equal(result.right, stereocli.read_image(out / "im1.png"))
    assert format_calib_txt(result.calib_txt) == (out / "calib.txt").read_text()
    assert isinstance(result.rectification, UncalibratedRectification) and result.range["source"] == "estimated"
    again = stereocli.rectify(left, right, result.rectification, disparity_range=(result.range["min_disp"],
                                                                                  result.range["max_disp"]))
    np.testing.assert_array_equal(again.right, result.right)
    assert again.ndisp == result.ndisp and again.range["source"] == "given"


def test_calibrate_takes_a_folder_or_pairs_of_paths_or_arrays(tmp_path, run_cli):
    # OpenCV's solvers sum in parallel: two runs agree to about 1e-9 px, not bit for bit.
    import json

    rig = SAMPLES / "rig"
    assert run_cli("calibrate", rig, "-o", tmp_path / "rig.yml", "--pattern", "9x6", "--square", "40mm",
                   "--fix-k3", "-q").code == 0
    cli = json.loads((tmp_path / "rig.report.json").read_text())
    names = sorted(p.name for p in (rig / "left").glob("*.png"))
    paths = [(rig / "left" / n, rig / "right" / n) for n in names]
    arrays = [(stereocli.read_image(a), stereocli.read_image(b)) for a, b in paths]
    for images in (rig, paths, arrays):
        result = stereocli.calibrate(images, "9x6" if images is rig else (9, 6), square="40mm" if images is rig else 40,
                                     units=None if images is rig else "mm", fix_k3=True)
        assert result.report["rms"] == pytest.approx(cli["rms"], rel=1e-6)
        assert result.report["baseline"]["length"] == pytest.approx(cli["baseline"]["length"], rel=1e-9)
        assert result.report["views_used"] == cli["views_used"] == 12 and result.calibration.units == "mm"
    with pytest.raises(ConfigError, match="unexpected keyword"):
        stereocli.calibrate(rig, "9x6", fix_k4=True)


# --------------------------------------------------------------------------- the documentation


def _public_functions():
    return [getattr(stereocli, name) for name in PUBLIC_FUNCTIONS]


@pytest.mark.parametrize("name", PUBLIC_FUNCTIONS)
def test_every_public_function_has_the_numpydoc_sections(name):
    doc = inspect.getdoc(getattr(stereocli, name))
    for section in ("Parameters", "Returns", "Raises", "Examples"):
        assert re.search(rf"^{section}\n-{{{len(section)}}}$", doc, re.M), f"{name}: no {section} section"
    section = doc.split("Parameters\n----------\n")[1].split("\nReturns\n")[0]
    documented = {n for names in re.findall(r"^(\w+(?:, \w+)*) :", section, re.M) for n in names.split(", ")}
    parameters = {p.name for p in inspect.signature(getattr(stereocli, name)).parameters.values()
                  if p.kind is not p.VAR_KEYWORD}
    assert parameters <= documented, f"{name}: undocumented parameters {sorted(parameters - documented)}"


@pytest.mark.slow
def test_the_examples_in_the_docstrings_run():
    finder = doctest.DocTestFinder()
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    tests = [t for t in finder.find(api, "stereocli.api") if t.examples]
    assert {t.name.rsplit(".", 1)[-1] for t in tests} >= set(PUBLIC_FUNCTIONS)
    for test in tests:
        runner.run(test)
    assert runner.failures == 0, f"{runner.failures} failing example(s); see the output above"


def _readme_python_blocks() -> list[str]:
    return re.findall(r"^```python\n(.*?)^```$", (REPO / "README.md").read_text(), re.M | re.S)


def test_every_python_block_of_the_readme_runs(tmp_path):
    blocks = _readme_python_blocks()
    assert len(blocks) >= 2
    script = tmp_path / "readme.py"
    script.write_text("\n\n".join(blocks))
    done = subprocess.run([sys.executable, str(script)], cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr[-3000:]


def test_docs_api_is_generated_from_the_docstrings():
    # Regenerate with: python -m stereocli.apidoc > docs/api.md
    from stereocli import apidoc

    assert (REPO / "docs" / "api.md").read_text() == apidoc.markdown()


PUBLIC_MODULES = ["stereocli", "stereocli.api", "stereocli.calib", "stereocli.evaluation", "stereocli.features",
                  "stereocli.io", "stereocli.matching", "stereocli.rectification", "stereocli.triangulation",
                  "stereocli.features.survey", "stereocli.runtime", "stereocli.evaluation.api",
                  "stereocli.evaluation.folders", "stereocli.evaluation.scoring"]


@pytest.mark.parametrize("module", PUBLIC_MODULES)
def test_every_public_module_says_what_it_exports(module):
    loaded = importlib.import_module(module)
    assert loaded.__all__ and len(set(loaded.__all__)) == len(loaded.__all__)
    for name in loaded.__all__:
        assert getattr(loaded, name) is not None, f"{module}.{name}"


def test_the_package_is_typed():
    import tomllib

    assert (REPO / "stereocli" / "py.typed").is_file()
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "py.typed" in data["stereocli"]
