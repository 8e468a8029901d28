//! The test's own reading of the files and its own geometry, written here from the definitions
//! (no Willow function): OBJ `v`/`vt`/`f` lines, the GLB's POSITION accessor through the
//! `gltf` crate, the cotan Willmore energy, the normal jump across the region's border, folds,
//! and the quasi-conformal distortion Q of a triangle's affine map.

use std::collections::HashMap;

/// What a test needs of an OBJ file: its `v` lines (file order), its `vt` lines, and each
/// triangle's `v` and `vt` numbers (0-based), with the group (`g` name) it was under.
pub struct Obj {
    pub v: Vec<[f64; 3]>,
    pub vt: Vec<[f64; 2]>,
    pub faces: Vec<[usize; 3]>,
    pub face_vt: Vec<Option<[usize; 3]>>,
    pub face_group: Vec<String>,
}

/// Reads `v`, `vt`, `g` and triangular `f` lines; panics naming the line on anything else a
/// test file should not hold (the inputs are the test's own, the outputs the service's).
pub fn parse_obj(text: &str) -> Obj {
    let mut obj = Obj {
        v: Vec::new(),
        vt: Vec::new(),
        faces: Vec::new(),
        face_vt: Vec::new(),
        face_group: Vec::new(),
    };
    let mut group = String::new();
    for (n, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        let numbers = |words: std::str::SplitWhitespace| -> Vec<f64> {
            words
                .map(|w| {
                    w.parse()
                        .unwrap_or_else(|_| panic!("line {}: {line}", n + 1))
                })
                .collect()
        };
        match words.next() {
            Some("v") => {
                let c = numbers(words);
                obj.v.push([c[0], c[1], c[2]]);
            }
            Some("vt") => {
                let c = numbers(words);
                obj.vt.push([c[0], c[1]]);
            }
            Some("g") => group = words.collect::<Vec<_>>().join(" "),
            Some("f") => {
                let corners: Vec<(usize, Option<usize>)> = words
                    .map(|w| {
                        let mut parts = w.split('/');
                        let index = |p: Option<&str>| {
                            p.filter(|s| !s.is_empty()).map(|s| {
                                s.parse::<usize>()
                                    .unwrap_or_else(|_| panic!("line {}: {line}", n + 1))
                                    - 1
                            })
                        };
                        let v = index(parts.next()).unwrap_or_else(|| panic!("line {}", n + 1));
                        (v, index(parts.next()))
                    })
                    .collect();
                assert_eq!(corners.len(), 3, "line {}: not a triangle", n + 1);
                obj.faces.push([corners[0].0, corners[1].0, corners[2].0]);
                obj.face_vt
                    .push(match (corners[0].1, corners[1].1, corners[2].1) {
                        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
                        _ => None,
                    });
                obj.face_group.push(group.clone());
            }
            _ => {}
        }
    }
    obj
}

/// A GLB's mesh: its POSITION values (f32, as stored), its triangles, and the translation of
/// the node holding it (f64, as the JSON holds it: a model far from the origin is stored
/// relative to it).
pub struct Glb {
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[usize; 3]>,
    pub origin: [f64; 3],
}

pub fn parse_glb(bytes: &[u8]) -> Glb {
    let glb = gltf::Gltf::from_slice(bytes).expect("the result is a GLB");
    let blob = glb.blob.as_deref().expect("a GLB carries its BIN chunk");
    // The gltf crate keeps a node's translation as f32: read it from the JSON chunk (the
    // 12-byte header, the chunk's length and type, then the JSON).
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().expect("4 bytes")) as usize;
    let json: serde_json::Value =
        serde_json::from_slice(&bytes[20..20 + json_len]).expect("the GLB's JSON chunk");
    let mut out = Glb {
        positions: Vec::new(),
        triangles: Vec::new(),
        origin: [0.0; 3],
    };
    let mut meshes = 0;
    for node in glb.nodes() {
        let Some(mesh) = node.mesh() else { continue };
        meshes += 1;
        let (_, r, s) = node.transform().decomposed();
        assert_eq!(
            (r, s),
            ([0.0, 0.0, 0.0, 1.0], [1.0; 3]),
            "a bare translation at most"
        );
        if let Some(t) = json["nodes"][node.index()]["translation"].as_array() {
            out.origin = [0, 1, 2].map(|k| t[k].as_f64().expect("a number"));
        }
        for primitive in mesh.primitives() {
            let reader = primitive.reader(|_| Some(blob));
            let base = out.positions.len();
            out.positions
                .extend(reader.read_positions().expect("POSITION"));
            let indices: Vec<usize> = reader
                .read_indices()
                .expect("indices")
                .into_u32()
                .map(|i| base + i as usize)
                .collect();
            out.triangles
                .extend(indices.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
        }
    }
    assert_eq!(
        meshes, 1,
        "one mesh node (several would need their own origins)"
    );
    out
}

