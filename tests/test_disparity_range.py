"""A user's own pairs: the estimated disparity range, the row-alignment check, and matching
without a calib.txt (synthetic pairs with known ranges, the real scenes of ../shared/data)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import V2_SCENES
from stereocli.errors import DataError
from stereocli.features.alignment import DEFAULT_THRESHOLD, row_alignment
from stereocli.features.disparity_range import estimate_range
from stereocli.features.points import match_points
from stereocli.io.images import read_image, write_image
from stereocli.io.pfm import read_pfm


def texture(h: int, w: int, seed: int) -> np.ndarray:
    """Random texture with some spatial correlation, float32 in [0, 255]."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.2)
    img -= img.min()
    return img * np.float32(255.0 / img.max())


def slanted_pair(lo: float, hi: float, *, h: int = 240, w: int = 320, seed: int = 0):
    """A textured plane whose left-referenced disparity runs from ``lo`` (left edge) to ``hi``
    (right edge): left(x, y) = right(x − d(x), y). Returns ``(left, right, disparity)``."""
    pad = int(max(abs(lo), abs(hi))) + 8
    right = texture(h, w + 2 * pad, seed)
    disp = np.tile(np.linspace(lo, hi, w, dtype=np.float32), (h, 1))
    xs = np.arange(w, dtype=np.float32)[None, :] - disp + pad
    ys = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, 1)
    left = cv2.remap(right, xs, ys, cv2.INTER_LINEAR)
    return left, np.ascontiguousarray(right[:, pad:pad + w]), disp


@pytest.mark.parametrize("lo, hi", [(4.0, 28.0), (-20.0, 6.0), (-30.0, -8.0), (40.0, 72.0)])
def test_estimated_range_covers_a_known_range(lo, hi):
    left, right, disp = slanted_pair(lo, hi, seed=int(abs(lo)))
    est = estimate_range(left, right)
    assert est.min_disp <= lo and est.max_disp >= hi, est
    # Tight enough to be useful: the margin is 2s + 4 px at each end (s = 2 at this size).
    assert est.ndisp <= (hi - lo) + 2 * (2 * est.scale + 4) + 4, est
    assert est.as_dict()["sparse_matches"] > 30


def test_a_pair_without_texture_cannot_be_estimated():
    flat = np.full((120, 160), 128.0, np.float32)
    with pytest.raises(DataError, match="too little texture"):
        estimate_range(flat, flat)


def test_row_alignment_of_a_rectified_and_a_shifted_pair():
    left, right, _ = slanted_pair(4.0, 20.0, seed=3)
    aligned = row_alignment(match_points(left, right))
    assert aligned.aligned and aligned.max_offset < 0.5
    lowered = np.ascontiguousarray(np.roll(right, 5, axis=0))  # the right view 5 rows lower
    shifted = row_alignment(match_points(left, lowered))
    assert not shifted.aligned
    assert shifted.median_dy == pytest.approx(-5.0, abs=0.3)
    assert "5." in shifted.describe()


def test_ransac_draws_three_distinct_matches_uniformly():
    from collections import Counter

    from stereocli.features.alignment import _distinct_triples

    draws = _distinct_triples(np.random.default_rng(1), 5, 100_000)
    assert draws.min() == 0 and draws.max() == 4
    assert (draws[:, 0] != draws[:, 1]).all() and (draws[:, 0] != draws[:, 2]).all()
    assert (draws[:, 1] != draws[:, 2]).all()
    # Each of the 10 sets of three is drawn 10,000 times in expectation (σ ≈ 95), and each
    # index in each position 20,000 times.
    sets = Counter(tuple(sorted(row)) for row in draws.tolist())
    assert len(sets) == 10 and all(9_500 < n < 10_500 for n in sets.values())
    for position in range(3):
        assert all(19_300 < n < 20_700 for n in np.bincount(draws[:, position], minlength=5))
    assert (np.sort(_distinct_triples(np.random.default_rng(1), 3, 50), axis=1) == [0, 1, 2]).all()  # n = 3


