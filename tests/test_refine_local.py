"""Local outlier handling (single matching phase, texture threshold, weighted-median fill), the
realtime preset, and every local stage through ``stereocli stages`` / ``stereocli match``."""

from __future__ import annotations

import numpy as np
import pytest

from local_scene import run_stages, scene
from stereocli import registry
from stereocli.errors import ConfigError
from stereocli.matching.config import build_config
from stereocli.matching.kernels.refine import single_matching_phase_kernel, weighted_median_at
from stereocli.matching.pipeline import match_pair
from stereocli.matching.state import MatchState

INF = np.inf


def test_single_matching_phase_keeps_the_better_claim():
    # row 0: x=2 (d=1) and x=3 (d=2) both claim right pixel 1; x=3 has the lower cost
    disp = np.array([[INF, INF, 1, 2, 0]], np.float32)
    cost = np.full((1, 5, 3), 9, np.float32)
    cost[0, 1, 0] = 1.0
    cost[0, 2, 1] = 5.0
    cost[0, 3, 2] = 2.0
    cost[0, 4, 0] = 1.0
    out = single_matching_phase_kernel(disp, cost, 0)
    np.testing.assert_array_equal(out, [[INF, INF, INF, 2, 0]])
    # the later claim loses when it is worse
    cost[0, 3, 2] = 7.0
    np.testing.assert_array_equal(single_matching_phase_kernel(disp, cost, 0), [[INF, INF, 1, INF, 0]])


