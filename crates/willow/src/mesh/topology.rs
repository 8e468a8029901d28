//! Connectivity of a [`Mesh`]: unique edges, which faces meet at each edge, boundary loops and
//! connected components with their Euler characteristic and genus.
//!
//! The flow needs these per component: the exactness constraints of a genus-g surface count 6g
//! (paper App. C.1), and boundary loops choose between the closed and the free-boundary
//! solves. Connectivity never changes during a flow, so a [`Topology`] is built once per job.

use super::Mesh;

/// One undirected edge per vertex pair, with the faces on each side.
///
/// Edges are numbered in lexicographic order of their sorted vertex pair, so numbering is
/// deterministic and independent of face order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct EdgeTable {
    /// `edges[e] = [a, b]` with `a < b`.
    pub(crate) edges: Vec<[usize; 2]>,
    /// `face_edges[f][k]` is the edge from corner `k` to corner `(k + 1) % 3` of face `f`.
    pub(crate) face_edges: Vec<[usize; 3]>,
    /// Half-edges around edge `e` are `half_edges[edge_start[e]..edge_start[e + 1]]`; half-edge
    /// `h` is face `h / 3`'s directed edge from corner `h % 3` to the next corner.
    edge_start: Vec<usize>,
    half_edges: Vec<usize>,
}

impl EdgeTable {
    /// Builds the table by ordering the 3F half-edges by their undirected vertex pair.
    ///
    /// Ordering bare half-edge ids (one word each, keys recomputed from the triangles) rather
    /// than hashing or sorting wide tuples keeps memory near 11 words per face at the
    /// 10-million-face limit, and the numbering reproducible. The order is a counting sort on
    /// the smaller vertex (linear, and stable, so ids stay ascending within a bucket) followed
    /// by a sort of each vertex's few half-edges by (larger vertex, id): the same order as one
    /// global comparison sort, which was a third of a hole fill's time on a 70k-face scan.
    /// Triangles must index existing vertices (not checked here).
    pub(crate) fn new(triangles: &[[usize; 3]]) -> EdgeTable {
        let key = |h: usize| {
            let t = triangles[h / 3];
            let (a, b) = (t[h % 3], t[(h % 3 + 1) % 3]);
            (a.min(b), a.max(b))
        };
        let half_edge_count = triangles.len() * 3;
        let vertex_count = triangles.iter().flatten().max().map_or(0, |&m| m + 1);
        let mut bucket_start = vec![0usize; vertex_count + 1];
        for h in 0..half_edge_count {
            bucket_start[key(h).0 + 1] += 1;
        }
        for v in 0..vertex_count {
            bucket_start[v + 1] += bucket_start[v];
        }
        let mut next = bucket_start.clone();
        let mut half_edges = vec![0usize; half_edge_count];
        for h in 0..half_edge_count {
            let slot = &mut next[key(h).0];
            half_edges[*slot] = h;
            *slot += 1;
        }
        drop(next);
        for v in 0..vertex_count {
            // Ties broken by id: faces around an edge are listed in ascending order.
            half_edges[bucket_start[v]..bucket_start[v + 1]]
                .sort_unstable_by_key(|&h| (key(h).1, h));
        }
        let mut edges: Vec<[usize; 2]> = Vec::new();
        let mut edge_start = Vec::new();
        let mut face_edges = vec![[0usize; 3]; triangles.len()];
        for (i, &h) in half_edges.iter().enumerate() {
            let (a, b) = key(h);
            if edges.last() != Some(&[a, b]) {
                edges.push([a, b]);
                edge_start.push(i);
            }
            face_edges[h / 3][h % 3] = edges.len() - 1;
        }
        edge_start.push(half_edges.len());
        EdgeTable {
            edges,
            face_edges,
            edge_start,
            half_edges,
        }
    }

    /// The half-edges around edge `e` (see [`EdgeTable::face_corner`]).
    pub(crate) fn faces_of(&self, e: usize) -> &[usize] {
        &self.half_edges[self.edge_start[e]..self.edge_start[e + 1]]
    }

    /// Face and corner of half-edge `h`.
    pub(crate) fn face_corner(h: usize) -> (usize, u8) {
        (h / 3, (h % 3) as u8)
    }
}

/// A boundary loop: the vertices along one closed chain of boundary edges.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BoundaryLoop {
    /// Vertices in order along the loop, each once. The order follows the faces' winding
    /// (the surface lies to the left when walking the loop seen from the outward side).
    pub vertices: Vec<usize>,
    /// `edges[i]` joins `vertices[i]` and `vertices[(i + 1) % len]`.
    pub edges: Vec<usize>,
    /// The connected component the loop bounds.
    pub component: usize,
}

/// One connected piece of the surface (faces connected through shared edges).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Component {
    /// Faces of this component, ascending.
    pub faces: Vec<usize>,
    /// Vertices of this component, ascending.
    pub vertices: Vec<usize>,
    /// Number of distinct edges of this component.
    pub edge_count: usize,
    /// Indices into [`Topology::boundary_loops`] of this component's loops.
    pub boundary_loops: Vec<usize>,
    /// χ = V − E + F.
    pub euler_characteristic: i64,
    /// g = (2 − χ − b) / 2 for an orientable surface with b boundary loops.
    pub genus: usize,
}

