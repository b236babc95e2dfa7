"""PLY writer: binary little endian and ASCII, read back with plyfile (test-only dependency)."""

from __future__ import annotations

import numpy as np
import plyfile  # the test extra installs it
import pytest

from stereocli.errors import DataError
from stereocli.io.ply import write_ply


@pytest.mark.parametrize("ascii", [False, True])
def test_roundtrip_with_plyfile(tmp_path, ascii):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)).astype(np.float32)
    col = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    conf = rng.uniform(size=500).astype(np.float32)
    nrm = rng.normal(size=(500, 3)).astype(np.float32)
    path = tmp_path / "c.ply"
    n = write_ply(path, pts, colors=col, normals=nrm, confidence=conf, comments=["units m; frame left"], ascii=ascii)
    assert n == 500
    assert path.read_bytes().startswith(b"ply\nformat " + (b"ascii" if ascii else b"binary_little_endian"))
    data = plyfile.PlyData.read(str(path))
    v = data["vertex"]
    assert v.count == 500 and data.comments == ["units m; frame left"]
    np.testing.assert_array_equal(np.c_[v["x"], v["y"], v["z"]], pts)
    np.testing.assert_array_equal(np.c_[v["red"], v["green"], v["blue"]], col)
    np.testing.assert_array_equal(v["confidence"], conf)
    np.testing.assert_array_equal(v["nx"], nrm[:, 0])


def test_empty_and_invalid(tmp_path):
    write_ply(tmp_path / "e.ply", np.zeros((0, 3)))
    assert plyfile.PlyData.read(str(tmp_path / "e.ply"))["vertex"].count == 0
    with pytest.raises(DataError, match="non-finite"):
        write_ply(tmp_path / "bad.ply", np.array([[0, 0, np.inf]]))
