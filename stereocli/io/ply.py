"""PLY point clouds: binary little endian by default, ASCII on request.

Vertex properties, in order: ``float x y z``, optional ``float nx ny nz``, optional
``uchar red green blue``, optional ``float confidence``. A ``comment`` line states the units
and frame, so a cloud file explains itself.
"""

from __future__ import annotations

import os
from typing import cast

import numpy as np

from ..errors import DataError
from .atomic import atomic_path


def _vertex_dtype(normals: bool, colors: bool, confidence: bool) -> np.dtype:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if confidence:
        fields += [("confidence", "<f4")]
    return np.dtype(fields)


def write_ply(path: str | os.PathLike, points: np.ndarray, *, colors: np.ndarray | None = None,
              normals: np.ndarray | None = None, confidence: np.ndarray | None = None,
              comments: list[str] | tuple[str, ...] = (), ascii: bool = False) -> int:
    """Write an (N, 3) float point cloud (+ optional (N, 3) uint8 colours, normals, (N,) confidence).

    Returns the number of vertices written. Non-finite points are rejected (callers drop them).
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise DataError(f"{path}: refusing to write non-finite points to PLY (drop invalid points first)")
    n = pts.shape[0]
    for name, arr, shape in (("colors", colors, (n, 3)), ("normals", normals, (n, 3)),
                             ("confidence", confidence, (n,))):
        if arr is not None and np.shape(arr) != shape:
            raise ValueError(f"{name} must have shape {shape}, got {np.shape(arr)}")
    dtype = _vertex_dtype(normals is not None, colors is not None, confidence is not None)
    vertices = np.empty(n, dtype=dtype)
    vertices["x"], vertices["y"], vertices["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float32)
        vertices["nx"], vertices["ny"], vertices["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    if colors is not None:
        col = np.asarray(colors, dtype=np.uint8)
        vertices["red"], vertices["green"], vertices["blue"] = col[:, 0], col[:, 1], col[:, 2]
    if confidence is not None:
        vertices["confidence"] = np.asarray(confidence, dtype=np.float32)
    header = ["ply", "format ascii 1.0" if ascii else "format binary_little_endian 1.0"]
    header += [f"comment {c}".replace("\n", " ") for c in comments]
    header.append(f"element vertex {n}")
    names = {"<f4": "float", "u1": "uchar"}
    fields = cast("tuple[str, ...]", dtype.names)  # a structured dtype has names
    for name in fields:
        header.append(f"property {names[dtype[name].str.replace('|', '')]} {name}")
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(head)
            if ascii:
                fmts = ["%.9g" if dtype[name].kind == "f" else "%d" for name in fields]
                cols = [vertices[name] for name in fields]
                table = np.column_stack([c.astype(np.float64) for c in cols]) if n else np.zeros((0, len(cols)))
                np.savetxt(fh, table, fmt=" ".join(fmts))
            else:
                fh.write(vertices.tobytes())
    return n
