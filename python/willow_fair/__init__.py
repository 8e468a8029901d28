"""willow-fair: mesh fairing by conformal Willmore flow, on numpy arrays.

Crane, Pinkall and Schröder, "Robust Fairing via Conformal Curvature Flow" (SIGGRAPH 2013),
the classic flows it is compared with, and feature-preserving denoising (guided mesh normal
filtering), from the Rust library ``willow``:

- ``fair(V, F, **params) -> Result``: a whole run, as ``willow fair in.obj -o out.obj``;
- ``Flow(V, F, **params)``: the same flow one ``step()`` at a time, its factorization kept;
- ``fill_holes(V, F, max=None) -> Filled``: holes closed by fair patches that meet the
  surface smoothly (``willow fair --fill-holes``), new vertices and faces appended;
- ``read(path)`` / ``write(path, V, F, like=path)``: OBJ, glTF, GLB, STL, PLY and OFF, in the
  file's own vertex numbering;
- ``willow_fair.trimesh.fair_trimesh(mesh, **params)``: a trimesh adapter (imported on first
  use).

Arrays are as trimesh and libigl hold them: ``V`` float64 of shape (n, 3), ``F`` int32 or
int64 of shape (m, 3), 0-based. Vertices at the same exact position are one vertex of the
surface (as when Willow reads a file: UV seams stay closed), and vertices no face uses stay
where they are. The GIL is released while a flow builds and steps.

Keywords (units and defaults; docs/python.md has the whole table). The default method is the
CLI's, ``denoise``: ``method="conformal"`` is the paper's Willmore flow.

- ``steps`` (int, 10 for ``fair``, no limit for ``Flow``): steps at most; the run stops
  earlier when W stops falling (unless ``until_converged=False``) or another rule applies.
- ``method`` ("denoise"): "denoise", "conformal", "mcf", "cmcf", "bilaplacian", "taubin".
- ``tau`` (0.5): time step; conformal: the paper's τ (stable below 1); mcf/cmcf unitless
  (step τ·area/4π); bilaplacian τ·(area/4π)²; taubin λ = τ.
- ``iterations`` (1): inverse power iterations per step (1–50).
- ``exactness`` (True), ``mobius_balancing`` (False), ``safeguard`` (True): booleans.
- ``filter_sigma`` / ``filter_k`` (None): the spectral filter (unitless σ, k in 0..3), together.
- ``boundary`` ("free"): "free", "fixed", "cmc" or "prescribed" with ``frame_angle`` (radians,
  0), ``boundary_rotation`` (radians: one angle, a list per boundary loop, or a dict
  vertex → angle) and ``boundary_axis`` ("tangent" or (x, y, z)).
- ``threads`` (0): threads of the factorizations, 0 every core; results are bitwise the same.
- ``precision`` ("auto"): "auto", "double" or "mixed" (the conformal flow's Dirac factor).
- ``regions`` ([]): only these move: a dict ``{"sphere": (x, y, z, r)}``,
  ``{"box": (xmin, ymin, zmin, xmax, ymax, zmax)}``, ``{"vertices": indices}`` (the caller's
  numbering), an index array, or a list of them (their union); model units.
- ``seam`` ("smooth"): "smooth" or "fixed", how a region meets the rest.
- ``preserve`` ("area"): "area", "volume" or "none", kept per component after every step.
- ``until_willmore`` (None): stop once W is at most this (4π for a round sphere).
- ``until_converged`` (True): stop once W has stopped falling (the CLI's ``--all-steps`` off).
- ``max_deviation`` (None, model units): stop before a step moves the surface further.
- ``measure_deviation`` (False): report ``deviation_max``/``deviation_mean`` every step.
- ``feature_size`` (None, model units): remove the detail below this length (conformal).
- ``falloff`` (None, model units): blend a region's motion to zero over this width.
- ``feature_angle`` ("auto"): sharp edges kept sharp: "auto" (30°, only on parts with long
  chains of sharp edges), "none", or an angle in degrees; the conformal flow holds them
  (metrics' ``crease_edges`` counts them).
- ``denoise_iterations`` (None: read off the mesh), ``denoise_vertex_iterations`` (10),
  ``denoise_sigma_r`` (0.35, unit-normal difference), ``denoise_radius`` (2.0, mean
  centroid distances), ``denoise_guided`` (True): method "denoise"'s filter.

An unknown keyword or a value of the wrong type is a TypeError naming it; a value the library
refuses is a ValueError with the library's message, as is a mesh it refuses (non-manifold,
NaN, an index out of range). A flow that fails while stepping raises ``FlowError``.
"""

