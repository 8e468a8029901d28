//! Sharp edges: the crease curves of a CAD part, found from the dihedral angles.
//!
//! Willmore flow rounds every crease by design (its energy is ∫H², and a crease is where H
//! concentrates), so a user who wants a part's edges kept names a *feature angle*: every
//! interior edge whose faces meet at more than it is a crease edge (the rule of CGAL's
//! `detect_sharp_edges`, VTK's `feature_angle`, MeshLab's `normalthr`). Two refinements make
//! the default safe on organic meshes:
//! - crease edges are kept only in chains of at least [`MIN_CREASE_EDGES`] connected edges:
//!   a CAD crease runs the length of a part, while the few sharp edges of a scan (an ear tip,
//!   a scanner spike) stand alone;
//! - the angles are read off the surface the caller passes, which for noisy input is the
//!   denoised one, so noise makes no false creases.
//!
//! A vertex on a crease is a *crease vertex*; one where a crease ends or where several meet
//! (its crease-edge count is not 2) is a *corner*.

use crate::geometry::vec3::{cross, dot, norm, sub};
use crate::mesh::topology::Topology;
use serde::{Deserialize, Serialize};

/// The feature angle a job takes when it names none, degrees. Fandisk's creases run from 30°
/// to 90°, and a smooth surface at a scan's resolution bends by a few degrees per edge: 30°
/// (VTK's default) separates the two with room on both sides, while noise that survives
/// denoising stays far below it.
pub const DEFAULT_FEATURE_ANGLE: f64 = 30.0;

/// The fewest connected crease edges kept as a crease (see the module notes).
pub const MIN_CREASE_EDGES: usize = 8;

/// `auto` holds creases only on a surface at least this share of whose interior edges are
/// flat (dihedral below [`FLAT_DEGREES`]): a part, made of planes and developable patches.
/// Organic surfaces have sharp features too (cheburashka's ear rims, a statue's cut base), but
/// they bend everywhere. Measured share of flat edges: fandisk 0.82, the block 0.76, the
/// chamfered test cylinder 0.77, and after denoising their noisy copies 0.56 and 0.35; spot,
/// cheburashka, nefertiti, the bunnies, botijo, the duck 0.10–0.16, the denoised noisy bunny
/// and Nicolo 0.24–0.25 (Nicolo's clean original, flat-backed, 0.36: its 39 sharp edges of
/// 33° are held).
pub const PART_FLAT_SHARE: f64 = 0.3;

/// Below this dihedral angle an edge is flat, for [`PART_FLAT_SHARE`], degrees.
pub const FLAT_DEGREES: f64 = 1.0;

/// `auto` also wants a part's edges either nearly flat or creases: at most this share of
/// interior edges may bend by between a third of the angle and the angle (10–30°). A coarse
/// surface of revolution has flat quad diagonals too, but its rings bend by 10–30° each.
/// Measured: fandisk 0.013, the block 0.019, the test cylinder 0 (their denoised noisy copies
/// 0.007, 0.008); the denoised noisy bunny and Nicolo 0.037, 0.042; clean organic meshes
/// 0.11–0.47; tori of 24×12 to 64×32 0.33–0.42.
pub const PART_MAX_BENDING_SHARE: f64 = 0.025;

/// The sharpest turn a crease takes from one edge to the next, degrees: a part's creases are
/// straight or gently curved at its tessellation (a circle of 64 edges turns 5.6° an edge),
/// while a chain of sharp edges that zigzags across the triangles is no crease.
pub const MAX_TURN_DEGREES: f64 = 45.0;

/// Hysteresis (as Canny's edge detector has): an edge sharper than this fraction of the
/// feature angle belongs to a crease when it continues one, through edges of the same kind,
/// from an edge sharper than the angle itself. A denoised 45° chamfer keeps a few edges
/// at 25–30°, which would otherwise cut its crease into pieces; the flat and gently curved
/// parts between creases bend far less than this.
pub const WEAK_FRACTION: f64 = 2.0 / 3.0;

/// Which edges count as creases. Its serialized form is the text form of
/// [`FeatureAngle::parse`]: `"auto"`, `"none"`, or the angle as a number (`45`).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub enum FeatureAngle {
    /// [`DEFAULT_FEATURE_ANGLE`], on chains of [`MIN_CREASE_EDGES`] or more: the creases of
    /// parts that have them, nothing on organic meshes.
    #[default]
    Auto,
    /// No creases: the flow fairs across every edge.
    None,
    /// Edges sharper than this many degrees (0 < angle < 180), on chains of
    /// [`MIN_CREASE_EDGES`] or more.
    Degrees(f64),
}

