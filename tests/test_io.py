"""File formats: PFM (row order, endianness), disparity PNG/npy, calib.txt, input pairing."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from stereocli.errors import DataError
from stereocli.io.images import read_disparity, read_image, write_disparity, write_image
from stereocli.io.middlebury import read_calib_txt
from stereocli.io.pairs import discover_pairs
from stereocli.io.pfm import read_pfm, write_pfm


def _pfm_bytes(rows_bottom_first, width, height, little=True):
    scale = b"-1.0" if little else b"1.0"
    fmt = "<" if little else ">"
    body = b"".join(struct.pack(f"{fmt}{width}f", *row) for row in rows_bottom_first)
    return b"Pf\n%d %d\n%s\n" % (width, height, scale) + body


@pytest.mark.parametrize("little", [True, False])
def test_pfm_rows_are_bottom_to_top_in_both_endiannesses(tmp_path, little):
    # File stores the bottom row first: [[5, 6], [3, 4], [1, 2]] means the top row is [1, 2].
    path = tmp_path / "x.pfm"
    path.write_bytes(_pfm_bytes([[5, 6], [3, 4], [1, 2]], 2, 3, little))
    img = read_pfm(path)
    assert img.dtype == np.float32
    np.testing.assert_array_equal(img, [[1, 2], [3, 4], [5, 6]])


def test_pfm_round_trip_keeps_inf_and_values(tmp_path):
    rng = np.random.default_rng(0)
    disp = rng.uniform(0, 100, (7, 5)).astype(np.float32)
    disp[2, 3] = np.inf
    write_pfm(tmp_path / "d.pfm", disp)
    back = read_pfm(tmp_path / "d.pfm")
    np.testing.assert_array_equal(back, disp)
    raw = (tmp_path / "d.pfm").read_bytes()
    assert raw.startswith(b"Pf\n5 7\n-1.0\n")
    # The first stored row is the image's bottom row.
    assert struct.unpack("<5f", raw[len(b"Pf\n5 7\n-1.0\n"):][:20]) == tuple(disp[-1].tolist())


def test_pfm_errors(tmp_path):
    (tmp_path / "bad.pfm").write_bytes(b"P6\n1 1\n255\n\x00\x00\x00")
    with pytest.raises(DataError, match="not a PFM"):
        read_pfm(tmp_path / "bad.pfm")
    (tmp_path / "short.pfm").write_bytes(b"Pf\n4 4\n-1.0\n" + b"\x00" * 10)
    with pytest.raises(DataError, match="truncated PFM"):
        read_pfm(tmp_path / "short.pfm")


def test_real_middlebury_pfm_and_calib(shared_data):
    scene = shared_data / "middlebury2014" / "trainingQ" / "Adirondack"
    gt = read_pfm(scene / "disp0GT.pfm")
    calib = read_calib_txt(scene / "calib.txt")
    assert gt.shape == (calib.height, calib.width) == (496, 718)
    finite = gt[np.isfinite(gt)]
    assert calib.vmin <= finite.min() and finite.max() <= calib.vmax
    assert calib.ndisp == 73 and calib.doffs == pytest.approx(53.271) and calib.baseline == pytest.approx(176.252)
    # Bottom-to-top: the image's top rows are the far wall (small disparity), the bottom rows the
    # chair's seat close to the camera (large disparity). A reader that forgot to flip fails this.
    top = np.nanmedian(np.where(np.isfinite(gt[:40]), gt[:40], np.nan))
    bottom = np.nanmedian(np.where(np.isfinite(gt[-40:]), gt[-40:], np.nan))
    assert top < bottom


def test_disparity_png16_and_npy(tmp_path):
    disp = np.array([[0.5, 10.25, np.inf], [255.99, -1.0, 3.0]], np.float32)
    write_disparity(tmp_path / "d.png", disp, png_scale=256)
    back = read_disparity(tmp_path / "d.png")
    np.testing.assert_allclose(back[np.isfinite(back)], [0.5, 10.25, 255.99, 3.0], atol=1 / 512)
    assert np.isinf(back[0, 2]) and np.isinf(back[1, 1])  # invalid and unrepresentable negative
    write_disparity(tmp_path / "d.npy", disp)
    np.testing.assert_array_equal(read_disparity(tmp_path / "d.npy"), disp)


def test_eight_bit_disparity_needs_scale(tmp_path):
    write_image(tmp_path / "gt.png", np.full((2, 2), 64, np.uint8))
    with pytest.raises(DataError, match="explicit scale"):
        read_disparity(tmp_path / "gt.png")
    assert read_disparity(tmp_path / "gt.png", scale=4)[0, 0] == 16.0


def test_nan_disparity_rejected(tmp_path):
    np.save(tmp_path / "n.npy", np.array([[np.nan, 1.0]], np.float32))
    with pytest.raises(DataError, match="NaN"):
        read_disparity(tmp_path / "n.npy")


def test_truncated_and_missing_images(tmp_path):
    write_image(tmp_path / "ok.png", np.zeros((8, 8, 3), np.uint8))
    data = (tmp_path / "ok.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="unreadable or truncated"):
        read_image(tmp_path / "cut.png")
    with pytest.raises(DataError, match="no such file"):
        read_image(tmp_path / "missing.png")


def _img(path):
    write_image(path, np.zeros((4, 4), np.uint8))


def test_pairing_forms(tmp_path):
    scene = tmp_path / "sceneA"
    scene.mkdir()
    _img(scene / "im0.png")
    _img(scene / "im1.png")
    (scene / "calib.txt").write_text("cam0=[1 0 2; 0 1 2; 0 0 1]\nndisp=16\n")
    pairs, problems = discover_pairs([str(scene)])
    assert [p.name for p in pairs] == ["sceneA"] and pairs[0].calib and not problems

    lr = tmp_path / "lr"
    (lr / "left").mkdir(parents=True)
    (lr / "right").mkdir()
    for stem in ("0001", "0002", "0003"):
        _img(lr / "left" / f"{stem}.png")
    for stem in ("0001", "0002", "0004"):
        _img(lr / "right" / f"{stem}.png")
    pairs, problems = discover_pairs([str(lr)])
    assert [p.name for p in pairs] == ["0001", "0002"]
    assert len(problems) == 2 and any("0003" in p for p in problems) and any("0004" in p for p in problems)

    pairs, _ = discover_pairs([str(lr / "left" / "0001.png"), str(lr / "right" / "0001.png")])
    assert pairs[0].name == "0001"


def test_pairing_errors(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="empty folder"):
        discover_pairs([str(empty)])
    with pytest.raises(DataError, match="no such file or folder"):
        discover_pairs([str(tmp_path / "nope")])
    _img(tmp_path / "a.png")
    with pytest.raises(DataError, match="left/right pairs"):
        discover_pairs([str(tmp_path / "a.png")])
