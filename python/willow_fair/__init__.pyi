# Type stubs of willow_fair (docstrings and units: __init__.py, docs/python.md). The keywords of
# fair and Flow are listed one by one for editors and type checkers; tests/test_api.py checks
# that they are exactly willow_fair.KEYWORDS.
import os
from typing import Any, Dict, Iterator, List, Literal, Mapping, NamedTuple, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

__version__: str
KEYWORDS: List[str]

class FlowError(RuntimeError): ...

Vertices = npt.NDArray[np.float64]
Faces = Union[npt.NDArray[np.int32], npt.NDArray[np.int64]]
PathLike = Union[str, os.PathLike[str]]
Method = Literal["denoise", "conformal", "mcf", "cmcf", "bilaplacian", "taubin"]
Region = Union[Mapping[str, Any], Sequence[int], npt.NDArray[np.integer[Any]]]

def defaults() -> Dict[str, Any]: ...

class Result:
    vertices: Vertices
    outcome: str
    reason: str
    metrics: List[Dict[str, Any]]
    initial_metrics: Dict[str, Any]

class Flow:
    def __init__(
        self,
        V: Vertices,
        F: Faces,
        *,
        steps: Optional[int] = None,
        method: Method = "denoise",
        tau: float = 0.5,
        iterations: int = 1,
        exactness: bool = True,
        mobius_balancing: bool = False,
        filter: Optional[Mapping[str, float]] = None,
        filter_sigma: Optional[float] = None,
        filter_k: Optional[int] = None,
        boundary: Union[Literal["auto", "free", "fixed", "cmc", "prescribed"], Mapping[str, Any]] = "auto",
        frame_angle: float = 0.0,
        boundary_rotation: Union[float, Sequence[float], Mapping[int, float]] = 0.0,
        boundary_axis: Union[Literal["tangent"], Sequence[float]] = "tangent",
        safeguard: bool = True,
        threads: int = 0,
        precision: Literal["auto", "double", "mixed"] = "auto",
        regions: Union[Region, Sequence[Region]] = (),
        seam: Literal["smooth", "fixed"] = "smooth",
        preserve: Literal["area", "volume", "none"] = "area",
        until_willmore: Optional[float] = None,
        until_converged: bool = True,
        max_deviation: Optional[float] = None,
        measure_deviation: bool = False,
        feature_size: Optional[float] = None,
        falloff: Optional[float] = None,
        feature_angle: Union[str, float] = "auto",
        denoise: Optional[Mapping[str, Any]] = None,
        denoise_iterations: Optional[int] = None,
        denoise_vertex_iterations: int = 10,
        denoise_sigma_r: float = 0.35,
        denoise_radius: float = 2.0,
        denoise_guided: bool = True,
    ) -> None: ...
    def step(self) -> Optional[Dict[str, Any]]: ...
    def run(self) -> List[Dict[str, Any]]: ...
    def __iter__(self) -> Iterator[Dict[str, Any]]: ...
    @property
    def vertices(self) -> Vertices: ...
    @property
    def outcome(self) -> Optional[str]: ...
    @property
    def reason(self) -> Optional[str]: ...
    @property
    def initial_metrics(self) -> Dict[str, Any]: ...
    @property
    def last_metrics(self) -> Dict[str, Any]: ...

def fair(
    V: Vertices,
    F: Faces,
    *,
    steps: int = 10,
    method: Method = "denoise",
    tau: float = 0.5,
    iterations: int = 1,
    exactness: bool = True,
    mobius_balancing: bool = False,
    filter: Optional[Mapping[str, float]] = None,
    filter_sigma: Optional[float] = None,
    filter_k: Optional[int] = None,
    boundary: Union[Literal["auto", "free", "fixed", "cmc", "prescribed"], Mapping[str, Any]] = "auto",
    frame_angle: float = 0.0,
    boundary_rotation: Union[float, Sequence[float], Mapping[int, float]] = 0.0,
    boundary_axis: Union[Literal["tangent"], Sequence[float]] = "tangent",
    safeguard: bool = True,
    threads: int = 0,
    precision: Literal["auto", "double", "mixed"] = "auto",
    regions: Union[Region, Sequence[Region]] = (),
    seam: Literal["smooth", "fixed"] = "smooth",
    preserve: Literal["area", "volume", "none"] = "area",
    until_willmore: Optional[float] = None,
    until_converged: bool = True,
    max_deviation: Optional[float] = None,
    measure_deviation: bool = False,
    feature_size: Optional[float] = None,
    falloff: Optional[float] = None,
    feature_angle: Union[str, float] = "auto",
    denoise: Optional[Mapping[str, Any]] = None,
    denoise_iterations: Optional[int] = None,
    denoise_vertex_iterations: int = 10,
    denoise_sigma_r: float = 0.35,
    denoise_radius: float = 2.0,
    denoise_guided: bool = True,
) -> Result: ...

class Filled(NamedTuple):
    vertices: npt.NDArray[np.float64]
    faces: npt.NDArray[np.int64]
    filled: int
    left_open: List[int]

def fill_holes(V: Vertices, F: Faces, *, max: Union[None, int, float] = None) -> Filled: ...

class Mesh(NamedTuple):
    vertices: Vertices
    faces: npt.NDArray[np.int64]

def read(path: PathLike) -> Mesh: ...
def write(path: PathLike, V: Vertices, F: Faces, *, like: Optional[PathLike] = None) -> None: ...