impl FeatureAngle {
    /// The threshold in degrees, or `None` when creases are off.
    pub fn degrees(self) -> Option<f64> {
        match self {
            FeatureAngle::Auto => Some(DEFAULT_FEATURE_ANGLE),
            FeatureAngle::None => None,
            FeatureAngle::Degrees(d) => Some(d),
        }
    }

    /// `auto`, `none` (any case) or a number of degrees: the one text form, for the CLI and
    /// the query string.
    pub fn parse(text: &str) -> Result<FeatureAngle, String> {
        match text.trim().to_ascii_lowercase().as_str() {
            "auto" => Ok(FeatureAngle::Auto),
            "none" | "off" => Ok(FeatureAngle::None),
            t => t.parse::<f64>().map(FeatureAngle::Degrees).map_err(|_| {
                format!("expected `auto`, `none` or an angle in degrees, got `{text}`")
            }),
        }
    }

    /// Checks the angle: a finite number strictly between 0 and 180 degrees.
    pub fn validate(self) -> Result<(), String> {
        match self {
            FeatureAngle::Degrees(d) if !(d.is_finite() && d > 0.0 && d < 180.0) => Err(format!(
                "must be an angle in degrees between 0 and 180 (exclusive), `auto` or `none`, \
                 got {d}"
            )),
            _ => Ok(()),
        }
    }
}

impl Serialize for FeatureAngle {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            FeatureAngle::Auto => s.serialize_str("auto"),
            FeatureAngle::None => s.serialize_str("none"),
            FeatureAngle::Degrees(d) => s.serialize_f64(*d),
        }
    }
}

impl<'de> Deserialize<'de> for FeatureAngle {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Form<'a> {
            Number(f64),
            Text(std::borrow::Cow<'a, str>),
        }
        match Form::deserialize(d)? {
            Form::Number(x) => Ok(FeatureAngle::Degrees(x)),
            Form::Text(t) => FeatureAngle::parse(&t).map_err(serde::de::Error::custom),
        }
    }
}

/// The creases of one surface.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Creases {
    /// Crease edges, as indices into [`Topology::edges`], ascending.
    pub edges: Vec<usize>,
    /// Whether each vertex lies on a crease.
    pub vertices: Vec<bool>,
    /// Whether each vertex is a corner: on a crease, with a crease-edge count other than 2.
    pub corners: Vec<bool>,
}

impl Creases {
    /// No creases on a surface of `vertex_count` vertices.
    pub fn none(vertex_count: usize) -> Creases {
        Creases {
            edges: Vec::new(),
            vertices: vec![false; vertex_count],
            corners: vec![false; vertex_count],
        }
    }

    pub fn is_empty(&self) -> bool {
        self.edges.is_empty()
    }

    pub fn corner_count(&self) -> usize {
        self.corners.iter().filter(|&&c| c).count()
    }

    /// The crease edges as vertex pairs (for frames and pictures).
    pub fn vertex_pairs(&self, topology: &Topology) -> Vec<[usize; 2]> {
        self.edges.iter().map(|&e| topology.edges[e]).collect()
    }
}

/// The angle (degrees) between the normals of the two faces of every edge; 0 on a boundary
/// edge and where a face is degenerate (no normal to compare).
pub fn edge_dihedral_angles(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    topology: &Topology,
) -> Vec<f64> {
    let normal = |f: usize| {
        let [a, b, c] = triangles[f].map(|v| positions[v]);
        cross(sub(b, a), sub(c, a))
    };
    topology
        .edge_faces
        .iter()
        .map(|pair| match *pair {
            [Some(f), Some(g)] => {
                let (m, n) = (normal(f), normal(g));
                let lengths = norm(m) * norm(n);
                if lengths > 0.0 && lengths.is_finite() {
                    (dot(m, n) / lengths).clamp(-1.0, 1.0).acos().to_degrees()
                } else {
                    0.0
                }
            }
            _ => 0.0,
        })
        .collect()
}

