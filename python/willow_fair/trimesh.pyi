from typing import Any

import trimesh

def fair_trimesh(mesh: trimesh.Trimesh, **params: Any) -> trimesh.Trimesh: ...