from __future__ import annotations

import importlib
import numbers
import os
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, NamedTuple, Optional, Union

import numpy as np

from . import _native
from . import _params

__all__ = [
    "fair",
    "fill_holes",
    "Filled",
    "Flow",
    "Result",
    "Mesh",
    "read",
    "write",
    "defaults",
    "FlowError",
    "KEYWORDS",
    "__version__",
]

__version__: str = _native.__version__
FlowError = _native.FlowError
#: Every keyword of ``fair`` and ``Flow`` (besides ``steps``).
KEYWORDS: List[str] = _params.keywords()

PathLike = Union[str, "os.PathLike[str]"]


def defaults() -> Dict[str, Any]:
    """Each keyword's default (``steps`` is ``fair``'s; a ``Flow`` has no limit by default)."""
    return _params.defaults()


def _vertices(V: Any, name: str = "V") -> np.ndarray:
    a = np.asarray(V)
    if a.dtype != np.float64:
        raise ValueError(f"{name} must be a float64 array of shape (n, 3), got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be a float64 array of shape (n, 3), got shape {a.shape}")
    return np.ascontiguousarray(a)


def _faces(F: Any, name: str = "F") -> np.ndarray:
    a = np.asarray(F)
    if a.dtype != np.int32 and a.dtype != np.int64:
        raise ValueError(
            f"{name} must be an int32 or int64 array of shape (m, 3) of 0-based vertex "
            f"indices, got dtype {a.dtype}"
        )
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(
            f"{name} must be an int32 or int64 array of shape (m, 3), got shape {a.shape}"
        )
    return np.ascontiguousarray(a)


@dataclass(frozen=True)
class Result:
    """What ``fair`` returns.

    ``vertices``: float64 (n, 3), the faired surface in the caller's numbering (model units);
    ``outcome``: why the run ended, the CLI's names: "completed", "converged", "stalled",
    "target_reached", "max_deviation", "no_progress", "feature_scale_reached", "already_fair";
    ``reason``: the sentence that says why; ``metrics``: one dict per step taken, with the keys
    of ``willow fair --json`` (``step``, ``willmore_energy``, ``q_mean``, ..., ``step_ms``);
    ``initial_metrics``: the same for the input (step 0).
    """

    vertices: np.ndarray
    outcome: str
    reason: str
    metrics: List[Dict[str, Any]] = field(repr=False)
    initial_metrics: Dict[str, Any] = field(repr=False)

    def __repr__(self) -> str:
        return (
            f"Result(outcome={self.outcome!r}, steps={len(self.metrics)}, "
            f"vertices=<{self.vertices.shape[0]}x3>, reason={self.reason!r})"
        )


class Flow:
    """A flow on one mesh, stepped by the caller; its factorizations are kept between steps.

    ``Flow(V, F, **params)`` takes the keywords of ``fair`` (module docs); ``steps`` is at
    most that many steps (default: no limit). The library's stopping rules apply as in
    ``fair``: ``step()`` returns one step's metrics dict, or None once the run is over, and
    then ``outcome`` and ``reason`` say why. ``vertices`` is the current surface, a new array
    on every read. k calls of ``step()`` take exactly the steps of ``fair(V, F, steps=k)``.
    Each call releases the GIL; two threads stepping one Flow take turns.
    """

    def __init__(self, V: Any, F: Any, *, steps: Optional[int] = None, **params: Any) -> None:
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int)
                                  or steps < 0):
            raise ValueError(f"steps must be an int ≥ 0 or None, got {steps!r}")
        self._native = _native.Flow(_vertices(V), _faces(F), _params.to_json(params), steps)

    def step(self) -> Optional[Dict[str, Any]]:
        """Take one step: its metrics dict, or None once the run is over."""
        return self._native.step()

    def run(self) -> List[Dict[str, Any]]:
        """Take every remaining step (GIL released throughout): their metrics dicts."""
        return self._native.run()

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        """The metrics of each further step, until the run is over."""
        while True:
            m = self.step()
            if m is None:
                return
            yield m

    @property
    def vertices(self) -> np.ndarray:
        """The current surface, float64 (n, 3), in the caller's numbering (a new array)."""
        return self._native.vertices

    @property
    def outcome(self) -> Optional[str]:
        """Why the run ended (``Result.outcome``'s names); None while it goes on."""
        return self._native.outcome

    @property
    def reason(self) -> Optional[str]:
        """The sentence that says why the run ended; None while it goes on."""
        return self._native.reason

    @property
    def initial_metrics(self) -> Dict[str, Any]:
        """The metrics of the input surface (step 0)."""
        return self._native.initial_metrics

    @property
    def last_metrics(self) -> Dict[str, Any]:
        """The metrics of the surface the flow is on (step 0 before any step)."""
        return self._native.last_metrics


