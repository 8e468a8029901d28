//! Closing holes: each chosen boundary loop is triangulated, refined to the edge length around
//! it, and handed to the fairing ([`crate::flow::holes`]) as a patch of new vertices.
//!
//! - **Triangulation** (Liepa 2003, after Barequet and Sharir 1995): the dynamic program over
//!   the loop's sub-polygons that minimizes, lexicographically, the largest dihedral angle
//!   between neighbouring triangles (the surface's own faces along the loop included) and then
//!   the total area. `O(n³)` in the loop's length `n`, so loops longer than
//!   [`MAX_DP_LOOP`] are closed by a fan around their centroid instead, which refinement and
//!   fairing then reshape. An edge that would join two loop vertices already joined outside
//!   the hole is never made, so the result stays manifold.
//! - **Refinement** (Liepa 2003, §3.2): every vertex carries a scale σ (on the loop, the mean
//!   length of its edges in the surface); a patch triangle is split at its centroid when the
//!   centroid lies farther than σ/√2 from each of its corners, then the patch's inner edges are
//!   swapped towards Delaunay. Repeated until nothing splits, so the patch's edges come out
//!   about as long as the surface's around the hole.
//! - **Numbering**: the surface's vertices and triangles keep their indices; new vertices are
//!   appended after them and new triangles after the surface's, hole by hole.

use std::collections::{HashMap, HashSet};

use super::{Limits, Mesh, MeshError, Topology};
use crate::geometry::vec3::{add, cross, dot, norm, scale, sub};

/// Longest loop triangulated by the `O(n³)` dynamic program (27M weight evaluations); longer
/// loops start from a centroid fan.
pub const MAX_DP_LOOP: usize = 300;

/// Liepa's density factor: a centroid is inserted when it is farther than `σ/α` from each
/// corner (√2 in his paper, the value CGAL uses).
const DENSITY: f64 = std::f64::consts::SQRT_2;

/// Which boundary loops count as holes to fill. In JSON, as in [`HoleSize::parse`]: `"all"`,
/// an integer (boundary vertices) or a decimal number (model units), as a number or a string.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub enum HoleSize {
    /// Every boundary loop.
    #[default]
    Any,
    /// Loops of at most this many boundary vertices.
    Vertices(usize),
    /// Loops whose bounding box has at most this diagonal (model units).
    Extent(f64),
}

impl HoleSize {
    /// `all`, an integer (boundary vertices: `120`) or a decimal length in model units
    /// (`0.25`, `2e-3`).
    pub fn parse(text: &str) -> Result<HoleSize, String> {
        let t = text.trim();
        if t.eq_ignore_ascii_case("all") || t.eq_ignore_ascii_case("any") {
            return Ok(HoleSize::Any);
        }
        if t.bytes().all(|b| b.is_ascii_digit()) && !t.is_empty() {
            return match t.parse::<usize>() {
                Ok(n) if n >= 3 => Ok(HoleSize::Vertices(n)),
                _ => Err(format!(
                    "a hole size in boundary vertices must be an integer of at least 3, got {t:?}"
                )),
            };
        }
        match t.parse::<f64>() {
            Ok(d) if d.is_finite() && d > 0.0 => Ok(HoleSize::Extent(d)),
            _ => Err(format!(
                "a hole size is `all`, a count of boundary vertices (an integer >= 3) or a \
                 length in model units (a positive decimal such as 0.25), got {t:?}"
            )),
        }
    }

    /// Whether the loop through `vertices` is small enough to fill.
    pub fn admits(&self, positions: &[[f64; 3]], vertices: &[usize]) -> bool {
        match *self {
            HoleSize::Any => true,
            HoleSize::Vertices(n) => vertices.len() <= n,
            HoleSize::Extent(d) => loop_extent(positions, vertices) <= d,
        }
    }
}

impl std::fmt::Display for HoleSize {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HoleSize::Any => f.write_str("all"),
            HoleSize::Vertices(n) => write!(f, "{n} boundary vertices"),
            HoleSize::Extent(d) => write!(f, "{d} model units across"),
        }
    }
}

impl serde::Serialize for HoleSize {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match *self {
            HoleSize::Any => s.serialize_str("all"),
            HoleSize::Vertices(n) => s.serialize_u64(n as u64),
            HoleSize::Extent(d) => s.serialize_f64(d),
        }
    }
}

