#!/usr/bin/env python3
"""Reference hole filler: CGAL's triangulate_refine_and_fair_hole on every boundary loop.

The project runs this script to pin CGAL's figures (holes found, holes filled, vertices added,
time) for the comparison with Willow's own hole filler. It is a reference tool, not part of
the library or the service, and nothing in CI depends on it.

Usage:
    python cgal-fill-holes.py IN.obj|IN.off OUT.obj [--repeat N]

It reads a polygon mesh (OBJ `v`/`f` lines, or OFF), finds every boundary loop, and fills each
one with CGAL::Polygon_mesh_processing::triangulate_refine_and_fair_hole with CGAL's default
parameters, as CGAL's `hole_filling_example` calls it (density_control_factor sqrt(2),
fairing_continuity 1, Delaunay-based hole triangulation). It writes OUT.obj with the input's
vertices first, in their input order and with their input coordinates (unreferenced vertices
included), then the new vertices; the input's faces come first, then the patch faces. It prints
one JSON line to stdout:

    {"holes": n, "filled": k, "new_vertices": m, "seconds": t}

`seconds` is the wall time of the filling calls only (no file I/O, no mesh building, no
boundary search); with `--repeat N` the whole fill runs N times on a fresh copy of the input
and the best time is printed. Warnings (loops CGAL left open, runs that disagree) go to stderr.

Dependency: CGAL's SWIG bindings from PyPI (the `cgal` package, GPL-3.0-or-later; they wrap
CGAL 6.0.1 for Polyhedron_3 with the EPICK kernel). Install them into a virtualenv with

    python3 -m pip install cgal==6.0.1.post202410241521 numpy==2.4.6

or run scripts/cgal-fill-holes-setup.sh, which makes the venv and prints its python. The
bindings' wrapper returns nothing, so whether CGAL's fairing step succeeded for a hole is not
visible here: a hole counts as filled when its boundary loop is closed after the call.
"""

import argparse
import json
import sys
import time


def read_mesh(path):
    """Returns (points, faces): points as float triples, faces as lists of 0-based indices."""
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        text = fh.read()
    if path.lower().endswith(".off"):
        return read_off(text, path)
    return read_obj(text, path)


