"""The API's contract: arrays, keywords, errors, Flow against fair, welding and regions."""

from __future__ import annotations

import ast
import pathlib

import numpy as np
import pytest

import willow_fair

CONFORMAL = dict(method="conformal", steps=4, until_converged=False)


def tetrahedron():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    F = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], dtype=np.int64)
    return V, F


# --- arrays -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "V, message",
    [
        (np.zeros((4, 3), dtype=np.float32), r"V must be a float64 array of shape \(n, 3\), got dtype float32"),
        (np.zeros((4, 3), dtype=np.int64), r"V must be a float64 array .* got dtype int64"),
        (np.zeros((4, 2)), r"V must be a float64 array of shape \(n, 3\), got shape \(4, 2\)"),
        (np.zeros(12), r"V must be .* got shape \(12,\)"),
    ],
)
def test_bad_vertices_are_value_errors_naming_V(V, message):
    _, F = tetrahedron()
    with pytest.raises(ValueError, match=message):
        willow_fair.fair(V, F)
    with pytest.raises(ValueError, match=message):
        willow_fair.Flow(V, F)


@pytest.mark.parametrize(
    "F, message",
    [
        (np.zeros((4, 3), dtype=np.float64), r"F must be an int32 or int64 array of shape \(m, 3\) .*got dtype float64"),
        (np.zeros((4, 3), dtype=np.uint8), r"F must be an int32 or int64 .*got dtype uint8"),
        (np.zeros((4, 4), dtype=np.int64), r"F must be an int32 or int64 array of shape \(m, 3\), got shape \(4, 4\)"),
    ],
)
def test_bad_faces_are_value_errors_naming_F(F, message):
    V, _ = tetrahedron()
    with pytest.raises(ValueError, match=message):
        willow_fair.fair(V, F)


def test_mesh_errors_carry_the_library_message():
    V, F = tetrahedron()
    bad = F.copy()
    bad[2, 1] = 7
    with pytest.raises(ValueError, match=r"1 triangles reference vertices out of range \(the mesh has 4 vertices\); first: 2"):
        willow_fair.fair(V, bad)
    bad[2, 1] = -1
    with pytest.raises(ValueError, match=r"F row 2 holds the negative index -1"):
        willow_fair.fair(V, bad)
    nan = V.copy()
    nan[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"non-finite \(NaN or infinite\) coordinates; first: 3"):
        willow_fair.fair(nan, F)
    # Three triangles on the edge 0–1: non-manifold.
    V5 = np.vstack([V, [[0.5, -1.0, 0.2]]])
    F5 = np.vstack([F, [[0, 1, 4]]])
    with pytest.raises(ValueError, match=r"non-manifold"):
        willow_fair.fair(V5, F5)


def test_int32_and_int64_faces_give_the_same_surface(spot):
    V, F = spot
    a = willow_fair.fair(V, F.astype(np.int64), **CONFORMAL)
    b = willow_fair.fair(V, F.astype(np.int32), **CONFORMAL)
    assert np.array_equal(a.vertices, b.vertices)
    assert a.vertices.dtype == np.float64 and a.vertices.shape == V.shape


def test_non_contiguous_arrays_are_accepted(spot):
    V, F = spot
    a = willow_fair.fair(V, F, **CONFORMAL)
    b = willow_fair.fair(np.asfortranarray(V), np.asfortranarray(F), **CONFORMAL)
    assert np.array_equal(a.vertices, b.vertices)


# --- keywords -----------------------------------------------------------------------------


def test_unknown_keywords_are_type_errors_naming_them():
    V, F = tetrahedron()
    with pytest.raises(TypeError, match=r"unknown keywords: speed, taus"):
        willow_fair.fair(V, F, taus=0.1, speed=2)


def test_wrong_types_are_type_errors_naming_the_keyword():
    V, F = tetrahedron()
    with pytest.raises(TypeError, match=r"^tau: invalid type: string"):
        willow_fair.fair(V, F, tau="fast")
    with pytest.raises(TypeError, match=r"^denoise_vertex_iterations: invalid type"):
        willow_fair.fair(V, F, denoise_vertex_iterations=2.5)


def test_invalid_values_are_value_errors_with_the_library_message(spot):
    V, F = spot
    cases = [
        (dict(tau=-1.0), r"invalid parameter `tau`: must be a positive finite number, got -1"),
        (dict(iterations=0), r"invalid parameter `iterations`: must be between 1 and 50"),
        (dict(method="conformal", feature_size=-2.0), r"invalid parameter `feature_size`"),
        (dict(denoise_sigma_r=3.0), r"invalid parameter `denoise.sigma_r`: must be in \(0, 2\]"),
        (dict(regions={"sphere": (0, 0, 0, 0.3)}), r"applies only to method `conformal`.*`denoise` is the default method"),
        (dict(method="conformal", filter_sigma=0.1), r"filter_sigma and filter_k go together"),
        (dict(frame_angle=0.1), r"frame_angle: only with boundary='prescribed'"),
    ]
    for params, message in cases:
        with pytest.raises((ValueError, TypeError), match=message):
            willow_fair.fair(V, F, **params)
    with pytest.raises(ValueError, match=r"^method: expected one of `conformal`, `mcf`"):
        willow_fair.fair(V, F, method="smooth")
    with pytest.raises(ValueError, match=r"tau: must be a finite number, got nan"):
        willow_fair.fair(V, F, tau=float("nan"))