impl<'de> serde::Deserialize<'de> for HoleSize {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(serde::Deserialize)]
        #[serde(untagged)]
        enum Form<'a> {
            Count(u64),
            Length(f64),
            Text(std::borrow::Cow<'a, str>),
        }
        let parsed = match Form::deserialize(d)? {
            Form::Count(n) => HoleSize::parse(&n.to_string()),
            Form::Length(x) if x.is_finite() && x > 0.0 => Ok(HoleSize::Extent(x)),
            Form::Length(x) => HoleSize::parse(&x.to_string()),
            Form::Text(t) => HoleSize::parse(&t),
        };
        parsed.map_err(serde::de::Error::custom)
    }
}

/// The diagonal of the bounding box of a loop's vertices.
pub fn loop_extent(positions: &[[f64; 3]], vertices: &[usize]) -> f64 {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &v in vertices {
        for k in 0..3 {
            lo[k] = lo[k].min(positions[v][k]);
            hi[k] = hi[k].max(positions[v][k]);
        }
    }
    norm(sub(hi, lo))
}

/// One closed hole.
#[derive(Clone, Debug, PartialEq)]
pub struct FilledHole {
    /// The loop's vertices, in the surface's boundary order.
    pub boundary: Vec<usize>,
    /// The new vertices of its patch: `first_vertex..first_vertex + vertex_count`.
    pub first_vertex: usize,
    pub vertex_count: usize,
    /// The patch's triangles: `first_triangle..first_triangle + triangle_count`.
    pub first_triangle: usize,
    pub triangle_count: usize,
    /// Whether the loop was closed by the dynamic program (else by a centroid fan).
    pub minimal_dihedral: bool,
}

/// The surface with its holes closed.
#[derive(Clone, Debug)]
pub struct Filled {
    pub mesh: Mesh,
    /// The vertices and triangles before filling (they keep their indices).
    pub original_vertices: usize,
    pub original_triangles: usize,
    pub holes: Vec<FilledHole>,
    /// Loops left open because [`HoleSize`] did not admit them, as their vertex counts.
    pub left_open: Vec<usize>,
}

impl Filled {
    /// `true` for every vertex a patch added.
    pub fn new_vertex_mask(&self) -> Vec<bool> {
        let mut mask = vec![false; self.mesh.vertex_count()];
        for slot in mask.iter_mut().skip(self.original_vertices) {
            *slot = true;
        }
        mask
    }
}

/// Closes every boundary loop `size` admits (module docs). The surface's own vertices keep
/// their positions and indices, its triangles their indices and winding; the patches are
/// flat-ish until faired ([`crate::flow::holes`]). The surface must be valid ([`Mesh::new`]);
/// the patches are manifold and non-degenerate by construction, so the result is not
/// validated again (on a million-triangle scan that would cost more than the filling).
pub fn fill_holes(mesh: &Mesh, size: HoleSize, limits: &Limits) -> Result<Filled, MeshError> {
    let borders = borders(mesh);
    let mut positions = mesh.positions.clone();
    let mut triangles = mesh.triangles.clone();
    let mut holes = Vec::new();
    let mut left_open = Vec::new();
    for (hole, outer_faces) in &borders.loops {
        if !size.admits(&mesh.positions, hole) {
            left_open.push(hole.len());
            continue;
        }
        let outer: Vec<[f64; 3]> = outer_faces
            .iter()
            .map(|&f| face_normal(&mesh.positions, mesh.triangles[f]))
            .collect();
        let first_vertex = positions.len();
        let first_triangle = triangles.len();
        let (mut patch, minimal_dihedral) =
            match triangulate_loop(&positions, hole, &outer, &borders.joined) {
                Some(t) => (t, true),
                None => (centroid_fan(&mut positions, hole), false),
            };
        let scale_of = |v: usize| borders.scale.get(&v).copied().unwrap_or(0.0);
        let mut scales: HashMap<usize, f64> = hole.iter().map(|&v| (v, scale_of(v))).collect();
        if positions.len() > first_vertex {
            // The fan's centre: the mean scale of the loop.
            let mean = hole.iter().map(|&v| scale_of(v)).sum::<f64>() / hole.len() as f64;
            scales.insert(first_vertex, mean);
        }
        refine_patch(
            &mut positions,
            &mut patch,
            &mut scales,
            &borders.joined,
            limits,
        )?;
        triangles.extend_from_slice(&patch);
        limits.check_faces(triangles.len())?;
        holes.push(FilledHole {
            boundary: hole.clone(),
            first_vertex,
            vertex_count: positions.len() - first_vertex,
            first_triangle,
            triangle_count: patch.len(),
            minimal_dihedral,
        });
    }
    Ok(Filled {
        mesh: Mesh {
            positions,
            triangles,
        },
        original_vertices: mesh.vertex_count(),
        original_triangles: mesh.face_count(),
        holes,
        left_open,
    })
}

