"""Keywords to the library's parameters.

Every field of the library's ``FlowParams`` is a keyword of its own name; the nested ones are
flattened as the CLI flattens them (``denoise_sigma_r`` for ``--denoise-sigma-r``, ``filter_k``
for ``--filter-k``), and a prescribed boundary takes the CLI's ``frame_angle``,
``boundary_rotation`` and ``boundary_axis``. The keywords become the library's own JSON form of
``FlowParams`` (a serde type), which the native module parses: names, parsing and any field a
later version of the library adds come from the library itself.
"""

from __future__ import annotations

import json
import math
import numbers
from typing import Any, Dict, List

import numpy as np

from . import _native

# The library's FlowParams::default(), field by field (its JSON form).
LIBRARY_DEFAULTS: Dict[str, Any] = json.loads(_native.flow_params_defaults())
# The fields of the nested parameters: {"denoise": [...], "filter": ["sigma", "k"]}.
NESTED: Dict[str, List[str]] = json.loads(_native.nested_fields())
# Where the CLI's defaults differ from the library's: `fair(V, F)` is `willow fair in -o out`.
CLI_DEFAULTS: Dict[str, Any] = {"method": "denoise", "threads": 0, "boundary": "auto"}
# The CLI's prescribed-boundary flags, gathered into `boundary`.
BOUNDARY_KEYWORDS = ("frame_angle", "boundary_rotation", "boundary_axis")
# `fair`'s step count, the CLI's `--steps` default (a `Flow` has no limit unless given one).
STEPS = 10


def keywords() -> List[str]:
    """Every keyword `fair` and `Flow` accept besides `steps`, in the library's field order."""
    names: List[str] = []
    for field in LIBRARY_DEFAULTS:
        names.append(field)
        names.extend(f"{field}_{sub}" for sub in NESTED.get(field, []))
        if field == "boundary":
            names.extend(BOUNDARY_KEYWORDS)
    return names


def defaults() -> Dict[str, Any]:
    """Each keyword's default, flattened as the keywords are (the dict forms left out)."""
    out: Dict[str, Any] = {"steps": STEPS}
    for field, value in LIBRARY_DEFAULTS.items():
        value = CLI_DEFAULTS.get(field, value)
        if field in NESTED:
            inner = value if isinstance(value, dict) else {}
            for sub in NESTED[field]:
                out[f"{field}_{sub}"] = inner.get(sub)
            continue
        out[field] = value
        if field == "boundary":
            out.update(frame_angle=0.0, boundary_rotation=0.0, boundary_axis="tangent")
    return out


def _plain(value: Any) -> Any:
    """numpy scalars and arrays as the Python numbers and lists JSON holds."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _finite(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return True


def _is_index(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def _region(r: Any) -> Any:
    """One region in the library's form; shorthands: an index list, a 4- or 6-number tuple."""
    if isinstance(r, dict) and len(r) == 1:
        (kind, body), = r.items()
        if kind == "sphere" and isinstance(body, (list, tuple)) and len(body) == 4:
            return {"sphere": {"center": list(body[:3]), "radius": body[3]}}
        if kind == "box" and isinstance(body, (list, tuple)) and len(body) == 6:
            return {"box": {"min": list(body[:3]), "max": list(body[3:])}}
        return r
    if isinstance(r, list) and all(_is_index(x) for x in r):
        return {"vertices": r}
    return r


def _regions(value: Any) -> List[Any]:
    value = _plain(value)
    if isinstance(value, dict):
        return [_region(value)]
    if isinstance(value, list) and value and all(_is_index(x) for x in value):
        return [{"vertices": value}]
    if isinstance(value, list):
        return [_region(r) for r in value]
    raise TypeError(
        "regions must be a region (a dict such as {'sphere': (x, y, z, r)}, or an array of "
        f"vertex indices) or a list of regions, got {type(value).__name__}"
    )


def _rotation(value: Any) -> Any:
    if isinstance(value, dict):
        return {"per_vertex": [[int(v), a] for v, a in value.items()]}
    if isinstance(value, list):
        return {"per_loop": value}
    return {"uniform": value}


def _axis(value: Any) -> Any:
    if isinstance(value, str) and value.lower() == "tangent":
        return "tangent"
    if isinstance(value, list) and len(value) == 3:
        return {"fixed": value}
    raise ValueError(f"must be 'tangent' or three numbers (x, y, z), got {value!r}")


def _fragment(keyword: str, value: Any) -> Dict[str, Any]:
    """The piece of the library's JSON form one keyword gives."""
    value = _plain(value)
    if keyword == "regions":
        return {"regions": _regions(value)}
    if keyword == "boundary" and isinstance(value, str) and value.lower() == "prescribed":
        return {"boundary": {"prescribed": {}}}
    if keyword in BOUNDARY_KEYWORDS:
        field = {"frame_angle": "frame_angle", "boundary_rotation": "angles",
                 "boundary_axis": "axis"}[keyword]
        convert = {"frame_angle": lambda v: v, "boundary_rotation": _rotation,
                   "boundary_axis": _axis}[keyword]
        return {"boundary": {"prescribed": {field: convert(value)}}}
    for field, subs in NESTED.items():
        prefix = field + "_"
        if keyword.startswith(prefix) and keyword[len(prefix):] in subs:
            return {field: {keyword[len(prefix):]: value}}
    return {keyword: value}


def _merge(into: Dict[str, Any], piece: Dict[str, Any], keyword: str) -> None:
    for key, value in piece.items():
        if isinstance(value, dict) and isinstance(into.get(key), dict):
            _merge(into[key], value, keyword)
        elif key in into:
            raise TypeError(f"{keyword}: {key!r} is given twice")
        else:
            into[key] = value


def to_json(params: Dict[str, Any]) -> str:
    """The JSON object of FlowParams fields for these keywords, the CLI's defaults under them.

    Raises TypeError for an unknown keyword or a value of the wrong type, ValueError for a
    value the library cannot parse, each naming its keyword. Values are checked by the library
    (``FlowParams::validate``) when the flow is built.
    """
    known = set(keywords())
    unknown = sorted(k for k in params if k not in known)
    if unknown:
        raise TypeError(
            f"unknown keyword{'s' if len(unknown) > 1 else ''}: {', '.join(unknown)} "
            f"(willow_fair.KEYWORDS lists them)"
        )
    given = [k for k in BOUNDARY_KEYWORDS if k in params]
    boundary = _plain(params.get("boundary"))
    prescribed = (isinstance(boundary, str) and boundary.lower() == "prescribed") or (
        isinstance(boundary, dict) and "prescribed" in boundary)
    if given and not prescribed:
        raise ValueError(f"{', '.join(given)}: only with boundary='prescribed'")
    out: Dict[str, Any] = {k: v for k, v in CLI_DEFAULTS.items() if k not in params}
    for keyword, value in params.items():
        piece = _fragment(keyword, value)
        if not _finite(piece):
            raise ValueError(f"{keyword}: must be a finite number, got {value!r}")
        if keyword not in ("filter_sigma", "filter_k"):  # a pair: checked together below
            try:
                _native.check_params(json.dumps(piece))
            except (TypeError, ValueError) as e:
                raise type(e)(f"{keyword}: {e}") from None
        _merge(out, piece, keyword)
    filt = out.get("filter")
    if isinstance(filt, dict) and set(filt) != set(NESTED["filter"]):
        raise TypeError("filter_sigma and filter_k go together (the spectral filter needs both)")
    text = json.dumps(out)
    _native.check_params(text)
    return text