pub fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn unit_normal(p: &[[f64; 3]], t: [usize; 3]) -> [f64; 3] {
    let n = cross(sub(p[t[1]], p[t[0]]), sub(p[t[2]], p[t[0]]));
    let l = norm(n);
    [n[0] / l, n[1] / l, n[2] / l]
}

fn area(p: &[[f64; 3]], t: [usize; 3]) -> f64 {
    norm(cross(sub(p[t[1]], p[t[0]]), sub(p[t[2]], p[t[0]]))) / 2.0
}

/// Each undirected edge and the faces on it.
fn edge_faces(faces: &[[usize; 3]]) -> HashMap<(usize, usize), Vec<usize>> {
    let mut edges: HashMap<(usize, usize), Vec<usize>> = HashMap::new();
    for (f, t) in faces.iter().enumerate() {
        for c in 0..3 {
            let (a, b) = (t[c], t[(c + 1) % 3]);
            edges.entry((a.min(b), a.max(b))).or_default().push(f);
        }
    }
    edges
}

/// The discrete Willmore energy of the `region` vertices that are not on the mesh's boundary:
/// Σ |L p|² / (4 Aᵢ), with L p at i = ½ Σⱼ (cot αᵢⱼ + cot βᵢⱼ)(pᵢ − pⱼ) the integrated mean
/// curvature normal 2 H n Aᵢ (the cotan formula), and Aᵢ a third of the area of the faces
/// around i (barycentric). A round sphere gives 4π.
pub fn willmore(p: &[[f64; 3]], faces: &[[usize; 3]], region: &[bool]) -> f64 {
    let n = p.len();
    let mut lap = vec![[0.0; 3]; n];
    let mut a = vec![0.0; n];
    for &t in faces {
        let third = area(p, t) / 3.0;
        for c in 0..3 {
            a[t[c]] += third;
            // The angle at corner c is opposite the edge (c+1, c+2).
            let (i, j, k) = (t[c], t[(c + 1) % 3], t[(c + 2) % 3]);
            let (u, v) = (sub(p[j], p[i]), sub(p[k], p[i]));
            let cot = dot(u, v) / norm(cross(u, v));
            let d = sub(p[j], p[k]);
            for x in 0..3 {
                lap[j][x] += 0.5 * cot * d[x];
                lap[k][x] -= 0.5 * cot * d[x];
            }
        }
    }
    let mut on_boundary = vec![false; n];
    for ((u, v), fs) in edge_faces(faces) {
        if fs.len() == 1 {
            on_boundary[u] = true;
            on_boundary[v] = true;
        }
    }
    (0..n)
        .filter(|&i| region[i] && !on_boundary[i])
        .map(|i| dot(lap[i], lap[i]) / (4.0 * a[i]))
        .sum()
}

/// Mean angle (radians) between the normals of the two faces of each edge on the region's
/// border: one face with a corner in the region, the other with none.
pub fn border_normal_jump(p: &[[f64; 3]], faces: &[[usize; 3]], region: &[bool]) -> f64 {
    let touches = |f: usize| faces[f].iter().any(|&v| region[v]);
    let (mut sum, mut count) = (0.0, 0usize);
    for fs in edge_faces(faces).values() {
        if let [f, g] = fs[..] {
            if touches(f) != touches(g) {
                let c = dot(unit_normal(p, faces[f]), unit_normal(p, faces[g]));
                sum += c.clamp(-1.0, 1.0).acos();
                count += 1;
            }
        }
    }
    assert!(count > 0, "the region has no border edge");
    sum / count as f64
}

/// Faces with a corner in the region whose normal turned by more than 90° from the input's.
pub fn folds(
    before: &[[f64; 3]],
    after: &[[f64; 3]],
    faces: &[[usize; 3]],
    region: &[bool],
) -> usize {
    faces
        .iter()
        .filter(|t| t.iter().any(|&v| region[v]))
        .filter(|&&t| dot(unit_normal(before, t), unit_normal(after, t)) <= 0.0)
        .count()
}