/// What filling needs to know of a surface's border, found in one sort of its edges rather
/// than a whole [`Topology`].
struct Borders {
    /// Each boundary loop's vertices in its faces' winding, with the face on each loop edge
    /// `l[i] → l[i+1]`.
    loops: Vec<(Vec<usize>, Vec<usize>)>,
    /// The surface's edges between two border vertices (`[min, max]`): a patch must not
    /// make them again.
    joined: HashSet<[usize; 2]>,
    /// Liepa's σ of each border vertex: the mean length of its edges.
    scale: HashMap<usize, f64>,
}

fn borders(mesh: &Mesh) -> Borders {
    let half = HalfEdgesByEdge::new(mesh);
    // Boundary half-edges: alone on their edge. `next[a]` is the one leaving `a`.
    let corner = |h: u32| {
        let (f, k) = (h as usize / 3, h as usize % 3);
        let t = mesh.triangles[f];
        (t[k], t[(k + 1) % 3], f)
    };
    let mut next: HashMap<usize, (usize, usize)> = HashMap::new();
    let mut pinched = false;
    half.for_each_edge(|_, _, halves| {
        if let [h] = halves {
            let (a, b, f) = corner(*h as u32);
            pinched |= next.insert(a, (b, f)).is_some();
        }
    });
    let loops = if pinched {
        // Two loops through one vertex: let the full topology order them.
        let topology = Topology::new(mesh);
        topology
            .boundary_loops
            .iter()
            .map(|l| {
                let faces = l
                    .edges
                    .iter()
                    .map(|&e| topology.edge_faces[e][0].unwrap_or(0))
                    .collect();
                (l.vertices.clone(), faces)
            })
            .collect()
    } else {
        let mut starts: Vec<usize> = next.keys().copied().collect();
        starts.sort_unstable();
        let mut seen: HashSet<usize> = HashSet::new();
        let mut loops = Vec::new();
        for s in starts {
            if seen.contains(&s) {
                continue;
            }
            let (mut vertices, mut faces) = (Vec::new(), Vec::new());
            let mut v = s;
            while seen.insert(v) {
                let Some(&(w, f)) = next.get(&v) else { break };
                vertices.push(v);
                faces.push(f);
                v = w;
            }
            if v == s && vertices.len() >= 3 {
                loops.push((vertices, faces));
            }
        }
        loops
    };
    let mut border_mask = vec![false; mesh.vertex_count()];
    for &v in next.keys() {
        border_mask[v] = true;
    }
    let on_border = |v: usize| border_mask[v];
    let mut joined = HashSet::new();
    let mut sums: HashMap<usize, (f64, usize)> = HashMap::new();
    half.for_each_edge(|a, b, _| {
        if on_border(a) || on_border(b) {
            let l = norm(sub(mesh.positions[a], mesh.positions[b]));
            for v in [a, b] {
                if on_border(v) {
                    let e = sums.entry(v).or_default();
                    e.0 += l;
                    e.1 += 1;
                }
            }
            if on_border(a) && on_border(b) {
                joined.insert([a, b]);
            }
        }
    });
    let scale = sums
        .into_iter()
        .map(|(v, (s, c))| (v, s / c.max(1) as f64))
        .collect();
    Borders {
        loops,
        joined,
        scale,
    }
}

/// Every half-edge `3f + k` (corner k of face f to the next), grouped by edge: a counting
/// sort on the edge's smaller vertex, then a sort of each vertex's handful of entries
/// (`other << 32 | half`, 8 bytes). O(F); one sort of all half-edges by key cost most of
/// filling a small hole in a large scan (10 of 23 ms on the 70k-face bunny).
struct HalfEdgesByEdge {
    start: Vec<usize>,
    entries: Vec<u64>,
}