def fair(V: Any, F: Any, *, steps: int = _params.STEPS, **params: Any) -> Result:
    """Fair a mesh: the whole run of ``willow fair`` on arrays (module docs: the keywords).

    ``V`` float64 (n, 3), ``F`` int32/int64 (m, 3), 0-based. ``fair(V, F)`` is
    ``willow fair in.obj -o out.obj``: method "denoise", at most 10 steps, every core.
    The GIL is released for the whole run.
    """
    flow = Flow(V, F, steps=steps, **params)
    metrics = flow.run()
    outcome, reason = flow.outcome, flow.reason
    assert outcome is not None and reason is not None  # run() returns once the run is over
    return Result(flow.vertices, outcome, reason, metrics, flow.initial_metrics)


class Filled(NamedTuple):
    """``fill_holes``' result: ``V, F, filled, left_open = fill_holes(V, F)``."""

    vertices: np.ndarray
    faces: np.ndarray
    #: Holes closed.
    filled: int
    #: The boundary vertex counts of the loops ``max`` left open.
    left_open: List[int]


def fill_holes(V: Any, F: Any, *, max: Union[None, int, float] = None) -> Filled:
    """Close the holes of a mesh, as ``willow fair --fill-holes [MAX]`` does.

    Every boundary loop up to ``max`` (``None``: all; an int: at most that many boundary
    vertices, at least 3; a float: a loop whose bounding box diagonal is at most that, model
    units) is triangulated (Liepa's minimal dihedral rule), refined to the surrounding edge
    length and faired: a thin-plate start, then the conformal flow with the surface's tangent
    planes held along the loop, so the patch meets the surface G1. The caller's vertices keep
    their positions and numbers and its faces their order; the patches' vertices and faces
    are appended. The GIL is released while it runs.
    """
    if max is None:
        size = "all"
    elif isinstance(max, bool) or not isinstance(max, numbers.Real):
        raise TypeError(f"max must be None, an int or a float, got {type(max).__name__}")
    elif isinstance(max, numbers.Integral):
        size = str(int(max))
    else:
        # A float is a length even when it is whole (3.0): repr keeps the point or exponent.
        size = repr(float(max))
    V2, F2, filled, left_open = _native.fill_holes(_vertices(V), _faces(F), size)
    return Filled(V2, F2, filled, list(left_open))


class Mesh(NamedTuple):
    """``read``'s result: ``V, F = read(path)``."""

    vertices: np.ndarray
    faces: np.ndarray


def read(path: PathLike) -> Mesh:
    """Read OBJ, glTF, GLB, STL, PLY or OFF (by extension, else by content).

    Returns ``(V, F)``: float64 (n, 3) positions in world space (glTF node transforms applied)
    and int64 (m, 3) faces, in the file's own numbering: OBJ ``v`` lines (unused ones too),
    glTF accessor vertices, PLY/OFF vertex records, STL's distinct corners in order of first
    appearance. Faces are wound like the oriented surface. A file the library refuses (or one
    that needs repair: ``willow fair --repair`` does it) is a ValueError with the library's
    message in the file's numbering; an unreadable one an OSError.
    """
    V, F = _native.read(os.fspath(path))
    return Mesh(V, F)


def write(path: PathLike, V: Any, F: Any, *, like: Optional[PathLike] = None) -> None:
    """Write a mesh in the format of ``path``'s extension.

    With ``like`` (a file ``read`` read ``V`` and ``F`` from), that file is written back with
    ``V`` as its positions: UVs, normals (recomputed), materials, groups and, for OBJ, the text
    itself are kept, and so is its numbering. Without, a new file of these arrays, in their
    numbering where the format has one (STL has none). glTF/GLB and STL store float32.
    """
    _native.write(
        os.fspath(path),
        _vertices(V),
        _faces(F),
        None if like is None else os.fspath(like),
    )


def __getattr__(name: str) -> Any:
    # `willow_fair.trimesh` is imported on first use: trimesh is an optional dependency.
    if name == "trimesh":
        return importlib.import_module(".trimesh", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
