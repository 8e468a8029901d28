"""The trimesh adapter: ``fair_trimesh(mesh, **params)``.

Imported on first use of ``willow_fair.trimesh``, so ``import willow_fair`` never needs
trimesh (``pip install willow-fair[trimesh]`` brings it).
"""

from __future__ import annotations

from typing import Any

import numpy as np

try:
    import trimesh as _trimesh
except ImportError as e:  # pragma: no cover - the test venv has trimesh
    raise ImportError(
        "willow_fair.trimesh needs trimesh: pip install trimesh (or willow-fair[trimesh])"
    ) from e

from . import fair

__all__ = ["fair_trimesh"]


def fair_trimesh(mesh: "_trimesh.Trimesh", **params: Any) -> "_trimesh.Trimesh":
    """A faired copy of a ``trimesh.Trimesh`` (``fair``'s keywords; its module docs).

    The copy keeps the mesh's faces, visuals (UVs, colours) and metadata, with the faired
    positions; ``copy.metadata["willow_fair"]`` holds the run's ``outcome``, ``reason`` and
    per-step ``metrics``. Vertices trimesh split at UV seams are one vertex of the surface
    (same exact position), so seams stay closed.
    """
    if not isinstance(mesh, _trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    result = fair(
        np.asarray(mesh.vertices, dtype=np.float64),
        np.asarray(mesh.faces, dtype=np.int64),
        **params,
    )
    out = mesh.copy()
    out.vertices = result.vertices
    out.metadata["willow_fair"] = {
        "outcome": result.outcome,
        "reason": result.reason,
        "metrics": result.metrics,
    }
    return out
