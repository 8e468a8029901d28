//! The door every mesh passes through: [`Mesh::new`] checks an indexed triangle list and
//! orients it, or says precisely why it cannot be faired.
//!
//! Checks run cheapest and most basic first, so each later check may rely on the earlier ones
//! (e.g. the edge table needs in-range indices):
//! size limits → empty → non-finite or out-of-range coordinates → indices in range → degenerate faces →
//! unreferenced vertices → non-manifold edges → non-manifold vertices → orientation.

use super::error::{MeshError, Offenders};
use super::topology::EdgeTable;
use super::Mesh;

/// Largest coordinate magnitude a mesh may have. The flow squares lengths (|e|² ≈ 4·10³⁰ here)
/// and areas (|e₁ × e₂|² ≈ 10⁶¹) and multiplies those again in the cotan weights, mass matrix
/// and Willmore energy; from 10¹⁵ all of that stays far inside f64's 1.8·10³⁰⁸, while a 1e300
/// coordinate is finite on input and overflows to infinity in its first squared length. It is
/// also where f64 still resolves 1/8 of a unit (below 2⁵³ ≈ 9·10¹⁵), and real models sit far
/// inside it (the Earth is 1.3·10¹⁰ mm across).
pub const MAX_COORDINATE: f64 = 1e15;

/// Upper bounds on what one upload may make Willow allocate.
///
/// They are "absurd input" guards, not performance tuning: a 10-million-face mesh is already
/// far beyond what a conformal flow step handles interactively. Checked before anything sized
/// from the input is allocated, so an upload claiming 4 billion vertices is an error, not an
/// out-of-memory abort.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Limits {
    /// Largest accepted file, in bytes.
    pub max_bytes: usize,
    /// Most vertices (as stored in the file, before welding).
    pub max_vertices: usize,
    /// Most triangles.
    pub max_faces: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            // 256 MiB: a 10M-face binary mesh is ~200 MB; text OBJ of 5M vertices about as much.
            max_bytes: 256 << 20,
            max_vertices: 5_000_000,
            max_faces: 10_000_000,
        }
    }
}

impl Limits {
    /// Refuses a body larger than `max_bytes`; the API layers call it on Content-Length before
    /// buffering an upload.
    pub fn check_bytes(&self, bytes: usize) -> Result<(), MeshError> {
        check_limit("bytes", bytes, self.max_bytes)
    }

    pub fn check_vertices(&self, vertices: usize) -> Result<(), MeshError> {
        check_limit("vertices", vertices, self.max_vertices)
    }

    pub fn check_faces(&self, faces: usize) -> Result<(), MeshError> {
        check_limit("faces", faces, self.max_faces)
    }
}

fn check_limit(what: &'static str, value: usize, limit: usize) -> Result<(), MeshError> {
    if value > limit {
        Err(MeshError::TooLarge { what, value, limit })
    } else {
        Ok(())
    }
}

impl Mesh {
    /// Validates an indexed triangle list and orients it, under the default [`Limits`].
    ///
    /// On success every triangle has three distinct in-range vertices and non-zero area, every
    /// vertex is used, every edge has one or two faces, every vertex has a single fan of faces,
    /// and faces are wound consistently within each connected component. Closed components are
    /// wound outward (positive signed volume), so the mean curvature of an outward sphere is
    /// positive; open components keep the winding most of their input faces had.
    ///
    /// ```
    /// use willow::mesh::Mesh;
    /// // A tetrahedron with every face wound inward comes out wound outward.
    /// let p = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    /// let inward = vec![[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]];
    /// let m = Mesh::new(p, inward).unwrap();
    /// assert_eq!(m.triangles[0], [0, 2, 1]);
    /// ```
    pub fn new(positions: Vec<[f64; 3]>, triangles: Vec<[usize; 3]>) -> Result<Mesh, MeshError> {
        Mesh::with_limits(positions, triangles, &Limits::default())
    }

    /// [`Mesh::new`] with explicit size limits.
    pub fn with_limits(
        positions: Vec<[f64; 3]>,
        mut triangles: Vec<[usize; 3]>,
        limits: &Limits,
    ) -> Result<Mesh, MeshError> {
        check_basic(&positions, &triangles, limits)?;
        let table = EdgeTable::new(&triangles);
        check_manifold(positions.len(), &triangles, &table)?;
        orient(&positions, &mut triangles, &table)?;
        Ok(Mesh {
            positions,
            triangles,
        })
    }
}

