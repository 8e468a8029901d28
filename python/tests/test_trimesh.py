"""The trimesh adapter, imported lazily."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import trimesh

import willow_fair
from conftest import SPOT

PARAMS = dict(method="conformal", steps=3)


def test_import_willow_fair_does_not_import_trimesh():
    code = "import sys, willow_fair; assert 'trimesh' not in sys.modules; " \
           "willow_fair.trimesh.fair_trimesh; assert 'trimesh' in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_fair_trimesh_is_fair_on_the_same_surface(spot):
    mesh = trimesh.load(SPOT, process=False)
    out = willow_fair.trimesh.fair_trimesh(mesh, **PARAMS)
    assert isinstance(out, trimesh.Trimesh) and out is not mesh
    assert np.array_equal(out.faces, mesh.faces)
    assert np.array_equal(mesh.vertices, trimesh.load(SPOT, process=False).vertices)
    info = out.metadata["willow_fair"]
    assert info["outcome"] == "completed" and len(info["metrics"]) == 3
    # trimesh splits vertices at UV seams; the surface is welded as Willow welds the file, so
    # each copy lands where Willow's own read of the file puts that vertex.
    V, F = spot
    ours = willow_fair.fair(V, F, **PARAMS).vertices
    where = {tuple(p): i for i, p in enumerate(V)}
    index = np.array([where[tuple(p)] for p in np.asarray(mesh.vertices)])
    assert np.array_equal(np.asarray(out.vertices), ours[index])