def test_the_alignment_quantiles_are_numpys():
    from stereocli.features.alignment import _quantile

    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 10, 101):
        values = rng.normal(size=n)
        for q in (0.0, 0.5, 0.9, 1.0):
            assert _quantile(values, q) == pytest.approx(np.quantile(values, q), abs=1e-12), (n, q)
    assert _quantile(np.array([4.0, 1.0, 3.0, 2.0]), 0.5) == 2.5


def test_too_few_matches_is_not_a_verdict():
    flat = np.full((60, 80), 10.0, np.float32)
    result = row_alignment(match_points(flat, flat))
    assert not result.measured and result.aligned and "not measured" in result.describe()


# --- the command line ---------------------------------------------------------------------------


def _write_pair(folder: Path, left, right) -> Path:
    folder.mkdir(parents=True)
    write_image(folder / "im0.png", np.rint(left).astype(np.uint8))
    write_image(folder / "im1.png", np.rint(right).astype(np.uint8))
    return folder


def test_match_without_calib_estimates_and_records_the_range(run_cli, tmp_path):
    left, right, disp = slanted_pair(-12.0, 10.0, seed=5)
    _write_pair(tmp_path / "pairs" / "neg", left, right)
    flat = _write_pair(tmp_path / "pairs" / "flat", np.full((120, 160), 90.0), np.full((120, 160), 90.0))
    r = run_cli("match", tmp_path / "pairs", "-o", tmp_path / "out")
    assert r.code == 3, r.err  # the textureless pair fails alone; the other is matched
    assert "flat" in r.err and "too little texture" in r.err and "Traceback" not in r.err
    params = json.loads((tmp_path / "out" / "neg" / "params.json").read_text())
    assert params["range"]["source"] == "estimated" and params["range"]["evidence"]["sparse_matches"] > 30
    assert params["min_disp"] == params["range"]["min_disp"] <= -12 and params["min_disp"] + params["ndisp"] > 10
    est = read_pfm(tmp_path / "out" / "neg" / "disp0.pfm")
    inner = (slice(8, -8), slice(24, -24))
    assert np.mean(np.abs(est[inner] - disp[inner]) < 1.0) > 0.97
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    by_name = {i["name"]: i for i in run["items"]}
    assert by_name["neg"]["details"]["range"]["source"] == "estimated"
    assert by_name["flat"]["status"] == "failed"
    assert not (tmp_path / "out" / "flat" / "disp0.pfm").exists()
    assert not flat.joinpath("calib.txt").exists()


def test_range_sources_option_calib_and_auto(run_cli, tmp_path):
    left, right, _ = slanted_pair(6.0, 18.0, seed=6)
    scene = _write_pair(tmp_path / "s", left, right)
    (scene / "calib.txt").write_text("cam0=[300 0 160; 0 300 120; 0 0 1]\nndisp=32\n")

    def plan(*extra):
        return json.loads(run_cli("match", scene, "-o", tmp_path / "o", "--dry-run", *extra).out)["items"][0]

    assert (plan()["range_source"], plan()["ndisp"]) == ("calib.txt", 32)
    assert (plan("--ndisp", "24")["range_source"], plan("--ndisp", "24")["ndisp"]) == ("option", 24)
    assert plan("--ndisp", "auto")["range_source"] == "estimated"
    r = run_cli("match", scene, "-o", tmp_path / "o", "--ndisp", "lots")
    assert r.code == 2 and "auto" in r.err
    r = run_cli("match", scene, "-o", tmp_path / "o2", "--ndisp", "auto")
    assert r.code == 0, r.err
    params = json.loads((tmp_path / "o2" / "s" / "params.json").read_text())
    assert params["range"]["source"] == "estimated"
    assert params["min_disp"] <= 6 and params["min_disp"] + params["ndisp"] > 18