impl HalfEdgesByEdge {
    fn new(mesh: &Mesh) -> HalfEdgesByEdge {
        let mut start = vec![0usize; mesh.vertex_count() + 1];
        for t in &mesh.triangles {
            for k in 0..3 {
                start[t[k].min(t[(k + 1) % 3]) + 1] += 1;
            }
        }
        for v in 0..mesh.vertex_count() {
            start[v + 1] += start[v];
        }
        let mut next = start.clone();
        let mut entries = vec![0u64; 3 * mesh.face_count()];
        for (f, t) in mesh.triangles.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let slot = &mut next[a.min(b)];
                entries[*slot] = ((a.max(b) as u64) << 32) | (3 * f + k) as u64;
                *slot += 1;
            }
        }
        for v in 0..mesh.vertex_count() {
            entries[start[v]..start[v + 1]].sort_unstable();
        }
        HalfEdgesByEdge { start, entries }
    }

    /// Calls `visit(a, b, halves)` once per edge `a < b`, in order, with its half-edges'
    /// entries (the low 32 bits of each are the half-edge).
    fn for_each_edge(&self, mut visit: impl FnMut(usize, usize, &[u64])) {
        for a in 0..self.start.len() - 1 {
            let group = &self.entries[self.start[a]..self.start[a + 1]];
            let mut i = 0;
            while i < group.len() {
                let b = group[i] >> 32;
                let mut j = i + 1;
                while j < group.len() && group[j] >> 32 == b {
                    j += 1;
                }
                visit(a, b as usize, &group[i..j]);
                i = j;
            }
        }
    }
}

/// The unit normal of a triangle (zero for a degenerate one).
pub fn face_normal(positions: &[[f64; 3]], t: [usize; 3]) -> [f64; 3] {
    let n = cross(
        sub(positions[t[1]], positions[t[0]]),
        sub(positions[t[2]], positions[t[0]]),
    );
    let l = norm(n);
    if l > 0.0 && l.is_finite() {
        scale(n, 1.0 / l)
    } else {
        [0.0; 3]
    }
}

/// Liepa's weight of a (partial) triangulation: the largest dihedral angle, then the area.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Weight {
    angle: f64,
    area: f64,
}

impl Weight {
    const ZERO: Weight = Weight {
        angle: 0.0,
        area: 0.0,
    };
    const INFINITE: Weight = Weight {
        angle: f64::INFINITY,
        area: f64::INFINITY,
    };

    fn combine(self, other: Weight) -> Weight {
        Weight {
            angle: self.angle.max(other.angle),
            area: self.area + other.area,
        }
    }

    /// Angles within 1e-9 rad are equal, so the area decides between near-coplanar choices.
    fn less(self, other: Weight) -> bool {
        if (self.angle - other.angle).abs() > 1e-9 {
            self.angle < other.angle
        } else {
            self.area < other.area
        }
    }
}

/// The cosine of the angle between two unit normals (−1, the angle π, when either is
/// degenerate, so a degenerate triangle is only ever the last resort).
fn normal_cosine(a: [f64; 3], b: [f64; 3]) -> f64 {
    if a == [0.0; 3] || b == [0.0; 3] {
        return -1.0;
    }
    dot(a, b).clamp(-1.0, 1.0)
}

/// The angle between two unit normals (π when either is degenerate).
fn normal_angle(a: [f64; 3], b: [f64; 3]) -> f64 {
    normal_cosine(a, b).acos()
}

