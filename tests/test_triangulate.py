"""triangulate: formulas, the OpenCV Q path, Middlebury calib.txt, outputs and errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from stereocli.errors import DataError
from stereocli.io.calib import StereoCalibration, load_calibration, save_calibration
from stereocli.io.middlebury import read_calib_txt
from stereocli.io.pfm import read_pfm, write_pfm
from stereocli.triangulation import (
    RectifiedGeometry,
    depth_from_disparity,
    geometry_from_calibration,
    geometry_from_q,
    reproject_q,
    triangulate,
)


def _plane_scene():
    """A rectified rig (f 500, B 0.1 m, doffs 3) looking at a known slanted plane."""
    geom = RectifiedGeometry(f=500.0, cx=159.5, cy=119.5, baseline=0.1, doffs=3.0, units="m")
    h, w = 240, 320
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    Z = 2.0 + 0.002 * x + 0.001 * y  # known depth
    disp = (geom.f * geom.baseline / Z - geom.doffs).astype(np.float32)
    return geom, disp, x, y


def test_synthetic_points_recovered():
    geom, disp, x, y = _plane_scene()
    depth, cloud = triangulate(disp, geom)
    Z = geom.f * geom.baseline / (disp.astype(np.float64) + geom.doffs)
    X, Y = Z * (x - geom.cx) / geom.f, Z * (y - geom.cy) / geom.f
    truth = np.stack([X, Y, Z], -1)[cloud.rows, cloud.cols]
    # The left columns whose match lands left of the right image (x − d < −0.5) are unmatched.
    seen = np.floor(x - disp + 0.5) >= 0
    assert cloud.points.shape == (int(seen.sum()), 3) and cloud.dropped["unmatched"] == int((~seen).sum())
    np.testing.assert_allclose(cloud.points, truth, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(depth[seen], (2.0 + 0.002 * x + 0.001 * y)[seen], rtol=1e-4)
    assert np.isinf(depth[~seen]).all()
    everything, cloud = triangulate(disp, geom, supported=False)
    assert cloud.points.shape == (disp.size, 3)
    np.testing.assert_allclose(everything, 2.0 + 0.002 * x + 0.001 * y, rtol=1e-4)


def test_q_path_agrees_with_opencv():
    geom, disp, _, _ = _plane_scene()
    P1 = np.array([[geom.f, 0, geom.cx, 0], [0, geom.f, geom.cy, 0], [0, 0, 1, 0]])
    P2 = np.array([[geom.f, 0, geom.cx + geom.doffs, -geom.f * geom.baseline], [0, geom.f, geom.cy, 0], [0, 0, 1, 0]])
    calib = StereoCalibration(K1=P1[:, :3], D1=np.zeros(5), K2=P2[:, :3], D2=np.zeros(5), R=np.eye(3),
                              T=[-geom.baseline, 0, 0], P1=P1, P2=P2, R1=np.eye(3), R2=np.eye(3),
                              image_size=(320, 240), units="m")
    from stereocli.io.calib import q_from_projections

    Q = q_from_projections(P1, P2)
    ours = reproject_q(disp, Q)
    cv = cv2.reprojectImageTo3D(disp, Q.astype(np.float32))
    np.testing.assert_allclose(ours, cv, rtol=1e-4)
    g_q = geometry_from_q(Q, "m")
    g_p = geometry_from_calibration(calib)
    for key in ("f", "cx", "cy", "baseline", "doffs"):
        assert getattr(g_q, key) == pytest.approx(getattr(g_p, key), rel=1e-12)
    _, cloud = triangulate(disp, g_q)
    np.testing.assert_allclose(cloud.points, cv[cloud.rows, cloud.cols], rtol=1e-4)


def test_opencv_rectify_q_matches(tmp_path):
    from stereocli.rectification import rectified_calibration
    from stereocli.synth.rig import default_rig

    calib = rectified_calibration(default_rig().calibration())
    disp = np.random.default_rng(0).uniform(5, 80, (480, 640)).astype(np.float32)
    g = geometry_from_calibration(calib)
    _, cloud = triangulate(disp, g)
    cv = cv2.reprojectImageTo3D(disp, calib.Q)
    np.testing.assert_allclose(cloud.points, cv[cloud.rows, cloud.cols], rtol=2e-4)
    assert cloud.points[:, 2].min() > 0  # z forward


def test_middlebury_depth_exact(shared_data, tmp_path, run_cli):
    scene = shared_data / "middlebury2014" / "trainingQ" / "Adirondack"
    mb = read_calib_txt(scene / "calib.txt")
    gt = read_pfm(scene / "disp0GT.pfm")
    res = run_cli("triangulate", scene, "-o", tmp_path / "out", "--summary")
    assert res.code == 0, res.err
    depth = read_pfm(tmp_path / "out" / "Adirondack" / "depth.pfm")
    expected = (mb.baseline * mb.cam0[0, 0] / (gt.astype(np.float64) + mb.doffs)).astype(np.float32)
    # Points whose match lands left of the right image (the left border's occluded strip) are dropped.
    x = np.arange(gt.shape[1])[None, :]
    finite = np.isfinite(gt) & (np.floor(x - np.where(np.isfinite(gt), gt, 0) + 0.5) >= 0)
    assert np.array_equal(depth[finite], expected[finite])
    assert np.isinf(depth[~finite]).all()
    summary = json.loads((tmp_path / "out" / "Adirondack" / "summary.json").read_text())
    assert summary["units"] == "mm" and summary["points"] == int(finite.sum())
    assert summary["dropped"]["unmatched"] == int((np.isfinite(gt) & ~finite).sum()) > 0
    assert summary["range"] == {"min_disp": 0, "ndisp": mb.ndisp, "source": str(scene / "calib.txt")}
    from plyfile import PlyData

    ply = PlyData.read(str(tmp_path / "out" / "Adirondack" / "cloud.ply"))
    assert ply["vertex"].count == int(finite.sum())
    assert any("units mm" in c for c in ply.comments)


def test_triangulate_cli_outputs(tmp_path, run_cli):
    geom, disp, x, y = _plane_scene()
    disp[:10] = np.inf  # invalid rows are dropped, never sentinel points
    write_pfm(tmp_path / "disp0.pfm", disp)
    image = np.zeros((240, 320, 3), np.uint8)
    image[..., 0] = (x % 256).astype(np.uint8)
    image[..., 1] = 7
    cv2.imwrite(str(tmp_path / "im0.png"), image[..., ::-1])
    P1 = np.array([[geom.f, 0, geom.cx, 0], [0, geom.f, geom.cy, 0], [0, 0, 1, 0]])
    P2 = P1.copy()
    P2[0, 2] += geom.doffs
    P2[0, 3] = -geom.f * geom.baseline
    calib = StereoCalibration(K1=P1[:, :3], D1=np.zeros(5), K2=P2[:, :3], D2=np.zeros(5), R=np.eye(3),
                              T=[-0.1, 0, 0], P1=P1, P2=P2, R1=np.eye(3), R2=np.eye(3), image_size=(320, 240),
                              units="m")
    save_calibration(tmp_path / "rig.yml", calib)
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", tmp_path / "rig.yml", "-o", tmp_path / "c.ply",
                  "--depth-format", "npy", "--depth-png16", "--summary", "--normals", "--stride", "2",
                  "--max-depth", "2.5")
    assert res.code == 0, res.err
    from plyfile import PlyData

    v = PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    names = [p.name for p in v.properties]
    assert names == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    depth = np.load(tmp_path / "c_depth.npy")
    keep = np.isfinite(depth)
    assert keep[:10].sum() == 0 and np.nanmax(np.where(keep, depth, np.nan)) <= 2.5
    assert v.count == int(keep[::2, ::2].sum())
    xs = np.round(v["x"] / v["z"] * geom.f + geom.cx).astype(int)
    assert np.array_equal(v["red"], (xs % 256).astype(np.uint8)) and (v["green"] == 7).all()
    assert (v["nz"] < 0).all()  # normals face the camera
    mm = cv2.imread(str(tmp_path / "c_depth_mm.png"), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16 and abs(int(mm[100, 100]) - depth[100, 100] * 1000) <= 0.5
    # ASCII + npy + units conversion
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", tmp_path / "rig.yml", "-o", tmp_path / "a.ply",
                  "--ascii", "--units", "mm", "--no-color")
    assert res.code == 0, res.err
    a = PlyData.read(str(tmp_path / "a.ply"))["vertex"]
    seen = np.isfinite(disp) & (np.floor(x - np.where(np.isfinite(disp), disp, 0) + 0.5) >= 0)
    assert a.count == int(seen.sum()) and float(np.min(a["z"])) > 1999
    assert run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", tmp_path / "rig.yml", "-o",
                   tmp_path / "p.npy").code == 0
    assert np.load(tmp_path / "p.npy").shape == (int(seen.sum()), 3)


def test_triangulate_errors(tmp_path, run_cli):
    geom, disp, _, _ = _plane_scene()
    write_pfm(tmp_path / "disp0.pfm", disp)
    (tmp_path / "calib.txt").write_text("cam0=[500 0 159.5; 0 500 119.5; 0 0 1]\n"
                                        "cam1=[500 0 162.5; 0 500 119.5; 0 0 1]\n"
                                        "doffs=3\nbaseline=100\nwidth=320\nheight=240\nndisp=64\n")
    cv2.imwrite(str(tmp_path / "im0.png"), np.zeros((100, 100), np.uint8))
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "-o", tmp_path / "c.ply")
    assert res.code == 1 and "image is 100x100" in res.err
    (tmp_path / "im0.png").unlink()
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "-o", tmp_path / "c.ply")
    assert res.code == 0, res.err
    write_pfm(tmp_path / "inv" / "disp0.pfm", np.full((240, 320), np.inf, np.float32))
    res = run_cli("triangulate", tmp_path / "inv" / "disp0.pfm", "--calib", tmp_path / "calib.txt", "-o",
                  tmp_path / "inv.ply")
    assert res.code == 1 and "every disparity is invalid" in res.err
    (tmp_path / "neg.txt").write_text("cam0=[500 0 159.5; 0 500 119.5; 0 0 1]\nbaseline=-100\nwidth=320\nheight=240\n")
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", tmp_path / "neg.txt", "-o", tmp_path / "n.ply")
    assert res.code == 1 and "baseline must be positive" in res.err
    (tmp_path / "nocam.txt").write_text("baseline=100\n")
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", tmp_path / "nocam.txt", "-o", tmp_path / "m.ply")
    assert res.code == 1 and "cam0" in res.err
    (tmp_path / "big.txt").write_text("cam0=[500 0 159.5; 0 500 119.5; 0 0 1]\nbaseline=100\nwidth=640\nheight=480\n")
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", tmp_path / "big.txt", "-o", tmp_path / "b.ply")
    assert res.code == 1 and "640x480" in res.err
    res = run_cli("triangulate", tmp_path / "disp0.pfm", "--calib", tmp_path / "calib.txt", "-o", tmp_path / "x.ply",
                  "--min-depth", "5", "--max-depth", "1")
    assert res.code == 2
    from stereocli.synth.rig import default_rig

    save_calibration(tmp_path / "unrect.yml", default_rig().calibration())
    with pytest.raises(DataError, match="no rectification"):
        geometry_from_calibration(load_calibration(tmp_path / "unrect.yml"))
    with pytest.raises(DataError, match="baseline"):
        RectifiedGeometry(f=500, cx=0, cy=0, baseline=-1)


def test_depth_handles_doffs_and_invalid():
    geom = RectifiedGeometry(f=100.0, cx=0, cy=0, baseline=2.0, doffs=-5.0)
    d = np.array([[np.inf, 4.0, 5.0, 15.0]], np.float32)
    depth = depth_from_disparity(d, geom)
    assert np.isinf(depth[0, :3]).all() and depth[0, 3] == pytest.approx(20.0)