impl Component {
    /// A closed component (no boundary): a sphere, a torus, …
    pub fn is_closed(&self) -> bool {
        self.boundary_loops.is_empty()
    }
}

/// Connectivity of a mesh: edges, edge–face incidence, boundary loops and components.
///
/// Built for meshes that passed [`Mesh::new`]: manifold, every vertex used. On other meshes
/// it does not panic, but edges shared by more than two faces keep only their first two and
/// the genus may be meaningless.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Topology {
    /// Unique undirected edges, `[a, b]` with `a < b`, in lexicographic order.
    pub edges: Vec<[usize; 2]>,
    /// `face_edges[f][k]` is the edge from corner `k` to corner `(k + 1) % 3` of face `f`.
    pub face_edges: Vec<[usize; 3]>,
    /// The (at most two) faces on each edge; `[Some(f), None]` on a boundary edge.
    pub edge_faces: Vec<[Option<usize>; 2]>,
    /// Edges with exactly one face, ascending.
    pub boundary_edges: Vec<usize>,
    /// Ordered boundary loops, sorted by their component and then by lowest edge.
    pub boundary_loops: Vec<BoundaryLoop>,
    /// Connected components, ordered by their lowest face index.
    pub components: Vec<Component>,
    /// `face_component[f]` is the component of face `f`.
    pub face_component: Vec<usize>,
    /// `vertex_component[v]` is the component of vertex `v` (`usize::MAX` if no face uses it).
    pub vertex_component: Vec<usize>,
}

impl Topology {
    pub fn new(mesh: &Mesh) -> Topology {
        // Size vertex arrays by the largest index too, so a hand-built mesh with a bad index
        // cannot make this panic (Mesh::new refuses such meshes anyway).
        let vertex_count = mesh
            .triangles
            .iter()
            .flatten()
            .map(|&v| v + 1)
            .max()
            .unwrap_or(0)
            .max(mesh.positions.len());
        let table = EdgeTable::new(&mesh.triangles);
        let edge_count = table.edges.len();
        let edge_faces: Vec<[Option<usize>; 2]> = (0..edge_count)
            .map(|e| {
                let around = table.faces_of(e);
                [
                    around.first().map(|&h| h / 3),
                    around.get(1).map(|&h| h / 3),
                ]
            })
            .collect();

        // Components: breadth-first over faces through shared edges.
        let face_count = mesh.triangles.len();
        let mut face_component = vec![usize::MAX; face_count];
        let mut component_faces: Vec<Vec<usize>> = Vec::new();
        let mut queue = Vec::new();
        for seed in 0..face_count {
            if face_component[seed] != usize::MAX {
                continue;
            }
            let c = component_faces.len();
            let mut faces = vec![seed];
            face_component[seed] = c;
            queue.clear();
            queue.push(seed);
            while let Some(f) = queue.pop() {
                for &e in &table.face_edges[f] {
                    for g in table.faces_of(e).iter().map(|&h| h / 3) {
                        if face_component[g] == usize::MAX {
                            face_component[g] = c;
                            faces.push(g);
                            queue.push(g);
                        }
                    }
                }
            }
            faces.sort_unstable();
            component_faces.push(faces);
        }

        let mut vertex_component = vec![usize::MAX; vertex_count];
        for (f, t) in mesh.triangles.iter().enumerate() {
            for &v in t {
                vertex_component[v] = face_component[f];
            }
        }

        let boundary_edges: Vec<usize> = (0..edge_count)
            .filter(|&e| table.faces_of(e).len() == 1)
            .collect();
        let boundary_loops = trace_boundary_loops(mesh, &table, &boundary_edges, &face_component);

        let mut components: Vec<Component> = component_faces
            .into_iter()
            .map(|faces| Component {
                faces,
                vertices: Vec::new(),
                edge_count: 0,
                boundary_loops: Vec::new(),
                euler_characteristic: 0,
                genus: 0,
            })
            .collect();
        for (v, &c) in vertex_component.iter().enumerate() {
            if let Some(comp) = components.get_mut(c) {
                comp.vertices.push(v);
            }
        }
        for around in &edge_faces {
            if let Some(f) = around[0] {
                components[face_component[f]].edge_count += 1;
            }
        }
        for (i, l) in boundary_loops.iter().enumerate() {
            components[l.component].boundary_loops.push(i);
        }
        for comp in &mut components {
            let chi = comp.vertices.len() as i64 - comp.edge_count as i64 + comp.faces.len() as i64;
            comp.euler_characteristic = chi;
            let twice_genus = 2 - chi - comp.boundary_loops.len() as i64;
            // Even and non-negative for every orientable manifold; clamp for invalid input.
            comp.genus = (twice_genus.max(0) / 2) as usize;
        }

        Topology {
            edges: table.edges,
            face_edges: table.face_edges,
            edge_faces,
            boundary_edges,
            boundary_loops,
            components,
            face_component,
            vertex_component,
        }
    }