/// The minimal-dihedral triangulation of the loop `l` (module docs), as triangles of the
/// surface's vertex numbers, oriented against the loop so they continue the surface's winding.
/// `outer[i]` is the normal of the surface's face on the loop edge `l[i] → l[i+1]`. `None`
/// when the loop is longer than [`MAX_DP_LOOP`] or no triangulation avoids the surface's
/// edges.
pub fn triangulate_loop(
    positions: &[[f64; 3]],
    l: &[usize],
    outer: &[[f64; 3]],
    edges: &HashSet<[usize; 2]>,
) -> Option<Vec<[usize; 3]>> {
    let n = l.len();
    if !(3..=MAX_DP_LOOP).contains(&n) {
        return None;
    }
    // The patch triangle on sub-polygon corners i < m < k is [l_i, l_k, l_m]: its edges run
    // l_m → l_i and l_k → l_m, against the loop, as the surface's neighbour faces need.
    let tri = |i: usize, m: usize, k: usize| [l[i], l[k], l[m]];
    let joined = |a: usize, b: usize| {
        let (a, b) = (l[a].min(l[b]), l[a].max(l[b]));
        edges.contains(&[a, b])
    };
    let idx = |i: usize, k: usize| i * n + k;
    let mut weight = vec![Weight::INFINITE; n * n];
    let mut best = vec![usize::MAX; n * n];
    // The normal of the face across edge (i, k) of a sub-polygon: the surface's for a loop
    // edge (k = i + 1), else that of the triangle sub-problem (i, k) chose, kept when it is
    // chosen so the O(n³) search below computes each candidate's normal once.
    let mut across = vec![[0.0; 3]; n * n];
    for i in 0..n - 1 {
        weight[idx(i, i + 1)] = Weight::ZERO;
        across[idx(i, i + 1)] = outer[i];
    }
    for len in 2..n {
        for i in 0..n - len {
            let k = i + len;
            // The chord (i, k) is a new edge unless it closes the loop (0, n − 1); it must not
            // exist outside the hole already.
            let closing = i == 0 && k == n - 1;
            if !closing && joined(i, k) {
                continue;
            }
            let (pi, pk) = (positions[l[i]], positions[l[k]]);
            let mut w_best = Weight::INFINITE;
            let mut m_best = usize::MAX;
            let mut n_best = [0.0; 3];
            for m in i + 1..k {
                let (w_im, w_mk) = (weight[idx(i, m)], weight[idx(m, k)]);
                if w_im.angle.is_infinite() || w_mk.angle.is_infinite() {
                    continue;
                }
                // A triangle only raises the largest angle and adds area, so a partial
                // weight that already loses cannot win (the search stays exact).
                let partial = w_im.combine(w_mk);
                if !partial.less(w_best) {
                    continue;
                }
                let c = cross(sub(pk, pi), sub(positions[l[m]], pi));
                let length = norm(c);
                let nt = if length > 0.0 && length.is_finite() {
                    scale(c, 1.0 / length)
                } else {
                    [0.0; 3]
                };
                // Largest angle = acos of the smallest cosine (one acos per candidate).
                let mut cosine =
                    normal_cosine(nt, across[idx(i, m)]).min(normal_cosine(nt, across[idx(m, k)]));
                if closing {
                    cosine = cosine.min(normal_cosine(nt, outer[n - 1]));
                }
                let w = partial.combine(Weight {
                    angle: cosine.acos(),
                    area: 0.5 * length,
                });
                if w.less(w_best) {
                    w_best = w;
                    m_best = m;
                    n_best = nt;
                }
            }
            weight[idx(i, k)] = w_best;
            best[idx(i, k)] = m_best;
            across[idx(i, k)] = n_best;
        }
    }
    if best[idx(0, n - 1)] == usize::MAX {
        return None;
    }
    let mut out = Vec::with_capacity(n - 2);
    let mut stack = vec![(0, n - 1)];
    while let Some((i, k)) = stack.pop() {
        if k <= i + 1 {
            continue;
        }
        let m = best[idx(i, k)];
        if m == usize::MAX {
            return None;
        }
        out.push(tri(i, m, k));
        stack.push((i, m));
        stack.push((m, k));
    }
    Some(out)
}

/// A fan from a new vertex at the loop's centroid (appended to `positions`), oriented as
/// [`triangulate_loop`]'s triangles.
pub fn centroid_fan(positions: &mut Vec<[f64; 3]>, l: &[usize]) -> Vec<[usize; 3]> {
    let mut c = [0.0; 3];
    for &v in l {
        c = add(c, positions[v]);
    }
    let c = scale(c, 1.0 / l.len() as f64);
    let centre = positions.len();
    positions.push(c);
    (0..l.len())
        .map(|i| [l[(i + 1) % l.len()], l[i], centre])
        .collect()
}

