"""Calibration file formats: OpenCV FileStorage, ROS pair, Middlebury calib.txt, Kalibr (read)."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from stereocli.cli.main import cli
from stereocli.errors import ConfigError, DataError
from stereocli.io.calib import (
    StereoCalibration,
    detect_format,
    load_calibration,
    q_from_projections,
    ros_pair_paths,
    save_calibration,
)
from stereocli.rectification import rectified_calibration
from stereocli.synth.rig import default_rig


@pytest.fixture()
def calib() -> StereoCalibration:
    c = rectified_calibration(default_rig().calibration(), alpha=0.0)
    c.rms = 0.1234567890123
    return c


def _same(a: StereoCalibration, b: StereoCalibration, keys=("K1", "D1", "K2", "D2", "R", "T", "E", "F", "R1",
                                                               "R2", "P1", "P2", "Q"), rtol=0.0, atol=0.0):
    for k in keys:
        np.testing.assert_allclose(getattr(b, k), getattr(a, k), rtol=rtol, atol=atol, err_msg=k)


@pytest.mark.parametrize("suffix", [".yml", ".yaml", ".xml", ".json"])
def test_opencv_roundtrip_is_lossless(tmp_path, calib, suffix):
    path = tmp_path / f"rig{suffix}"
    save_calibration(path, calib)
    assert detect_format(path) == "opencv"
    back = load_calibration(path)
    _same(calib, back)  # bit-exact: FileStorage writes 17 significant digits
    assert back.image_size == calib.image_size and back.units == "m" and back.rms == calib.rms
    assert back.rectified_size == calib.rectified_size


def test_ros_pair_roundtrip(tmp_path, calib):
    written = save_calibration(tmp_path / "rig.yaml", calib, "ros")
    assert [p.name for p in written] == ["rig_left.yaml", "rig_right.yaml"]
    text = written[1].read_text()
    assert "projection_matrix" in text and "plumb_bob" in text
    for name in ("rig.yaml", "rig_left.yaml", "rig_right.yaml"):
        back = load_calibration(tmp_path / name)
        _same(calib, back, keys=("K1", "D1", "K2", "D2", "R1", "R2", "P1", "P2"))
        # R, T are recovered from R1, R2, P2 up to floating-point round-off.
        _same(calib, back, keys=("R", "T", "Q"), atol=1e-12)
    # right P[0,3] = -fx' * B
    assert back.P2[0, 3] == pytest.approx(-back.P2[0, 0] * calib.baseline, rel=1e-4)


def test_ros_single_file_with_two_documents(tmp_path, calib):
    left, right = save_calibration(tmp_path / "rig.yaml", calib, "ros")
    both = tmp_path / "both.yaml"
    both.write_text(left.read_text() + "---\n" + right.read_text())
    _same(calib, load_calibration(both), keys=("K1", "K2", "P1", "P2"))


def test_middlebury_roundtrip_and_units(tmp_path, calib):
    path = tmp_path / "calib.txt"
    save_calibration(path, calib, ndisp=96)
    text = path.read_text()
    baseline_mm = -calib.P2[0, 3] / calib.P2[0, 0] * 1000
    assert f"baseline={baseline_mm:.10g}" in text and "ndisp=96" in text
    back = load_calibration(path)
    assert back.units == "mm"
    np.testing.assert_allclose(back.P1, calib.P1, rtol=1e-9)
    np.testing.assert_allclose(back.P2[:, :3], calib.P2[:, :3], rtol=1e-9)
    np.testing.assert_allclose(back.P2[0, 3], calib.P2[0, 3] * 1000, rtol=1e-9)
    # Writing it again gives the same file (lossless at the format's precision).
    save_calibration(tmp_path / "again.txt", back, ndisp=96)
    assert (tmp_path / "again.txt").read_text() == text


def test_kalibr_camchain_read(tmp_path):
    rig = default_rig()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rig.R, rig.T
    fx, fy, cx, cy = (float(v) for v in (rig.K1[0, 0], rig.K1[1, 1], rig.K1[0, 2], rig.K1[1, 2]))
    gx, gy, dx, dy = (float(v) for v in (rig.K2[0, 0], rig.K2[1, 1], rig.K2[0, 2], rig.K2[1, 2]))
    text = f"""cam0:
  camera_model: pinhole
  intrinsics: [{fx!r}, {fy!r}, {cx!r}, {cy!r}]
  distortion_model: radtan
  distortion_coeffs: {rig.D1[:4].tolist()}
  resolution: [640, 480]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1:
{chr(10).join('  - ' + str(row.tolist()) for row in T)}
  camera_model: pinhole
  intrinsics: [{gx!r}, {gy!r}, {dx!r}, {dy!r}]
  distortion_model: radtan
  distortion_coeffs: {rig.D2[:4].tolist()}
  resolution: [640, 480]