def read_obj(text, path):
    points, faces = [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            points.append((float(parts[1]), float(parts[2]), float(parts[3])))
        elif parts[0] == "f":
            face = []
            for tok in parts[1:]:
                i = int(tok.split("/")[0])
                i = i - 1 if i > 0 else len(points) + i  # OBJ: 1-based, negatives are relative
                if not 0 <= i < len(points):
                    sys.exit(f"{path}:{lineno}: face index {tok} out of range")
                face.append(i)
            faces.append(face)
    return points, faces


def read_off(text, path):
    tokens = []
    for line in text.splitlines():
        line = line.split("#", 1)[0]
        tokens.extend(line.split())
    if not tokens or not tokens[0].endswith("OFF"):
        sys.exit(f"{path}: not an OFF file")
    if tokens[0] != "OFF":
        sys.exit(f"{path}: only plain OFF is read, not {tokens[0]}")
    pos = 1
    nv, nf = int(tokens[pos]), int(tokens[pos + 1])
    pos += 3
    points = []
    for _ in range(nv):
        points.append((float(tokens[pos]), float(tokens[pos + 1]), float(tokens[pos + 2])))
        pos += 3
    faces = []
    for _ in range(nf):
        k = int(tokens[pos])
        face = [int(t) for t in tokens[pos + 1:pos + 1 + k]]
        pos += 1 + k
        if any(not 0 <= i < nv for i in face):
            sys.exit(f"{path}: face index out of range")
        faces.append(face)
    if pos != len(tokens):
        sys.exit(f"{path}: trailing data after the faces (coloured faces are not read)")
    return points, faces


def check_manifold(faces, path):
    """CGAL's soup-to-mesh conversion needs an oriented manifold mesh: refuse anything else."""
    directed = set()
    for f in faces:
        if len(f) < 3 or len(set(f)) != len(f):
            sys.exit(f"{path}: degenerate face {f}")
        for a, b in zip(f, f[1:] + f[:1]):
            if (a, b) in directed:
                sys.exit(f"{path}: edge {a}-{b} used twice in one direction "
                         "(non-manifold or inconsistently oriented)")
            directed.add((a, b))
    # Around each vertex the faces must form one fan: link the corner edges (prev -> next)
    # and count the pieces.
    links = {}
    for f in faces:
        n = len(f)
        for k in range(n):
            links.setdefault(f[k], []).append((f[k - 1], f[(k + 1) % n]))
    for v, edges in links.items():
        parent = {}

        def find(x):
            while parent.setdefault(x, x) != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for a, b in edges:
            parent[find(a)] = find(b)
        if len({find(x) for x in parent}) != 1:
            sys.exit(f"{path}: vertex {v + 1} is non-manifold (its faces form several fans)")


def build_polyhedron(points, faces, cgal):
    PMP, Polyhedron_3, Point_3 = cgal
    pts = PMP.Point_3_Vector()
    pts.reserve(len(points))
    for x, y, z in points:
        pts.append(Point_3(x, y, z))
    polys = PMP.Polygon_Vector()
    for f in faces:
        ints = PMP.Int_Vector()
        for i in f:
            ints.append(i)
        polys.append(ints)
    P = Polyhedron_3()
    PMP.polygon_soup_to_polygon_mesh(pts, polys, P)
    if P.size_of_vertices() != len(points) or P.size_of_facets() != len(faces):
        sys.exit(f"CGAL built {P.size_of_vertices()} vertices and {P.size_of_facets()} faces "
                 f"from {len(points)} and {len(faces)}")
    # Tag every vertex with its input index. The soup conversion adds the vertices in input
    # order; match by coordinates should that ever change.
    verts = list(P.vertices())
    in_order = all(_xyz(v) == points[i] for i, v in enumerate(verts))
    if in_order:
        for i, v in enumerate(verts):
            v.set_id(i)
    else:
        by_xyz = {}
        for i, p in enumerate(points):
            by_xyz.setdefault(p, []).append(i)
        for v in verts:
            ids = by_xyz.get(_xyz(v))
            if not ids:
                sys.exit("CGAL changed a vertex position while building the mesh")
            v.set_id(ids.pop())
    for i, f in enumerate(P.facets()):
        f.set_id(i)
    return P


def _xyz(v):
    p = v.point()
    return (p.x(), p.y(), p.z())


def boundary_loops(P):
    """One border halfedge per boundary loop, with the loop's length."""
    for i, h in enumerate(P.halfedges()):
        h.set_id(i)
    seen, loops = set(), []
    for h in P.halfedges():
        if not h.is_border() or h.id() in seen:
            continue
        n, g = 0, h
        while True:
            seen.add(g.id())
            n += 1
            g = g.next()
            if g == h:
                break
        loops.append((h, n))
    return loops


def fill_all(points, faces, cgal):
    """Builds the mesh, fills every loop; returns (mesh, holes, filled, new_vertices, seconds)."""
    PMP = cgal[0]
    P = build_polyhedron(points, faces, cgal)
    loops = boundary_loops(P)
    filled, new_vertices, seconds = 0, 0, 0.0
    for h, n in loops:
        out_faces, out_vertices = [], []
        t0 = time.perf_counter()
        try:
            PMP.triangulate_refine_and_fair_hole(P, h, out_faces, out_vertices)
        except Exception as exc:  # a CGAL precondition surfaces as a Python exception
            seconds += time.perf_counter() - t0
            print(f"cgal-fill-holes: loop of {n} edges: CGAL raised {exc}", file=sys.stderr)
            continue
        seconds += time.perf_counter() - t0
        new_vertices += len(out_vertices)
        if out_faces and not h.is_border():
            filled += 1
        else:
            print(f"cgal-fill-holes: loop of {n} edges left open "
                  f"({len(out_faces)} faces added)", file=sys.stderr)
    return P, len(loops), filled, new_vertices, seconds


def write_obj(P, points, faces, path):
    """Input vertices first (ids 0..V-1), then the new ones; input faces first, then the patch."""
    verts = list(P.vertices())
    nxt = len(points)
    for v in verts:
        if v.id() < 0:  # CGAL creates patch vertices with the default id
            v.set_id(nxt)
            nxt += 1
    ordered = [None] * len(verts)
    for v in verts:
        if not 0 <= v.id() < len(verts) or ordered[v.id()] is not None:
            sys.exit(f"vertex id {v.id()} out of range or repeated: refusing to write")
        ordered[v.id()] = v
    for i, v in enumerate(ordered[:len(points)]):
        if _xyz(v) != points[i]:
            sys.exit(f"input vertex {i + 1} moved: refusing to write")
    seen_old = [False] * len(faces)
    new_faces = []
    for f in P.facets():
        h = f.halfedge()
        ring = []
        for _ in range(f.facet_degree()):
            ring.append(h.vertex().id())
            h = h.next()
        i = f.id()
        if 0 <= i < len(faces) and not seen_old[i] and _same_cycle(ring, faces[i]):
            seen_old[i] = True
        else:
            new_faces.append(ring)
    if not all(seen_old):
        sys.exit(f"{seen_old.count(False)} input faces changed: refusing to write")
    with open(path, "w", encoding="utf-8") as out:
        out.write(f"# {len(ordered)} vertices ({len(points)} input first), "
                  f"{len(faces) + len(new_faces)} faces ({len(faces)} input first); holes "
                  "filled by CGAL triangulate_refine_and_fair_hole\n")
        for v in ordered:
            x, y, z = _xyz(v)
            out.write(f"v {x!r} {y!r} {z!r}\n")
        for ring in faces + new_faces:
            out.write("f " + " ".join(str(i + 1) for i in ring) + "\n")


def _same_cycle(ring, face):
    if len(ring) != len(face) or face[0] not in ring:
        return False
    k = ring.index(face[0])
    return ring[k:] + ring[:k] == face


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    ap.add_argument("input", help="mesh with boundary loops (.obj or .off)")
    ap.add_argument("output", help="filled mesh (.obj)")
    ap.add_argument("--repeat", type=int, default=1, help="runs; the best time is printed")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error("--repeat must be at least 1")

    try:
        from CGAL import CGAL_Polygon_mesh_processing as PMP
        from CGAL.CGAL_Kernel import Point_3
        from CGAL.CGAL_Polyhedron_3 import Polyhedron_3
    except ImportError:
        sys.exit("the CGAL bindings are missing: run scripts/cgal-fill-holes-setup.sh, or "
                 "pip install cgal==6.0.1.post202410241521 numpy==2.4.6")
    cgal = (PMP, Polyhedron_3, Point_3)

    points, faces = read_mesh(args.input)
    check_manifold(faces, args.input)

    best, result = None, None
    for run in range(args.repeat):
        P, holes, filled, new_vertices, seconds = fill_all(points, faces, cgal)
        if result is not None and result[1:] != (holes, filled, new_vertices):
            print(f"cgal-fill-holes: run {run + 1} differs: {(holes, filled, new_vertices)} "
                  f"against {result[1:]}", file=sys.stderr)
        best = seconds if best is None else min(best, seconds)
        result = (P, holes, filled, new_vertices)
    P, holes, filled, new_vertices = result

    write_obj(P, points, faces, args.output)
    print(json.dumps({"holes": holes, "filled": filled, "new_vertices": new_vertices,
                      "seconds": round(best, 6)}))


if __name__ == "__main__":
    main()