/// Liepa's refinement of a patch (module docs): centroid splits while a triangle is larger
/// than its corners' scales, with Delaunay swaps of the patch's inner edges after each round.
/// New vertices are appended to `positions` with their scale in `scales`.
pub fn refine_patch(
    positions: &mut Vec<[f64; 3]>,
    patch: &mut Vec<[usize; 3]>,
    scales: &mut HashMap<usize, f64>,
    surface_edges: &HashSet<[usize; 2]>,
    limits: &Limits,
) -> Result<(), MeshError> {
    relax_patch(positions, patch, surface_edges);
    // Each round at least triples the triangles it splits; 64 rounds is far past any patch a
    // mesh within its limits can need.
    for _ in 0..64 {
        let mut split = false;
        let count = patch.len();
        for t in 0..count {
            let tri = patch[t];
            let c = scale(
                add(add(positions[tri[0]], positions[tri[1]]), positions[tri[2]]),
                1.0 / 3.0,
            );
            let s = |v: usize| scales.get(&v).copied().unwrap_or(0.0);
            let sc = (s(tri[0]) + s(tri[1]) + s(tri[2])) / 3.0;
            let coarse = tri.iter().all(|&v| {
                let d = DENSITY * norm(sub(c, positions[v]));
                d > sc && d > s(v)
            });
            if !coarse {
                continue;
            }
            let centre = positions.len();
            limits.check_vertices(centre + 1)?;
            positions.push(c);
            scales.insert(centre, sc);
            patch[t] = [tri[0], tri[1], centre];
            patch.push([tri[1], tri[2], centre]);
            patch.push([tri[2], tri[0], centre]);
            split = true;
        }
        limits.check_faces(patch.len())?;
        if !split {
            break;
        }
        relax_patch(positions, patch, surface_edges);
    }
    Ok(())
}

/// Swaps the patch's inner edges until each is locally Delaunay (its two opposite angles sum
/// to at most π), never making an edge that exists already.
fn relax_patch(
    positions: &[[f64; 3]],
    patch: &mut [[usize; 3]],
    surface_edges: &HashSet<[usize; 2]>,
) {
    let mut half = PatchHalfEdges::new(patch);
    // (sin α, cos α) of the angle at p of the triangle (p, a, b), scaled by |pa|·|pb|; `None`
    // when a side has no length (the angle counted as π, so the edge is swapped away).
    let corner = |p: [f64; 3], a: [f64; 3], b: [f64; 3]| {
        let (u, v) = (sub(a, p), sub(b, p));
        let (nu, nv) = (norm(u), norm(v));
        (nu > 0.0 && nv > 0.0).then(|| (norm(cross(u, v)), dot(u, v), nu * nv))
    };
    let third = |tri: [usize; 3], a: usize, b: usize| {
        tri.iter().copied().find(|&v| v != a && v != b).unwrap_or(a)
    };
    // Each pass visits every edge; a Delaunay flip sequence terminates, the cap only guards
    // against round-off cycling between two near-cocircular choices.
    for _ in 0..32 {
        let mut flipped = false;
        for t1 in 0..patch.len() {
            for k in 0..3 {
                let tri = patch[t1];
                let (a, b) = (tri[k], tri[(k + 1) % 3]);
                let Some(t2) = half.get(b, a) else {
                    continue; // a loop edge: the surface is on the other side
                };
                if t2 == t1 {
                    continue;
                }
                let c = third(tri, a, b);
                let d = third(patch[t2], a, b);
                if c == d
                    || half.get(c, d).is_some()
                    || half.get(d, c).is_some()
                    || surface_edges.contains(&[c.min(d), c.max(d)])
                {
                    continue;
                }
                let (pa, pb, pc, pd) = (positions[a], positions[b], positions[c], positions[d]);
                // α + β > π exactly when sin(α + β) < 0 (both angles lie in (0, π)): the
                // Delaunay test without an acos, with the same 1e-9 rad of slack.
                let delaunay = match (corner(pc, pa, pb), corner(pd, pa, pb)) {
                    (Some((s1, c1, l1)), Some((s2, c2, l2))) => {
                        s1 * c2 + c1 * s2 >= -1e-9 * l1 * l2
                    }
                    (Some((_, c, l)), None) | (None, Some((_, c, l))) => {
                        // π plus α: past π unless α is (within slack) zero.
                        c >= l * (1.0 - 5e-19)
                    }
                    (None, None) => false,
                };
                if delaunay {
                    continue;
                }
                // The swap must not fold: both new triangles keep the old pair's orientation.
                let n_old = add(
                    cross(sub(pb, pa), sub(pc, pa)),
                    cross(sub(pa, pb), sub(pd, pb)),
                );
                let n1 = cross(sub(pa, pc), sub(pd, pc));
                let n2 = cross(sub(pb, pd), sub(pc, pd));
                if dot(n1, n_old) <= 0.0 || dot(n2, n_old) <= 0.0 {
                    continue;
                }
                // (a, b, c) and (b, a, d) become (c, a, d) and (d, b, c).
                for (x, y) in [(a, b), (b, c), (c, a), (b, a), (a, d), (d, b)] {
                    half.remove(x, y);
                }
                patch[t1] = [c, a, d];
                patch[t2] = [d, b, c];
                for (x, y) in [(c, a), (a, d), (d, c)] {
                    half.insert(x, y, t1);
                }
                for (x, y) in [(d, b), (b, c), (c, d)] {
                    half.insert(x, y, t2);
                }
                flipped = true;
            }
        }
        if !flipped {
            break;
        }
    }
}