def test_misaligned_pair_warns_and_fails_on_request(run_cli, tmp_path):
    left, right, _ = slanted_pair(6.0, 18.0, seed=7)
    scene = _write_pair(tmp_path / "low", left, np.roll(right, 6, axis=0))
    r = run_cli("match", scene, "-o", tmp_path / "o", "--ndisp", "32", "-c", "fast")
    assert r.code == 0
    warning = [line for line in r.err.splitlines() if line.startswith("Warning: low: rows not aligned")]
    assert len(warning) == 1 and ("median -6." in warning[0] or "median -5.9" in warning[0])
    assert warning[0].endswith("rectify the pair first (stereocli rectify --calib RIG.yml, or stereocli rectify "
                               "--uncalibrated without a calibration)")  # fast has no row_align
    params = json.loads((tmp_path / "o" / "low" / "params.json").read_text())
    assert params["alignment"]["aligned"] is False and params["warnings"]
    assert params["alignment"]["source"] == "sparse matches"
    # The default's row_align measures the rows (no sparse matches) and moves them back, and the
    # warning says so.
    r = run_cli("match", scene, "-o", tmp_path / "o1", "--ndisp", "32")
    warning = [line for line in r.err.splitlines() if line.startswith("Warning: low: rows not aligned")]
    assert r.code == 0 and len(warning) == 1 and "row_align moved the right view's rows by up to 6." in warning[0]
    params = json.loads((tmp_path / "o1" / "low" / "params.json").read_text())
    note = params["stage_notes"]["row_align"]
    assert note["applied"] is True and note["measured"] is True and abs(note["offset_px"] - 6.0) < 0.2
    assert params["alignment"]["source"] == "row_align" and params["alignment"]["aligned"] is False
    assert abs(params["alignment"]["max_offset"] - note["largest_px"]) < 1e-3 and params["survey_seconds"] == 0.0
    r = run_cli("match", scene, "-o", tmp_path / "o2", "--ndisp", "32", "--require-aligned")
    assert r.code == 1 and "--require-aligned" in r.err and "rows not aligned" in r.err
    assert not (tmp_path / "o2" / "low" / "disp0.pfm").exists()


def test_rows_measured_once_per_pair(run_cli, tmp_path, monkeypatch):
    import stereocli.features.points as points

    left, right, _ = slanted_pair(6.0, 18.0, seed=9)
    scene = _write_pair(tmp_path / "flat", left, right)
    calls = []
    real = points.match_points
    monkeypatch.setattr(points, "match_points", lambda *a, **k: calls.append(1) or real(*a, **k))
    # The range known and row_align tracking: its fit is the measurement, no sparse matches.
    r = run_cli("match", scene, "-o", tmp_path / "o", "--ndisp", "32")
    alignment = json.loads((tmp_path / "o" / "flat" / "params.json").read_text())["alignment"]
    assert r.code == 0 and calls == [] and "rows not aligned" not in r.err
    assert alignment["source"] == "row_align" and alignment["aligned"] is True and alignment["max_offset"] < 0.5
    # A fit that is no measurement (too few tracks for it) falls back to the sparse matches.
    r = run_cli("match", scene, "-o", tmp_path / "o1", "--ndisp", "32",
                "--set", "preprocess.row_align.min_tracks=100000")
    params = json.loads((tmp_path / "o1" / "flat" / "params.json").read_text())
    assert r.code == 0 and len(calls) == 1 and params["stage_notes"]["row_align"]["measured"] is False
    assert params["alignment"]["source"] == "sparse matches" and params["alignment"]["aligned"] is True
    # Without a known range the survey matches anyway (for the estimate) and measures the rows.
    r = run_cli("match", scene, "-o", tmp_path / "o2", "--ndisp", "auto")
    alignment = json.loads((tmp_path / "o2" / "flat" / "params.json").read_text())["alignment"]
    assert r.code == 0 and len(calls) == 2 and alignment["source"] == "sparse matches"


def test_two_files_of_a_scene_folder_are_that_scene(run_cli, tmp_path):
    left, right, _ = slanted_pair(6.0, 18.0, seed=8)
    scene = _write_pair(tmp_path / "Bench", left, right)
    (scene / "calib.txt").write_text("cam0=[300 0 160; 0 300 120; 0 0 1]\nndisp=40\n")
    r = run_cli("match", scene / "im0.png", scene / "im1.png", "-o", tmp_path / "o", "--dry-run")
    item = json.loads(r.out)["items"][0]
    assert item["name"] == "Bench" and item["ndisp"] == 40 and item["inputs"]["calib"].endswith("calib.txt")
    loose = tmp_path / "loose"
    loose.mkdir()
    for name in ("a.png", "b.png"):
        shutil.copy(scene / "im0.png", loose / name)
    r = run_cli("match", loose / "a.png", loose / "b.png", "-o", tmp_path / "o", "--dry-run")
    item = json.loads(r.out)["items"][0]
    assert item["name"] == "a" and item["range_source"] == "estimated"