def test_single_matching_phase_rejects_occlusions_on_the_scene():
    left, right, gt, mask = scene(color=True)
    st = run_stages(left, right, 16, [("cost", "sad", {"window": [7, 7]}), ("optimizer", "wta", {}),
                                      ("refinement", "single_matching_phase", {})])
    good = np.isfinite(st.disparity)
    assert (st.disparity[mask & good] == gt[mask & good]).all()
    assert good[mask].mean() > 0.97
    # in the band occluded in the right view (left of the foreground) most pixels are rejected
    h, w = gt.shape
    band = np.zeros_like(mask)
    band[h // 4 + 4:3 * h // 4 - 4, w // 3 - 5:w // 3 - 1] = True
    assert (~good[band]).mean() > 0.5


def test_texture_threshold_marks_flat_regions_invalid():
    left, right, gt, mask = scene(color=False)
    left[:, :30] = 100.0  # a flat band
    st = MatchState(left, right, 0, 16, disparity=np.ones_like(gt))
    stage = registry.get("refinement", "texture")
    stage.func(st, stage.make_params({"window": [5, 5], "min_std": 2.0}))
    assert not np.isfinite(st.disparity[:, :27]).any()
    assert np.isfinite(st.disparity[:, 40:]).all()


def test_weighted_median_fills_only_holes():
    disp = np.full((9, 9), 4.0, np.float32)
    disp[:, 5:] = 8.0
    guide = np.zeros((9, 9, 1), np.float32)
    guide[:, 5:] = 200.0
    todo = np.zeros((9, 9), bool)
    todo[4, 4] = todo[4, 6] = True
    holes = disp.copy()
    holes[4, 4] = 8.0  # a wrong value the median must fix (its colour says "left side")
    holes[4, 6] = INF
    out = weighted_median_at(holes, todo, guide, 3, 3.0, 25.5)
    assert out[4, 4] == 4.0 and out[4, 6] == 8.0
    assert (out[~todo] == holes[~todo]).all()
    st = MatchState(guide[..., 0], guide[..., 0], 0, 16, disparity=np.where(todo, INF, disp).astype(np.float32))
    stage = registry.get("refinement", "fill_weighted_median")
    stage.func(st, stage.make_params({"radius": 3}))
    np.testing.assert_array_equal(st.disparity, disp)


def test_realtime_preset_end_to_end():
    cfg = build_config(["realtime"])
    assert cfg.cost.stage.name == "sad"
    assert [c.stage.name for c in cfg.refinement] == ["single_matching_phase", "subpixel", "texture"]
    left, right, gt, mask = scene(color=True)
    res = match_pair(left, right, cfg, ndisp=16)
    good = np.isfinite(res.disparity) & mask
    assert good.sum() / mask.sum() > 0.9
    assert np.abs(res.disparity[good] - gt[good]).max() < 0.5  # sub-pixel stays near the integer truth


@pytest.mark.parametrize("name,values,key", [
    ("texture", {"window": [4, 4]}, "window"),
    ("texture", {"min_std": -1}, "min_std"),
    ("single_matching_phase", {"radius": 2}, "radius"),
    ("fill_weighted_median", {"sigma_c": 0}, "sigma_c"),
])
def test_invalid_parameters(name, values, key):
    with pytest.raises(ConfigError, match=key):
        registry.get("refinement", name).make_params(values, source="x.yaml", section="refinement[0]")


def test_volume_stage_order_is_enforced(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("refinement: [{name: texture}, {name: single_matching_phase}]\n")
    with pytest.raises(ConfigError, match="single_matching_phase"):
        build_config([str(bad)])


LOCAL_STAGES = {
    "preprocess": ["log", "mean_removal", "bilateral_subtraction", "xsobel", "histogram_matching"],
    "cost": ["ad", "sd", "tad", "sad", "ssd", "stad", "ncc", "zncc", "gradient", "color_gradient", "bt",
             "census", "rank", "ad_census", "ordinal"],
    "aggregation": ["box", "shiftable", "multiple_windows", "variable_window", "cross", "adaptive_weights",
                    "segment_support", "fast_bilateral", "locally_consistent", "guided_filter"],
    "refinement": ["single_matching_phase", "texture", "fill_weighted_median"],
}


def test_every_local_stage_is_listed(run_cli):
    r = run_cli("stages", "--format", "json")
    assert r.code == 0, r.err
    import json

    listed = {(s["kind"], s["name"]): s for s in json.loads(r.out)}
    for kind, names in LOCAL_STAGES.items():
        for name in names:
            s = listed[(kind, name)]
            assert s["summary"] and len(s["doc"].splitlines()) > 2, name  # summary + documentation
            for p in s["params"]:
                assert p["help"], (name, p["name"])


def test_match_cli_runs_local_stages(run_cli, tmp_path):
    from stereocli.io.images import write_image
    from stereocli.io.pfm import read_pfm

    left, right, gt, mask = scene(color=True)
    folder = tmp_path / "pair"
    folder.mkdir()
    write_image(folder / "im0.png", np.rint(left).astype(np.uint8))
    write_image(folder / "im1.png", np.rint(right).astype(np.uint8))
    local = ("cost: {name: tad, truncate: 30}\naggregation: [{name: adaptive_weights, window: 11}]\n"
             "optimizer: {name: wta}\nrefinement: [{name: subpixel}, {name: lr_check}, {name: fill}]\n")
    (tmp_path / "aw.yaml").write_text(local)
    (tmp_path / "gf.yaml").write_text("preprocess: [{name: histogram_matching}]\n" + local.replace(
        "{name: tad, truncate: 30}", "{name: color_gradient}").replace("{name: adaptive_weights, window: 11}",
                                                                         "{name: guided_filter, radius: 5}"))
    runs = {
        "realtime": ["--config", "realtime"],
        "aw": ["--config", tmp_path / "aw.yaml"],
        "gf": ["--config", tmp_path / "gf.yaml", "--set", "aggregation.guided_filter.eps=0.001"],
    }
    for tag, args in runs.items():
        out = tmp_path / tag
        r = run_cli("match", folder / "im0.png", folder / "im1.png", "-o", out, "--ndisp", "16", *args)
        assert r.code == 0, (tag, r.err)
        disp = read_pfm(next(out.rglob("disp0.pfm")))
        good = np.isfinite(disp) & mask
        assert good.sum() > 0.9 * mask.sum() and (np.abs(disp[good] - gt[good]) < 1).mean() > 0.97, tag
    r = run_cli("match", folder / "im0.png", folder / "im1.png", "-o", tmp_path / "bad", "--ndisp", "16",
                "--set", "cost.name=sad", "--set", "cost.window=[4,4]")
    assert r.code == 2 and "cost.window" in r.err