    /// Total genus over all components.
    pub fn genus(&self) -> usize {
        self.components.iter().map(|c| c.genus).sum()
    }

    /// χ of the whole mesh (the sum over components).
    pub fn euler_characteristic(&self) -> i64 {
        self.components.iter().map(|c| c.euler_characteristic).sum()
    }

    /// True if no edge lies on a boundary.
    pub fn is_closed(&self) -> bool {
        self.boundary_edges.is_empty()
    }

    /// Marks boundary vertices: `true` for every vertex on some boundary loop.
    pub fn boundary_vertex_mask(&self, vertex_count: usize) -> Vec<bool> {
        let mut mask = vec![false; vertex_count];
        for l in &self.boundary_loops {
            for &v in &l.vertices {
                if let Some(m) = mask.get_mut(v) {
                    *m = true;
                }
            }
        }
        mask
    }
}

/// Chains boundary edges into loops by following each boundary half-edge `a → b` (in its face's
/// winding) to the boundary half-edge leaving `b`. On a manifold mesh exactly one leaves each
/// boundary vertex; elsewhere the first unused one is taken, so this always terminates.
fn trace_boundary_loops(
    mesh: &Mesh,
    table: &EdgeTable,
    boundary_edges: &[usize],
    face_component: &[usize],
) -> Vec<BoundaryLoop> {
    use std::collections::HashMap;
    // Directed boundary half-edges: (from, to, edge, face).
    let directed: Vec<(usize, usize, usize, usize)> = boundary_edges
        .iter()
        .map(|&e| {
            let (f, k) = EdgeTable::face_corner(table.faces_of(e)[0]);
            let t = mesh.triangles[f];
            (t[k as usize], t[(k as usize + 1) % 3], e, f)
        })
        .collect();
    let mut leaving: HashMap<usize, Vec<usize>> = HashMap::with_capacity(directed.len());
    for (i, d) in directed.iter().enumerate() {
        leaving.entry(d.0).or_default().push(i);
    }
    let mut used = vec![false; directed.len()];
    let mut loops = Vec::new();
    for start in 0..directed.len() {
        if used[start] {
            continue;
        }
        let mut vertices = Vec::new();
        let mut edges = Vec::new();
        let mut cur = start;
        loop {
            used[cur] = true;
            let (from, to, e, _) = directed[cur];
            vertices.push(from);
            edges.push(e);
            let next = leaving
                .get(&to)
                .and_then(|out| out.iter().copied().find(|&i| !used[i]));
            match next {
                Some(n) => cur = n,
                None => break,
            }
        }
        loops.push(BoundaryLoop {
            vertices,
            edges,
            component: face_component[directed[start].3],
        });
    }
    loops.sort_by_key(|l| (l.component, l.edges.iter().copied().min().unwrap_or(0)));
    loops
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tetrahedron_edges_are_unique_and_each_has_two_faces() {
        let m = Mesh {
            positions: vec![[0.0; 3]; 4],
            triangles: vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]],
        };
        let t = Topology::new(&m);
        assert_eq!(t.edges.len(), 6);
        assert!(t.edge_faces.iter().all(|f| f[1].is_some()));
        assert_eq!(t.euler_characteristic(), 2);
        for (f, tri) in m.triangles.iter().enumerate() {
            for k in 0..3 {
                let [a, b] = t.edges[t.face_edges[f][k]];
                let (p, q) = (tri[k], tri[(k + 1) % 3]);
                assert_eq!([a, b], [p.min(q), p.max(q)]);
            }
        }
    }
    #[test]
    fn edge_table_orders_half_edges_as_one_global_sort() {
        // A fan around edge 0-1 with four faces (non-manifold) plus a strip whose vertex ids are
        // scattered, so buckets hold several edges and ties need the id order.
        let mut triangles = vec![[0, 1, 2], [0, 4, 1], [1, 0, 6], [0, 1, 7], [3, 5, 2]];
        for i in 0..40 {
            triangles.push([8 + i, 9 + i, 10 + (i * 7) % 40]);
        }
        let table = EdgeTable::new(&triangles);
        let key = |h: usize| {
            let t = triangles[h / 3];
            let (a, b) = (t[h % 3], t[(h % 3 + 1) % 3]);
            (a.min(b), a.max(b), h)
        };
        let mut expected: Vec<usize> = (0..triangles.len() * 3).collect();
        expected.sort_by_key(|&h| key(h));
        assert_eq!(table.half_edges, expected);
        let e01 = table
            .edges
            .iter()
            .position(|&e| e == [0, 1])
            .expect("edge 0-1");
        assert_eq!(table.faces_of(e01).len(), 4);
        let faces: Vec<usize> = table.faces_of(e01).iter().map(|&h| h / 3).collect();
        assert_eq!(faces, vec![0, 1, 2, 3]);
        for (f, t) in triangles.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                assert_eq!(table.edges[table.face_edges[f][k]], [a.min(b), a.max(b)]);
            }
        }
        assert!(EdgeTable::new(&[]).edges.is_empty());
    }
}