def _stub_keywords(name: str) -> dict:
    stub = pathlib.Path(willow_fair.__file__).with_name("__init__.pyi")
    tree = ast.parse(stub.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef) and node.name == name:
            args = node.args
            return {
                a.arg: ast.literal_eval(d) if not isinstance(d, ast.Tuple) else []
                for a, d in zip(args.kwonlyargs, args.kw_defaults)
            }
    raise AssertionError(f"{name} not in the stub")


def test_the_stubs_docs_and_keywords_agree():
    # Every FlowParams field of the library is a keyword (KEYWORDS comes from the library):
    # the stubs list the same ones with the same defaults, the docstring names each.
    stub = _stub_keywords("fair")
    assert set(stub) == set(willow_fair.KEYWORDS) | {"steps"}
    defaults = willow_fair.defaults()
    for k, v in defaults.items():
        assert stub[k] == v, (k, stub[k], v)
    assert set(stub) - set(defaults) == {"filter", "denoise"}  # the dict forms
    for k in defaults:
        assert f"``{k}``" in willow_fair.__doc__, k
    assert (pathlib.Path(willow_fair.__file__).parent / "py.typed").is_file()
    assert (pathlib.Path(willow_fair.__file__).parent / "_native.pyi").is_file()


def test_defaults_are_the_cli_defaults():
    d = willow_fair.defaults()
    assert d["method"] == "denoise" and d["steps"] == 10 and d["threads"] == 0
    assert d["tau"] == 0.5 and d["preserve"] == "area" and d["until_converged"] is True
    assert d["boundary"] == "auto"


def bumpy_patch(n=16):
    """An open n × n grid over [-1, 1]², a bump in the middle, its border on z = 0."""
    x, y = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(-1, 1, n + 1), indexing="ij")
    z = 0.4 * np.exp(-4 * (x**2 + y**2)) * (1 - x**2) * (1 - y**2)
    V = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    idx = lambda i, j: i * (n + 1) + j  # noqa: E731
    F = []
    for i in range(n):
        for j in range(n):
            F += [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)], [idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]]
    border = (np.abs(V[:, 0]) == 1) | (np.abs(V[:, 1]) == 1)
    return V, np.array(F, dtype=np.int64), border


def test_the_conformal_flow_holds_an_open_border_unless_asked_free():
    V, F, border = bumpy_patch()
    held = willow_fair.fair(V, F, **CONFORMAL)
    assert np.array_equal(held.vertices[border], V[border]), "auto holds the border"
    assert not np.array_equal(held.vertices, V), "and fairs the rest"
    free = willow_fair.fair(V, F, boundary="free", **CONFORMAL)
    moved = np.linalg.norm(free.vertices[border] - V[border], axis=1).max()
    assert moved > 1e-3, f"free: the border moved {moved}"



def chamfered_cylinder(segments=64, step=0.1):
    """A cylinder of radius 1, height 2, both rims chamfered at 45°: four crease rings."""
    profile = [(0.0, 0.0), (0.8, 0.0), (1.0, 0.2), (1.0, 1.8), (0.8, 2.0), (0.0, 2.0)]
    points = []
    for (r0, z0), (r1, z1) in zip(profile, profile[1:]):
        pieces = max(1, int(np.ceil(np.hypot(r1 - r0, z1 - z0) / step)))
        points += [(r0 + (r1 - r0) * k / pieces, z0 + (z1 - z0) * k / pieces) for k in range(pieces)]
    points.append(profile[-1])
    V, rows = [], []
    for r, z in points:
        if r == 0.0:
            rows.append([len(V)])
            V.append((0.0, 0.0, z))
        else:
            rows.append(list(range(len(V), len(V) + segments)))
            a = 2 * np.pi * np.arange(segments) / segments
            V += [(r * np.cos(t), r * np.sin(t), z) for t in a]
    F = []
    at = lambda row, j: row[0] if len(row) == 1 else row[j % segments]  # noqa: E731
    for lower, upper in zip(rows, rows[1:]):
        for j in range(segments):
            a, b, c, d = at(lower, j), at(lower, j + 1), at(upper, j + 1), at(upper, j)
            if a != b:
                F.append((a, b, c))
            if c != d:
                F.append((a, c, d))
    return np.array(V, dtype=np.float64), np.array(F, dtype=np.int64)