/// The creases of a surface under `angle`: interior edges sharper than it, in smooth
/// chains of at least [`MIN_CREASE_EDGES`] such edges, and the edges sharper than
/// [`WEAK_FRACTION`] of it that continue those chains. Under [`FeatureAngle::Auto`], only on
/// a part ([`PART_FLAT_SHARE`]).
pub fn detect_creases(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    topology: &Topology,
    angle: FeatureAngle,
) -> Creases {
    let n = positions.len();
    let Some(threshold) = angle.degrees() else {
        return Creases::none(n);
    };
    let dihedral = edge_dihedral_angles(positions, triangles, topology);
    if angle == FeatureAngle::Auto && !looks_like_a_part(&dihedral, topology, threshold) {
        return Creases::none(n);
    }
    let candidates: Vec<usize> = (0..dihedral.len())
        .filter(|&e| dihedral[e] > threshold * WEAK_FRACTION)
        .collect();
    let strong: Vec<bool> = candidates
        .iter()
        .map(|&e| dihedral[e] > threshold)
        .collect();
    let kept = long_chains(
        &candidates,
        &strong,
        &topology.edges,
        positions,
        MIN_CREASE_EDGES,
    );
    let mut degree = vec![0u32; n];
    for &e in &kept {
        for v in topology.edges[e] {
            if let Some(d) = degree.get_mut(v) {
                *d += 1;
            }
        }
    }
    Creases {
        edges: kept,
        vertices: degree.iter().map(|&d| d > 0).collect(),
        corners: degree.iter().map(|&d| d > 0 && d != 2).collect(),
    }
}

/// Whether the interior edges' `dihedral` angles are a part's under `threshold`: at least
/// [`PART_FLAT_SHARE`] of them flat and at most [`PART_MAX_BENDING_SHARE`] between a third
/// of the threshold and the threshold.
pub fn looks_like_a_part(dihedral: &[f64], topology: &Topology, threshold: f64) -> bool {
    let interior: Vec<f64> = dihedral
        .iter()
        .zip(&topology.edge_faces)
        .filter(|(_, faces)| faces.iter().all(Option::is_some))
        .map(|(&d, _)| d)
        .collect();
    if interior.is_empty() {
        return false;
    }
    let share = |keep: &dyn Fn(f64) -> bool| {
        interior.iter().filter(|&&d| keep(d)).count() as f64 / interior.len() as f64
    };
    share(&|d| d < FLAT_DEGREES) >= PART_FLAT_SHARE
        && share(&|d| d > threshold / 3.0 && d <= threshold) <= PART_MAX_BENDING_SHARE
}