/// Checks that need no connectivity: limits, emptiness, finiteness, index range, degeneracy
/// and unreferenced vertices.
fn check_basic(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    limits: &Limits,
) -> Result<(), MeshError> {
    if positions.is_empty() || triangles.is_empty() {
        return Err(MeshError::Empty {
            vertices: positions.len(),
            faces: triangles.len(),
        });
    }
    limits.check_vertices(positions.len())?;
    limits.check_faces(triangles.len())?;

    let mut non_finite = Offenders::default();
    for (v, p) in positions.iter().enumerate() {
        if !p.iter().all(|x| x.is_finite()) {
            non_finite.push(v);
        }
    }
    if !non_finite.is_empty() {
        return Err(MeshError::NonFinite {
            vertices: non_finite,
        });
    }
    let mut huge = Offenders::default();
    for (v, p) in positions.iter().enumerate() {
        if p.iter().any(|x| x.abs() > MAX_COORDINATE) {
            huge.push(v);
        }
    }
    if !huge.is_empty() {
        return Err(MeshError::CoordinateOutOfRange {
            vertices: huge,
            limit: MAX_COORDINATE,
        });
    }

    let n = positions.len();
    let mut out_of_range = Offenders::default();
    for (f, t) in triangles.iter().enumerate() {
        if t.iter().any(|&v| v >= n) {
            out_of_range.push(f);
        }
    }
    if !out_of_range.is_empty() {
        return Err(MeshError::IndexOutOfRange {
            faces: out_of_range,
            vertex_count: n,
        });
    }

    let mut degenerate = Offenders::default();
    for (f, &[a, b, c]) in triangles.iter().enumerate() {
        if a == b || b == c || c == a || cross(positions[a], positions[b], positions[c]) == [0.0; 3]
        {
            degenerate.push(f);
        }
    }
    if !degenerate.is_empty() {
        return Err(MeshError::DegenerateFaces { faces: degenerate });
    }

    let mut used = vec![false; n];
    for t in triangles {
        for &v in t {
            used[v] = true;
        }
    }
    let mut unused = Offenders::default();
    for (v, &u) in used.iter().enumerate() {
        if !u {
            unused.push(v);
        }
    }
    if !unused.is_empty() {
        return Err(MeshError::UnreferencedVertices { vertices: unused });
    }
    Ok(())
}

/// `(b − a) × (c − a)`: twice the area vector. Exactly zero only for truly degenerate faces;
/// slivers with tiny but non-zero area pass (nefertiti has angles of 0.06°).
fn cross(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let w = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    [
        u[1] * w[2] - u[2] * w[1],
        u[2] * w[0] - u[0] * w[2],
        u[0] * w[1] - u[1] * w[0],
    ]
}

/// Refuses edges with more than two faces and vertices whose faces form several fans.
///
/// Fans are found with a union–find over corners: the two corners at vertex `v` of faces
/// sharing an edge through `v` are joined. A manifold vertex ends with one class of corners.
fn check_manifold(
    vertex_count: usize,
    triangles: &[[usize; 3]],
    table: &EdgeTable,
) -> Result<(), MeshError> {
    let mut bad_edges = Offenders::default();
    for (e, edge) in table.edges.iter().enumerate() {
        if table.faces_of(e).len() > 2 {
            bad_edges.push(*edge);
        }
    }
    if !bad_edges.is_empty() {
        return Err(MeshError::NonManifoldEdges { edges: bad_edges });
    }

    let mut parent: Vec<usize> = (0..triangles.len() * 3).collect();
    let corner_of = |f: usize, v: usize| -> usize {
        let t = triangles[f];
        // `v` is a vertex of `f` because `f` lies on an edge through `v`.
        let k = t.iter().position(|&x| x == v).unwrap_or(0);
        3 * f + k
    };
    for (e, &[a, b]) in table.edges.iter().enumerate() {
        if let [hf, hg] = table.faces_of(e) {
            for v in [a, b] {
                union(&mut parent, corner_of(hf / 3, v), corner_of(hg / 3, v));
            }
        }
    }
    let mut first_class = vec![usize::MAX; vertex_count];
    let mut flagged = vec![false; vertex_count];
    for (f, t) in triangles.iter().enumerate() {
        for (k, &v) in t.iter().enumerate() {
            let root = find(&mut parent, 3 * f + k);
            if first_class[v] == usize::MAX {
                first_class[v] = root;
            } else if first_class[v] != root {
                flagged[v] = true;
            }
        }
    }
    let mut bad_vertices = Offenders::default();
    for (v, &bad) in flagged.iter().enumerate() {
        if bad {
            bad_vertices.push(v);
        }
    }
    if !bad_vertices.is_empty() {
        return Err(MeshError::NonManifoldVertices {
            vertices: bad_vertices,
        });
    }
    Ok(())
}