/// A patch's half-edges `a → b` with their triangle: each vertex's few outgoing ones in a
/// list, the vertices found by binary search. The swaps only rearrange edges among the
/// patch's vertices, so the vertex set is fixed; a hashed table cost most of a refinement.
struct PatchHalfEdges {
    vertices: Vec<usize>,
    out: Vec<Vec<(usize, usize)>>,
}

impl PatchHalfEdges {
    fn new(patch: &[[usize; 3]]) -> PatchHalfEdges {
        let mut vertices: Vec<usize> = patch.iter().flatten().copied().collect();
        vertices.sort_unstable();
        vertices.dedup();
        let mut half = PatchHalfEdges {
            out: vec![Vec::new(); vertices.len()],
            vertices,
        };
        for (t, tri) in patch.iter().enumerate() {
            for k in 0..3 {
                half.insert(tri[k], tri[(k + 1) % 3], t);
            }
        }
        half
    }

    fn slot(&self, v: usize) -> Option<usize> {
        self.vertices.binary_search(&v).ok()
    }

    fn get(&self, a: usize, b: usize) -> Option<usize> {
        let out = &self.out[self.slot(a)?];
        out.iter().find(|&&(w, _)| w == b).map(|&(_, t)| t)
    }

    fn insert(&mut self, a: usize, b: usize, t: usize) {
        if let Some(s) = self.slot(a) {
            let out = &mut self.out[s];
            match out.iter_mut().find(|(w, _)| *w == b) {
                Some(entry) => entry.1 = t,
                None => out.push((b, t)),
            }
        }
    }

    fn remove(&mut self, a: usize, b: usize) {
        if let Some(s) = self.slot(a) {
            self.out[s].retain(|&(w, _)| w != b);
        }
    }
}

/// A hole cut into a surface, for measuring a filler against the surface it replaces.
#[derive(Clone, Debug)]
pub struct CutHole {
    /// The surface without the cut-away faces, its unused vertices dropped.
    pub mesh: Mesh,
    /// For each vertex of `mesh`, its index in the uncut surface.
    pub kept: Vec<usize>,
    /// For each face of `mesh`, its index in the uncut surface.
    pub kept_faces: Vec<usize>,
    /// The cut-away triangles, as positions.
    pub removed: Vec<[[f64; 3]; 3]>,
}

/// Cuts away every face whose three corners lie within `radius` of `centre` (a vertex's
/// neighbourhood on a closed mesh: a disk, so one new boundary loop). `None` when no face
/// lies that close or what is left is not a valid mesh.
pub fn cut_ball(mesh: &Mesh, centre: [f64; 3], radius: f64) -> Option<CutHole> {
    let inside = |v: usize| norm(sub(mesh.positions[v], centre)) <= radius;
    let (cut, kept_faces): (Vec<usize>, Vec<usize>) =
        (0..mesh.face_count()).partition(|&f| mesh.triangles[f].iter().all(|&v| inside(v)));
    if cut.is_empty() || kept_faces.is_empty() {
        return None;
    }
    let mut new_index = vec![usize::MAX; mesh.vertex_count()];
    let mut kept = Vec::new();
    let triangles: Vec<[usize; 3]> = kept_faces
        .iter()
        .map(|&f| {
            mesh.triangles[f].map(|v| {
                if new_index[v] == usize::MAX {
                    new_index[v] = kept.len();
                    kept.push(v);
                }
                new_index[v]
            })
        })
        .collect();
    let positions = kept.iter().map(|&v| mesh.positions[v]).collect();
    let removed = cut
        .iter()
        .map(|&f| mesh.triangles[f].map(|v| mesh.positions[v]))
        .collect();
    Some(CutHole {
        mesh: Mesh::new(positions, triangles).ok()?,
        kept,
        kept_faces,
        removed,
    })
}

