"""End to end: synthetic rig photos -> calibrate -> rectify -> match (default preset) ->
triangulate recovers the true scene depth within 1 % median relative error."""

from __future__ import annotations

import numpy as np
import pytest

from stereocli.io.calib import load_calibration
from stereocli.synth.rig import default_rig, default_scene, render_rig, render_scene


@pytest.mark.slow
def test_calibrate_rectify_match_triangulate(tmp_path, run_cli):
    render_rig(tmp_path / "rig", n_pairs=12, seed=0)
    scene = default_scene(seed=3)
    render_scene(default_rig(), scene, out_dir=tmp_path / "pair")
    cal = tmp_path / "rig.yml"
    assert run_cli("calibrate", tmp_path / "rig", "-o", cal, "--pattern", "9x6", "--square", "0.04m", "-q").code == 0
    res = run_cli("rectify", tmp_path / "pair" / "left.png", tmp_path / "pair" / "right.png", "--calib", cal,
                  "-o", tmp_path / "rect")
    assert res.code == 0, res.err
    res = run_cli("match", tmp_path / "rect", "-o", tmp_path / "disp")
    assert res.code == 0, res.err
    res = run_cli("triangulate", tmp_path / "disp", "--scenes", tmp_path / "rect", "-o", tmp_path / "cloud",
                  "--units", "m")
    assert res.code == 0, res.err
    import plyfile  # the test extra installs it

    ply = plyfile.PlyData.read(str(tmp_path / "cloud" / "pair" / "cloud.ply"))
    assert any("units m;" in c for c in ply.comments)
    v = ply["vertex"]
    pts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    R1 = load_calibration(cal).R1  # same alpha (0) as rectify's default
    rays = pts @ R1  # rectified frame -> unrectified left camera frame (R1ᵀ·X)
    truth = scene.depth_along(rays)
    rel = np.abs(np.linalg.norm(rays, axis=1) - truth) / truth
    assert len(pts) > 0.8 * 640 * 480
    assert np.median(rel) < 0.01