fn find(parent: &mut [usize], mut x: usize) -> usize {
    while parent[x] != x {
        parent[x] = parent[parent[x]]; // path halving
        x = parent[x];
    }
    x
}

fn union(parent: &mut [usize], a: usize, b: usize) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    if ra != rb {
        parent[ra.max(rb)] = ra.min(rb);
    }
}

/// Winds every face consistently within its component, outward for closed components.
///
/// Breadth-first from the lowest face of each component: a neighbour must traverse the shared
/// edge in the opposite direction, so it is flipped if needed; meeting an already placed face
/// that disagrees means no consistent winding exists (a Möbius strip).
fn orient(
    positions: &[[f64; 3]],
    triangles: &mut [[usize; 3]],
    table: &EdgeTable,
) -> Result<(), MeshError> {
    // `forward(f, k)`: does face f's edge k run from the lower to the higher vertex index?
    let forward = |t: &[usize; 3], k: u8| t[k as usize] < t[(k as usize + 1) % 3];
    let face_count = triangles.len();
    let mut placed = vec![false; face_count];
    let mut flip = vec![false; face_count];
    let mut queue = std::collections::VecDeque::new();
    let mut component = 0usize;
    for seed in 0..face_count {
        if placed[seed] {
            continue;
        }
        placed[seed] = true;
        queue.push_back(seed);
        let mut faces = vec![seed];
        let mut closed = true;
        while let Some(f) = queue.pop_front() {
            for k in 0..3u8 {
                let e = table.face_edges[f][k as usize];
                let around = table.faces_of(e);
                if around.len() < 2 {
                    closed = false;
                }
                let f_forward = forward(&triangles[f], k) ^ flip[f];
                for (g, kg) in around.iter().map(|&h| EdgeTable::face_corner(h)) {
                    if g == f {
                        continue;
                    }
                    let g_forward = forward(&triangles[g], kg);
                    // Consistent when the two faces run the edge in opposite directions.
                    let g_flip = g_forward == f_forward;
                    if !placed[g] {
                        placed[g] = true;
                        flip[g] = g_flip;
                        faces.push(g);
                        queue.push_back(g);
                    } else if flip[g] != g_flip {
                        return Err(MeshError::NonOrientable { component, face: g });
                    }
                }
            }
        }

        let flipped = faces.iter().filter(|&&f| flip[f]).count();
        // Volume relative to a vertex of the component, not the origin, so a mesh far from
        // the origin does not lose the sign to cancellation.
        let volume = if closed {
            let o = positions[triangles[seed][0]];
            faces
                .iter()
                .map(|&f| {
                    let [a, b, c] = triangles[f];
                    let c_ = cross(positions[a], positions[b], positions[c]);
                    let d = sub(positions[a], o);
                    let v = d[0] * c_[0] + d[1] * c_[1] + d[2] * c_[2];
                    if flip[f] {
                        -v
                    } else {
                        v
                    }
                })
                .sum::<f64>()
        } else {
            0.0
        };
        let reverse_all = if volume != 0.0 {
            volume < 0.0
        } else {
            // Open (or volume-less) component: agree with the majority of the input faces.
            2 * flipped > faces.len()
        };
        for &f in &faces {
            if flip[f] != reverse_all {
                triangles[f].swap(1, 2);
            }
        }
        component += 1;
    }
    Ok(())
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