/// The holes a benchmark cuts (issue 40): balls of radius 3%, 5% and 8% of the bounding-box
/// diagonal around the vertices at 1/6, 1/2 and 5/6 of the vertex order, cut one after the
/// other. What is left, with every face cut away; `None` when a ball holds no face.
pub fn cut_benchmark_holes(mesh: &Mesh) -> Option<CutHole> {
    let d = loop_extent(
        &mesh.positions,
        &(0..mesh.vertex_count()).collect::<Vec<_>>(),
    );
    let n = mesh.vertex_count();
    let centres = [n / 6, n / 2, 5 * n / 6].map(|v| mesh.positions[v]);
    let mut current = CutHole {
        mesh: mesh.clone(),
        kept: (0..n).collect(),
        kept_faces: (0..mesh.face_count()).collect(),
        removed: Vec::new(),
    };
    for (c, share) in centres.iter().zip([0.03, 0.05, 0.08]) {
        let cut = cut_ball(&current.mesh, *c, share * d)?;
        current = CutHole {
            kept: cut.kept.iter().map(|&v| current.kept[v]).collect(),
            kept_faces: cut
                .kept_faces
                .iter()
                .map(|&f| current.kept_faces[f])
                .collect(),
            removed: [current.removed, cut.removed].concat(),
            mesh: cut.mesh,
        };
    }
    Some(current)
}

/// The mean dihedral angle (degrees) the uncut surface had across the edges where `cut`
/// left a border: the seam angle a perfect filler would give back.
pub fn true_seam_dihedral(original: &Mesh, cut: &CutHole) -> f64 {
    let mut kept = vec![false; original.face_count()];
    for &f in &cut.kept_faces {
        kept[f] = true;
    }
    let topology = Topology::new(original);
    let (mut sum, mut count) = (0.0, 0usize);
    for faces in &topology.edge_faces {
        if let [Some(f), Some(g)] = *faces {
            if kept[f] != kept[g] {
                sum += normal_angle(
                    face_normal(&original.positions, original.triangles[f]),
                    face_normal(&original.positions, original.triangles[g]),
                )
                .to_degrees();
                count += 1;
            }
        }
    }
    if count > 0 {
        sum / count as f64
    } else {
        0.0
    }
}

/// Quality of a filled hole against what was cut away.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct PatchQuality {
    /// Mean distance from the patch's new vertices to the cut-away surface.
    pub mean_distance: f64,
    /// Mean angle (degrees) between the normals of the two faces on each loop edge.
    pub seam_dihedral_deg: f64,
    /// Patch edges whose two faces turn by more than 90°: folds.
    pub folds: usize,
}

/// Measures the patches of a filled surface whose first `original_vertices` vertices and
/// `original_triangles` triangles are the surface before filling (any filler's output in
/// that numbering, [`Filled`]'s or CGAL's): distance of the new vertices to `removed`, the
/// seam's dihedral angle, and the folds.
pub fn patch_quality(
    mesh: &Mesh,
    original_vertices: usize,
    original_triangles: usize,
    removed: &[[[f64; 3]; 3]],
) -> PatchQuality {
    let mut distance = 0.0;
    let mut count = 0usize;
    for p in mesh.positions.iter().skip(original_vertices) {
        let mut best = f64::INFINITY;
        for t in removed {
            let q = crate::geometry::bvh::closest_point_on_triangle(*p, t[0], t[1], t[2]);
            best = best.min(norm(sub(*p, q)));
        }
        distance += best;
        count += 1;
    }
    let topology = Topology::new(mesh);
    let mut seam = 0.0;
    let mut seam_edges = 0usize;
    let mut folds = 0;
    for faces in &topology.edge_faces {
        let (Some(f), Some(g)) = (faces[0], faces[1]) else {
            continue;
        };
        let patch = |f: usize| f >= original_triangles;
        if !patch(f) && !patch(g) {
            continue;
        }
        let angle = normal_angle(
            face_normal(&mesh.positions, mesh.triangles[f]),
            face_normal(&mesh.positions, mesh.triangles[g]),
        );
        if patch(f) != patch(g) {
            seam += angle.to_degrees();
            seam_edges += 1;
        }
        if angle > std::f64::consts::FRAC_PI_2 {
            folds += 1;
        }
    }
    PatchQuality {
        mean_distance: if count > 0 {
            distance / count as f64
        } else {
            0.0
        },
        seam_dihedral_deg: if seam_edges > 0 {
            seam / seam_edges as f64
        } else {
            0.0
        },
        folds,
    }
}

#[cfg(test)]
#[path = "holes_tests.rs"]
mod tests;