def test_feature_angle_holds_a_parts_creases():
    V, F = chamfered_cylinder()
    held = willow_fair.fair(V, F, tau=0.05, **CONFORMAL)
    assert all(m["crease_edges"] == 4 * 64 for m in held.metrics), held.metrics[-1]
    rims = np.isclose(np.hypot(V[:, 0], V[:, 1]), 1.0) & (np.isclose(V[:, 2], 0.2) | np.isclose(V[:, 2], 1.8))
    assert rims.sum() == 2 * 64
    assert np.array_equal(held.vertices[rims], V[rims]), "crease vertices stay"
    assert not np.array_equal(held.vertices, V), "the patches between them are faired"
    across = willow_fair.fair(V, F, tau=0.05, feature_angle="none", **CONFORMAL)
    assert "crease_edges" not in across.metrics[-1]
    assert not np.array_equal(across.vertices[rims], V[rims])
    with pytest.raises(ValueError, match="between 0 and 180"):
        willow_fair.fair(V, F, feature_angle=200.0, **CONFORMAL)
    with pytest.raises(ValueError, match="expected `auto`, `none` or an angle"):
        willow_fair.fair(V, F, feature_angle="sharp", **CONFORMAL)

# --- Flow and fair ------------------------------------------------------------------------


def test_flow_steps_are_the_steps_of_fair(spot):
    V, F = spot
    k = 4
    result = willow_fair.fair(V, F, **CONFORMAL)
    flow = willow_fair.Flow(V, F, **CONFORMAL)
    assert flow.outcome is None and flow.last_metrics["step"] == 0
    steps = []
    while (m := flow.step()) is not None:
        steps.append(m)
        assert np.isfinite(flow.vertices).all()
    assert flow.step() is None  # over, and stays over
    assert len(steps) == len(result.metrics) == k
    assert np.array_equal(flow.vertices, result.vertices)
    assert (flow.outcome, flow.reason) == (result.outcome, result.reason) == (
        "completed", f"ran its {k} steps")
    for a, b in zip(steps, result.metrics):
        a, b = dict(a), dict(b)
        a.pop("step_ms"), b.pop("step_ms")
        assert a == b
    assert result.initial_metrics == flow.initial_metrics
    assert result.metrics[-1]["willmore_energy"] < result.initial_metrics["willmore_energy"]


def test_flow_without_a_step_limit_runs_until_a_rule_stops_it(spot):
    V, F = spot
    flow = willow_fair.Flow(V, F, method="conformal", until_willmore=1.1 * 4 * np.pi)
    taken = list(flow)
    assert flow.outcome == "target_reached", flow.reason
    assert taken[-1]["willmore_energy"] <= 1.1 * 4 * np.pi


def test_default_method_is_denoise_which_leaves_a_clean_mesh(spot):
    V, F = spot
    r = willow_fair.fair(V, F)
    assert r.outcome == "already_fair" and r.metrics == []
    assert np.array_equal(r.vertices, V)


def test_metrics_are_dicts_of_numbers_with_the_cli_names(spot):
    V, F = spot
    r = willow_fair.fair(V, F, method="conformal", steps=2, measure_deviation=True)
    m = r.metrics[0]
    for key in ("step", "willmore_energy", "q_mean", "q_area_mean", "q_p95", "q_max",
                "closure_residual", "eigen_residual", "area", "step_ms", "tau", "rejected",
                "volume", "deviation_max", "deviation_mean", "willmore_energy_vector"):
        assert key in m, key
    assert isinstance(m["step"], int) and isinstance(m["willmore_energy"], float)
    assert "deviation_max" not in willow_fair.fair(V, F, **CONFORMAL).metrics[0]


# --- welding, unused vertices, regions ----------------------------------------------------


def test_split_copies_move_together_and_unused_vertices_stay(spot):
    V, F = spot
    base = willow_fair.fair(V, F, **CONFORMAL).vertices
    # A copy of vertex 0 used by one of its faces (a UV seam), and a vertex no face uses.
    n = len(V)
    V2 = np.vstack([V, V[:1], [[5.0, 6.0, 7.0]]])
    F2 = F.copy()
    face = np.nonzero((F2 == 0).any(axis=1))[0][-1]
    F2[face][F2[face] == 0] = n
    out = willow_fair.fair(V2, F2, **CONFORMAL).vertices
    assert np.array_equal(out[:n], base)
    assert np.array_equal(out[n], out[0])
    assert np.array_equal(out[n + 1], [5.0, 6.0, 7.0])


def test_a_vertex_region_moves_only_its_part(spot):
    V, F = spot
    inside = np.nonzero(np.linalg.norm(V - V[0], axis=1) < 0.25)[0]
    out = willow_fair.fair(V, F, method="conformal", steps=3, regions=inside).vertices
    moved = np.nonzero((out != V).any(axis=1))[0]
    assert len(moved) > 0 and set(moved) <= set(inside)
    sphere = willow_fair.fair(V, F, method="conformal", steps=3,
                              regions=[{"sphere": (*V[0], 0.25)}]).vertices
    assert set(np.nonzero((sphere != V).any(axis=1))[0]) <= set(inside)
    with pytest.raises(ValueError, match=r"regions: vertex 99999 is not a vertex of any face"):
        willow_fair.fair(V, F, method="conformal", regions=[[0, 99999]])