/// The 2×2 matrix of a triangle's edge vectors e1 = b − a, e2 = c − a in an orthonormal frame
/// of its own plane (columns: e1, e2).
fn in_plane(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [[f64; 2]; 2] {
    let (e1, e2) = (sub(b, a), sub(c, a));
    let l1 = norm(e1);
    let u = e1.map(|x| x / l1);
    let w = cross(cross(e1, e2), e1);
    let lw = norm(w);
    let v = w.map(|x| x / lw);
    [[l1, dot(e2, u)], [0.0, dot(e2, v)]]
}

/// Q of the affine map sending triangle `from` onto triangle `to` (each a 2×2 edge matrix):
/// the ratio σ₁/σ₂ of the singular values of M = To · From⁻¹; 1 for a similarity.
fn q_of(from: [[f64; 2]; 2], to: [[f64; 2]; 2]) -> f64 {
    let det = from[0][0] * from[1][1] - from[0][1] * from[1][0];
    let inv = [
        [from[1][1] / det, -from[0][1] / det],
        [-from[1][0] / det, from[0][0] / det],
    ];
    let m = |r: usize, c: usize| to[r][0] * inv[0][c] + to[r][1] * inv[1][c];
    let (a, b, c, d) = (m(0, 0), m(0, 1), m(1, 0), m(1, 1));
    let fro2 = a * a + b * b + c * c + d * d;
    let det_m = (a * d - b * c).abs();
    let disc = (fro2 * fro2 - 4.0 * det_m * det_m).max(0.0).sqrt();
    ((fro2 + disc) / (fro2 - disc).max(f64::MIN_POSITIVE)).sqrt()
}

/// Mean (weighted by the input face's area) and max of Q over the faces with a corner in the region, for the map
/// from each face's triangle in `from` to the same face in `to` (3D positions).
pub fn q_between(
    from: &[[f64; 3]],
    to: &[[f64; 3]],
    faces: &[[usize; 3]],
    region: &[bool],
) -> (f64, f64) {
    weighted_q(faces, region, from, |f| {
        let t = faces[f];
        q_of(
            in_plane(from[t[0]], from[t[1]], from[t[2]]),
            in_plane(to[t[0]], to[t[1]], to[t[2]]),
        )
    })
}

/// The texture's Q: the map from each face's UV triangle to its 3D triangle in `p`, as mean
/// (weighted by the input face's area, `obj` being the input) and max over the faces with a
/// corner in the region.
pub fn q_texture(obj: &Obj, p: &[[f64; 3]], region: &[bool]) -> (f64, f64) {
    weighted_q(&obj.faces, region, &obj.v, |f| {
        let t = obj.faces[f];
        let uv = obj.face_vt[f].expect("every face has UVs");
        let lift = |k: usize| [obj.vt[uv[k]][0], obj.vt[uv[k]][1], 0.0];
        q_of(
            in_plane(lift(0), lift(1), lift(2)),
            in_plane(p[t[0]], p[t[1]], p[t[2]]),
        )
    })
}

fn weighted_q(
    faces: &[[usize; 3]],
    region: &[bool],
    p: &[[f64; 3]],
    q: impl Fn(usize) -> f64,
) -> (f64, f64) {
    let (mut sum, mut total, mut max) = (0.0, 0.0, 1.0f64);
    for (f, t) in faces.iter().enumerate() {
        if t.iter().any(|&v| region[v]) {
            let (qf, a) = (q(f), area(p, *t));
            sum += qf * a;
            total += a;
            max = max.max(qf);
        }
    }
    (sum / total, max)
}

/// A round sphere's W is 4π (the Willmore energy's minimum), whatever its tessellation (to
/// the discretization's error): the check of `willmore` itself.
#[test]
fn willmore_of_a_round_sphere_is_four_pi() {
    let sphere = willow::mesh::generate::icosphere(3);
    let region = vec![true; sphere.positions.len()];
    let w = willmore(&sphere.positions, &sphere.triangles, &region);
    assert!((w / (4.0 * std::f64::consts::PI) - 1.0).abs() < 0.01, "{w}");
}

/// Q of a similarity is 1, of a stretch by 2 along one axis is 2.
#[test]
fn q_of_a_similarity_and_of_a_stretch() {
    let from = in_plane([0.0; 3], [1.0, 0.0, 0.0], [0.3, 0.8, 0.0]);
    let rotated = in_plane([1.0, 1.0, 1.0], [1.0, 3.0, 1.0], [1.0, 1.6, 2.6]);
    assert!((q_of(from, rotated) - 1.0).abs() < 1e-12);
    let stretched = in_plane([0.0; 3], [2.0, 0.0, 0.0], [0.6, 0.8, 0.0]);
    assert!((q_of(from, stretched) - 2.0).abs() < 1e-12);
}