/// The edges of `sharp` in long, smooth crease segments, ascending. Two sharp edges continue
/// each other at a vertex with exactly two sharp edges, turning there by less than
/// [`MAX_TURN_DEGREES`]; a segment of edges continuing each other is kept when at least
/// `min_edges` of them are marked `strong` (one flag per edge of `sharp`). A CAD crease is a
/// curve from corner to corner; the sharp edges of an organic mesh (ridges of a coarse
/// tessellation, an ear's rim) branch and zigzag every few edges, so their segments stay short.
fn long_chains(
    sharp: &[usize],
    strong: &[bool],
    edges: &[[usize; 2]],
    positions: &[[f64; 3]],
    min_edges: usize,
) -> Vec<usize> {
    let n = positions.len();
    let valid = |e: usize| edges.get(e).is_some_and(|ends| ends.iter().all(|&v| v < n));
    // Per vertex: how many sharp edges meet there, and the first two (local indices).
    let mut degree = vec![0u32; n];
    let mut first_two = vec![[usize::MAX; 2]; n];
    for (i, &e) in sharp.iter().enumerate().filter(|&(_, &e)| valid(e)) {
        for v in edges[e] {
            if degree[v] < 2 {
                first_two[v][degree[v] as usize] = i;
            }
            degree[v] += 1;
        }
    }
    // Union-find over the sharp edges, joined where one continues another.
    let mut parent: Vec<usize> = (0..sharp.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let cos_max_turn = MAX_TURN_DEGREES.to_radians().cos();
    for v in (0..n).filter(|&v| degree[v] == 2) {
        let [i, j] = first_two[v];
        let other = |k: usize| {
            let [a, b] = edges[sharp[k]];
            if a == v {
                b
            } else {
                a
            }
        };
        let incoming = sub(positions[v], positions[other(i)]);
        let outgoing = sub(positions[other(j)], positions[v]);
        let lengths = norm(incoming) * norm(outgoing);
        if lengths > 0.0 && dot(incoming, outgoing) > cos_max_turn * lengths {
            let (ri, rj) = (root(&mut parent, i), root(&mut parent, j));
            if ri != rj {
                parent[ri] = rj;
            }
        }
    }
    let mut size = vec![0usize; sharp.len()];
    for i in 0..sharp.len() {
        if strong[i] && valid(sharp[i]) {
            let r = root(&mut parent, i);
            size[r] += 1;
        }
    }
    let mut kept: Vec<usize> = (0..sharp.len())
        .filter(|&i| valid(sharp[i]) && size[root(&mut parent, i)] >= min_edges)
        .map(|i| sharp[i])
        .collect();
    kept.sort_unstable();
    kept
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::icosphere;
    use crate::mesh::Mesh;

    /// A cube of side 1 with each face split into `k × k` squares of two triangles.
    pub(crate) fn cube(k: usize) -> Mesh {
        let mut positions: Vec<[f64; 3]> = Vec::new();
        let mut index = std::collections::HashMap::new();
        let mut triangles = Vec::new();
        let mut id = |p: [i64; 3], positions: &mut Vec<[f64; 3]>| {
            *index.entry(p).or_insert_with(|| {
                positions.push(p.map(|x| x as f64 / k as f64));
                positions.len() - 1
            })
        };
        let k = k as i64;
        // Each face: an axis, a side, and two in-plane axes ordered for an outward normal.
        for (axis, u, v) in [(0usize, 1usize, 2usize), (1, 2, 0), (2, 0, 1)] {
            for side in [0, k] {
                for i in 0..k {
                    for j in 0..k {
                        let corner = |di: i64, dj: i64| {
                            let mut p = [0i64; 3];
                            p[axis] = side;
                            p[u] = i + di;
                            p[v] = j + dj;
                            p
                        };
                        let q = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)]
                            .map(|p| id(p, &mut positions));
                        if side == k {
                            triangles.push([q[0], q[1], q[2]]);
                            triangles.push([q[0], q[2], q[3]]);
                        } else {
                            triangles.push([q[0], q[2], q[1]]);
                            triangles.push([q[0], q[3], q[2]]);
                        }
                    }
                }
            }
        }
        Mesh {
            positions,
            triangles,
        }
    }

    #[test]
    fn a_cube_has_twelve_creases_meeting_at_eight_corners() {
        // Each cube edge must be a crease on its own (its ends are corners): k ≥ 8.
        let k = 8;
        let mesh = cube(k);
        let topology = Topology::new(&mesh);
        let creases = detect_creases(
            &mesh.positions,
            &mesh.triangles,
            &topology,
            FeatureAngle::Auto,
        );
        // 12 edges of the cube, each split into k mesh edges, all at exactly 90°.
        assert_eq!(creases.edges.len(), 12 * k);
        assert_eq!(creases.corner_count(), 8);
        let on_crease = creases.vertices.iter().filter(|&&c| c).count();
        assert_eq!(on_crease, 12 * (k - 1) + 8);
        // The diagonals inside each face are flat: no crease.
        let angles = edge_dihedral_angles(&mesh.positions, &mesh.triangles, &topology);
        for &e in &creases.edges {
            assert!((angles[e] - 90.0).abs() < 1e-9, "{}", angles[e]);
        }
    }

    #[test]
    fn a_round_sphere_and_none_have_no_creases() {
        let mesh = icosphere(3);
        let topology = Topology::new(&mesh);
        let found = |a| detect_creases(&mesh.positions, &mesh.triangles, &topology, a);
        assert!(found(FeatureAngle::Auto).is_empty());
        // A coarse torus has flat quad diagonals like a part, but rings bending 15–30° an
        // edge: no part, no crease.
        let torus = crate::mesh::generate::torus(1.0, 0.4, 24, 12);
        let t = Topology::new(&torus);
        let on_torus = detect_creases(&torus.positions, &torus.triangles, &t, FeatureAngle::Auto);
        assert!(on_torus.is_empty(), "{}", on_torus.edges.len());
        // A feature angle below the sphere's per-edge bend makes every edge sharp, and so every
        // vertex a branch of six: no chain continues, no crease.
        let bend = edge_dihedral_angles(&mesh.positions, &mesh.triangles, &topology)
            .into_iter()
            .fold(f64::INFINITY, f64::min);
        let all = found(FeatureAngle::Degrees(bend * 0.5));
        assert!(all.is_empty(), "{}", all.edges.len());
        let cube = cube(3);
        let t = Topology::new(&cube);
        assert!(
            detect_creases(&cube.positions, &cube.triangles, &t, FeatureAngle::None).is_empty()
        );
    }

    #[test]
    fn short_chains_of_sharp_edges_are_not_creases() {
        // Two paths of sharp edges: 0-1-…-7 (7 edges) and 10-11-…-18 (8 edges); only the
        // longer one reaches MIN_CREASE_EDGES.
        let mut edges: Vec<[usize; 2]> = (0..7).map(|i| [i, i + 1]).collect();
        edges.extend((10..18).map(|i| [i, i + 1]));
        let sharp: Vec<usize> = (0..edges.len()).collect();
        let all_strong = vec![true; sharp.len()];
        let line: Vec<[f64; 3]> = (0..19).map(|i| [i as f64, 0.0, 0.0]).collect();
        assert_eq!(MIN_CREASE_EDGES, 8);
        assert_eq!(
            long_chains(&sharp, &all_strong, &edges, &line, MIN_CREASE_EDGES),
            (7..15).collect::<Vec<_>>()
        );
        // Joined at vertex 7 = 10 they are one chain of 15.
        edges[7] = [7, 11];
        assert_eq!(
            long_chains(&sharp, &all_strong, &edges, &line, MIN_CREASE_EDGES).len(),
            15
        );
        // Weak edges count toward no chain's length, but ride along with a long one.
        let mut weak = all_strong.clone();
        weak[3] = false;
        assert_eq!(
            long_chains(&sharp, &weak, &edges, &line, MIN_CREASE_EDGES).len(),
            15
        );
        let mut weak_short = vec![true; sharp.len()];
        for w in weak_short.iter_mut().skip(7) {
            *w = false;
        }
        assert!(long_chains(&sharp, &weak_short, &edges, &line, MIN_CREASE_EDGES).is_empty());
        // The same chain zigzagging (turning by 112° at every vertex) is no crease.
        let zigzag: Vec<[f64; 3]> = (0..19)
            .map(|i| [i as f64, (i % 2) as f64 * 1.5, 0.0])
            .collect();
        assert!(long_chains(&sharp, &all_strong, &edges, &zigzag, MIN_CREASE_EDGES).is_empty());
        // A third sharp edge at 7 (a spur 7–0, vertex 0 moved off the line) splits the chain
        // there: only 7–11–…–18, 8 edges, is long enough.
        edges.push([7, 0]);
        let mut with_spur = line.clone();
        with_spur[0] = [7.0, 5.0, 0.0];
        let sharp: Vec<usize> = (0..edges.len()).collect();
        let strong = vec![true; sharp.len()];
        assert_eq!(
            long_chains(&sharp, &strong, &edges, &with_spur, MIN_CREASE_EDGES),
            (7..15).collect::<Vec<_>>()
        );
    }

    #[test]
    fn the_text_forms_parse_and_bad_angles_are_refused() {
        assert_eq!(FeatureAngle::parse("AUTO"), Ok(FeatureAngle::Auto));
        assert_eq!(FeatureAngle::parse("none"), Ok(FeatureAngle::None));
        assert_eq!(FeatureAngle::parse("45"), Ok(FeatureAngle::Degrees(45.0)));
        assert!(FeatureAngle::parse("sharp").is_err());
        for bad in [0.0, 180.0, -5.0, f64::NAN, f64::INFINITY] {
            assert!(FeatureAngle::Degrees(bad).validate().is_err(), "{bad}");
        }
        assert!(FeatureAngle::Degrees(60.0).validate().is_ok());
        for (json, angle) in [
            ("\"auto\"", FeatureAngle::Auto),
            ("\"none\"", FeatureAngle::None),
            ("45.0", FeatureAngle::Degrees(45.0)),
        ] {
            assert_eq!(serde_json::from_str::<FeatureAngle>(json).ok(), Some(angle));
            assert_eq!(serde_json::to_string(&angle).ok().as_deref(), Some(json));
        }
        assert!(serde_json::from_str::<FeatureAngle>("\"sharp\"").is_err());
    }
}
