"""read/write: every format, the file's numbering kept, `like=` keeping the file."""

from __future__ import annotations

import numpy as np
import pytest

import willow_fair
from conftest import SPOT, shared

FORMATS = ["obj", "gltf", "glb", "stl", "ply", "off"]
FLOAT32 = {"gltf", "glb", "stl"}


def same(a, b, ext):
    if ext in FLOAT32:
        return np.array_equal(a.astype(np.float32), b.astype(np.float32))
    return np.array_equal(a, b)


def moved(V):
    # A new surface in the same numbering (what a flow gives).
    return V * 1.25 + np.array([0.5, -0.25, 2.0])


@pytest.mark.parametrize("ext", FORMATS)
def test_round_trip_keeps_the_numbering(tmp_path, spot, ext):
    V, F = spot
    first = tmp_path / f"new.{ext}"
    willow_fair.write(first, V, F)
    V1, F1 = willow_fair.read(first)
    assert V1.dtype == np.float64 and F1.dtype == np.int64
    if ext == "stl":
        # STL has no shared vertices: its numbering is its distinct corners in order of first
        # appearance, which the same triangles give again.
        assert np.array_equal(V1[F1].astype(np.float32), V[F].astype(np.float32))
    else:
        assert np.array_equal(F1, F) and same(V1, V, ext)
    # Written back like itself: the numbering (and the file) kept, the positions new.
    second = tmp_path / f"like.{ext}"
    V2 = moved(V1)
    willow_fair.write(second, V2, F1, like=first)
    V3, F3 = willow_fair.read(second)
    assert np.array_equal(F3, F1) and same(V3, V2, ext)


def test_like_keeps_an_obj_file_as_it_was(tmp_path, spot):
    V, F = spot
    out = tmp_path / "spot.obj"
    willow_fair.write(out, moved(V), F, like=SPOT)
    before, after = SPOT.read_text().splitlines(), out.read_text().splitlines()
    assert len(before) == len(after)
    kept = [a == b for a, b in zip(before, after) if not a.startswith(("v ", "vn "))]
    assert all(kept)  # vt, f, g, mtllib lines byte for byte


def test_obj_numbering_counts_unused_v_lines(tmp_path):
    text = SPOT.read_text() + "v 9 8 7\n"
    path = tmp_path / "unused.obj"
    path.write_text(text)
    V, F = willow_fair.read(path)
    assert len(V) == 2931 and np.array_equal(V[-1], [9.0, 8.0, 7.0])
    r = willow_fair.fair(V, F, method="conformal", steps=2)
    assert np.array_equal(r.vertices[-1], [9.0, 8.0, 7.0])
    out = tmp_path / "out.obj"
    willow_fair.write(out, r.vertices, F, like=path)
    V2, _ = willow_fair.read(out)
    assert np.array_equal(V2, r.vertices)


def test_gltf_with_its_document_round_trips(tmp_path):
    duck = shared("Duck.glb")
    V, F = willow_fair.read(duck)
    r = willow_fair.fair(V, F, method="conformal", steps=2)
    out = tmp_path / "duck.glb"
    willow_fair.write(out, r.vertices, F, like=duck)
    V2, F2 = willow_fair.read(out)
    assert np.array_equal(F2, F)
    # World space read back through the node transform the document keeps (float32 local).
    assert np.abs(V2 - r.vertices).max() <= 1e-5 * np.abs(r.vertices).max()


def test_io_errors(tmp_path, spot):
    V, F = spot
    with pytest.raises(FileNotFoundError, match="cannot read"):
        willow_fair.read(tmp_path / "missing.obj")
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(ValueError, match="bad.obj"):
        willow_fair.read(bad)
    with pytest.raises(ValueError, match=r"unknown extension"):
        willow_fair.write(tmp_path / "x.xyz", V, F)
    with pytest.raises(ValueError, match=r"F is not the faces of like="):
        willow_fair.write(tmp_path / "x.obj", V, F[::-1].copy(), like=SPOT)
    with pytest.raises(ValueError, match=r"V has 3 rows but like="):
        willow_fair.write(tmp_path / "x.obj", V[:3].copy(), F, like=SPOT)