"""
    path = tmp_path / "camchain.yaml"
    path.write_text(text)
    assert detect_format(path) == "kalibr"
    c = load_calibration(path)
    np.testing.assert_allclose(c.K1, rig.K1)
    np.testing.assert_allclose(c.R, rig.R)
    np.testing.assert_allclose(c.T, rig.T)
    assert c.units == "m" and c.image_size == (640, 480)


def test_q_from_projections_matches_opencv(calib):
    np.testing.assert_allclose(q_from_projections(calib.P1, calib.P2), calib.Q, rtol=1e-9, atol=1e-12)


def test_bad_calibration_files(tmp_path):
    corrupt = tmp_path / "bad.yml"
    corrupt.write_text("%YAML:1.0\nM1: !!opencv-matrix\n   rows: 3\n   cols: [\n")
    with pytest.raises(DataError, match="bad.yml"):
        load_calibration(corrupt)
    missing = tmp_path / "missing.yml"
    save_calibration(missing, default_rig().calibration())
    missing.write_text(missing.read_text().replace("M2:", "X2:"))
    with pytest.raises(DataError, match="missing key M2"):
        load_calibration(missing)
    with pytest.raises(ConfigError, match="unknown calibration format"):
        load_calibration(tmp_path / "rig.ini")
    with pytest.raises(DataError, match="no such file"):
        load_calibration(tmp_path / "nothere.yml")
    ros = tmp_path / "cam_left.yaml"
    ros.write_text("image_width: 640\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 2]\nprojection_matrix: {}\n")
    (tmp_path / "cam_right.yaml").write_text(ros.read_text())
    with pytest.raises(DataError, match="camera_matrix"):
        load_calibration(ros)
    assert ros_pair_paths(tmp_path / "cam.yaml")[1].name == "cam_right.yaml"


def test_convert_calib_cli(tmp_path, calib, run_cli):
    src = tmp_path / "rig.yml"
    save_calibration(src, default_rig().calibration())  # unrectified: converter rectifies for ros/txt
    runner = CliRunner()
    res = runner.invoke(cli, ["convert-calib", str(src), str(tmp_path / "rig.json")])
    assert res.exit_code == 0, res.output
    _same(load_calibration(src), load_calibration(tmp_path / "rig.json"), keys=("K1", "D1", "K2", "D2", "R", "T"))
    res = runner.invoke(cli, ["convert-calib", str(src), str(tmp_path / "ros"), "--to", "ros"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "ros_left.yaml").is_file() and (tmp_path / "ros_right.yaml").is_file()
    back = load_calibration(tmp_path / "ros_left.yaml")
    np.testing.assert_allclose(back.T, default_rig().T, atol=1e-12)
    res = runner.invoke(cli, ["convert-calib", str(src), str(tmp_path / "calib.txt")])
    assert res.exit_code == 0 and "baseline=" in (tmp_path / "calib.txt").read_text()
    # refuses to clobber; unknown format; corrupt input
    res = run_cli("convert-calib", src, tmp_path / "rig.json")
    assert res.code == 1 and "already exists" in res.err
    res = run_cli("convert-calib", src, tmp_path / "rig.cfg")
    assert res.code == 2 and "format" in res.err
    (tmp_path / "junk.yml").write_text("%YAML:1.0\nM1: !!opencv-matrix\n  rows: [\n")
    res = run_cli("convert-calib", tmp_path / "junk.yml", tmp_path / "o.yml")
    assert res.code == 1 and "junk.yml" in res.err and len(res.err.strip().splitlines()) == 1
    res = run_cli("convert-calib", src, tmp_path / "x.yml", "--to", "kalibr")
    assert res.code == 2