# --- real scenes (../shared/data) ---------------------------------------------------------------


def _real_scenes(data: Path):
    for folder in sorted((data / "middlebury2014" / "trainingQ").iterdir()):
        yield folder.name, folder, folder / "im0.png", folder / "im1.png"
    for name, (sub, left, right, _) in V2_SCENES.items():
        yield name, data / sub, data / sub / f"{left}.png", data / sub / f"{right}.png"


@pytest.fixture(scope="module")
def real_estimates(shared_data):
    from stereocli.evaluation.datasets import load_scene

    out = {}
    for name, folder, left, right in _real_scenes(shared_data):
        gt = load_scene(folder).gt
        out[name] = (estimate_range(read_image(left), read_image(right)), gt[np.isfinite(gt)])
    assert len(out) == 19
    return out


@pytest.mark.shared_data
def test_estimated_range_covers_the_ground_truth_of_every_real_scene(real_estimates):
    for name, (est, gt) in real_estimates.items():
        covered = np.mean((gt >= est.min_disp) & (gt <= est.max_disp))
        assert covered >= 0.995, (name, est, covered)


@pytest.mark.shared_data
def test_estimated_range_is_at_most_twice_the_span_plus_32(real_estimates):
    for name, (est, gt) in real_estimates.items():
        assert est.ndisp <= 2 * (gt.max() - gt.min()) + 32, (name, est)


@pytest.mark.shared_data
def test_no_false_alignment_alarm_on_real_rectified_pairs(shared_data):
    offsets = {}
    for name, _, left, right in _real_scenes(shared_data):
        result = row_alignment(match_points(read_image(left), read_image(right)))
        assert result.measured and result.aligned, (name, result)
        offsets[name] = result.max_offset
    assert max(offsets.values()) < DEFAULT_THRESHOLD / 2, offsets  # a margin below the threshold


@pytest.mark.shared_data
def test_adirondack_six_rows_lower_is_flagged(shared_data):
    folder = shared_data / "middlebury2014" / "trainingQ" / "Adirondack"
    left, right = read_image(folder / "im0.png"), read_image(folder / "im1.png")
    result = row_alignment(match_points(left, np.roll(right, 6, axis=0)))
    assert not result.aligned and result.median_dy == pytest.approx(-6.0, abs=0.4)


@pytest.mark.shared_data
@pytest.mark.slow
def test_default_preset_with_estimated_ranges_scores_like_the_known_ones(shared_data):
    """Mean bad 2.0 (official rules) over the 19 scenes: at most 1.0 point worse than with the
    known ranges (MiddEval3 calib.txt ndisp; 16/32/64/64 for the 2001/2003 scenes)."""
    from stereocli.evaluation.api import EvalOptions, evaluate_pair
    from stereocli.evaluation.datasets import load_scene
    from stereocli.io.middlebury import read_calib_txt
    from stereocli.matching.config import build_config
    from stereocli.matching.pipeline import match_pair

    config = build_config()
    known, estimated = [], []
    for name, folder, left_path, right_path in _real_scenes(shared_data):
        left, right = read_image(left_path), read_image(right_path)
        if name in V2_SCENES:
            ndisp, options, gt = V2_SCENES[name][3], EvalOptions(ndisp=V2_SCENES[name][3]), load_scene(folder)
        else:
            ndisp = read_calib_txt(folder / "calib.txt").ndisp
            options, gt = EvalOptions(resolution="Q", threshold_units="full"), load_scene(folder, resolution="Q")
        est = estimate_range(left, right)
        for scores, (lo, nd) in ((known, (0, ndisp)), (estimated, (est.min_disp, est.ndisp))):
            disp = match_pair(left, right, config, min_disp=lo, ndisp=nd).disparity
            scores.append(evaluate_pair(disp, gt, options=options, name=name).metrics["nonocc"]["bad2.0"])
    assert np.mean(estimated) <= np.mean(known) + 1.0, (np.mean(known), np.mean(estimated))
