//! The intrinsic Delaunay triangulation (iDT) of a surface mesh and the cotan Laplacian built
//! on it (Sharp, Soliman & Crane 2019, "Navigating intrinsic triangulations", §3–4; Bobenko &
//! Springborn 2007 for the Laplacian).
//!
//! The intrinsic metric is the one the current positions give the mesh: its edge lengths. Edges
//! that are not Delaunay (`cot α + cot β < 0` for the two angles opposite the edge) are flipped
//! *in that metric*: the new edge is the geodesic across the two triangles, with its length
//! from laying the pair out in the plane. Vertices, the surface and the output's connectivity
//! do not change; only the operator is built on the flipped triangulation. Its edge weights
//! `½(cot α + cot β)` are then non-negative, and it is still the P1 (Galerkin) Laplacian of
//! the same piecewise flat surface, so it keeps linear precision. Negative cotan weights across
//! the obtuse angles of slivers make them collapse under the conformal flow; what this operator
//! changes there is measured in docs/cheburashka-collapse.md (it is not the flow's default:
//! docs/algorithm.md §6b).
//!
//! Halfedge `3f + c` of face `f` is the one opposite corner `c`, from `tri[c+1]` to `tri[c+2]`,
//! as in [`super::corner_cotangents_into`]. Buffers are sized once; [`IntrinsicDelaunay::flip_to_delaunay`]
//! refills them in place (one pass per refresh of the geometry, no allocation).

use super::vec3::{norm, sub};

/// No twin: a boundary edge, or an edge of a non-manifold fan (never flipped).
const NONE: usize = usize::MAX;

/// An edge is Delaunay when `cot α + cot β ≥ −DELAUNAY_TOLERANCE` (dimensionless). A regular
/// grid's diagonals have exactly 0 and must not flip back and forth on rounding.
pub const DELAUNAY_TOLERANCE: f64 = 1e-10;

/// Flips per edge, at most, in one pass: the flip algorithm terminates (Sharp et al. 2019,
/// §3.3, after Indermitte et al. 2001); this bound only guards against rounding loops.
const MAX_FLIPS_PER_EDGE: usize = 10;

/// The intrinsic Delaunay triangulation of a fixed mesh under changing positions.
pub struct IntrinsicDelaunay {
    input_triangles: Vec<[usize; 3]>,
    input_twin: Vec<usize>,
    /// The intrinsic triangles (same count and faces' indices as the input; flipped faces hold
    /// other vertices).
    pub triangles: Vec<[usize; 3]>,
    twin: Vec<usize>,
    /// Intrinsic length of each halfedge.
    lengths: Vec<f64>,
    /// Cotangent of each intrinsic corner (as [`super::corner_cotangents_into`]).
    pub cotangents: Vec<[f64; 3]>,
    /// Faces a flip changed this pass.
    pub changed: Vec<bool>,
    flips: usize,
    stack: Vec<usize>,
    queued: Vec<bool>,
}

impl IntrinsicDelaunay {
    pub fn new(triangles: &[[usize; 3]]) -> Self {
        let nf = triangles.len();
        let twin = halfedge_twins(triangles);
        IntrinsicDelaunay {
            input_triangles: triangles.to_vec(),
            triangles: triangles.to_vec(),
            twin: twin.clone(),
            input_twin: twin,
            lengths: vec![0.0; 3 * nf],
            cotangents: vec![[0.0; 3]; nf],
            changed: vec![false; nf],
            flips: 0,
            stack: Vec::with_capacity(3 * nf),
            queued: vec![false; 3 * nf],
        }
    }

    /// How many flips the last pass made.
    pub fn flip_count(&self) -> usize {
        self.flips
    }

    /// Flip the input triangulation, in the metric of `positions`, until every interior edge
    /// is Delaunay. `cotangents` are the input's
    /// corner cotangents at these positions (from the vectors: more accurate on needles
    /// than from lengths, and bit-identical where nothing flips).
    pub fn flip_to_delaunay(&mut self, positions: &[[f64; 3]], cotangents: &[[f64; 3]]) {
        self.triangles.copy_from_slice(&self.input_triangles);
        self.twin.copy_from_slice(&self.input_twin);
        self.cotangents.copy_from_slice(cotangents);
        self.changed.fill(false);
        self.flips = 0;
        for (f, tri) in self.triangles.iter().enumerate() {
            for c in 0..3 {
                self.lengths[3 * f + c] = norm(sub(
                    positions[tri[(c + 2) % 3]],
                    positions[tri[(c + 1) % 3]],
                ));
            }
        }
        self.stack.clear();
        for h in 0..self.twin.len() {
            let t = self.twin[h];
            self.queued[h] = t != NONE && h < t;
            if self.queued[h] {
                self.stack.push(h);
            }
        }
        let max_flips = MAX_FLIPS_PER_EDGE * self.twin.len();
        while let Some(h) = self.stack.pop() {
            self.queued[h] = false;
            let t = self.twin[h];
            if t == NONE || t / 3 == h / 3 || self.flips >= max_flips {
                continue;
            }
            let (f, c, g, d) = (h / 3, h % 3, t / 3, t % 3);
            if self.cotangents[f][c] + self.cotangents[g][d] >= -DELAUNAY_TOLERANCE {
                continue;
            }
            self.flip(f, c, g, d);
            for k in [0, 2] {
                for face in [f, g] {
                    let e = 3 * face + k;
                    let te = self.twin[e];
                    if te != NONE {
                        let rep = e.min(te);
                        if !self.queued[rep] {
                            self.queued[rep] = true;
                            self.stack.push(rep);
                        }
                    }
                }
            }
        }
    }

    /// Flip the edge between faces `f` and `g`. Quad (counter-clockwise) `vc, a, vd, b` with
    /// `f = (vc, a, b)`, `g = (vd, b, a)` becomes `f = (vc, a, vd)`, `g = (vd, b, vc)`.
    /// `c` is the corner of `f` opposite the edge, `d` the corner of `g` opposite its twin.
    fn flip(&mut self, f: usize, c: usize, g: usize, d: usize) {
        let (vc, a, b) = (
            self.triangles[f][c],
            self.triangles[f][(c + 1) % 3],
            self.triangles[f][(c + 2) % 3],
        );
        let vd = self.triangles[g][d];
        // Lengths of the quad's sides, and the outer twins, before anything moves.
        let l_ab = self.lengths[3 * f + c];
        let (l_bvc, l_vca) = (
            self.lengths[3 * f + (c + 1) % 3],
            self.lengths[3 * f + (c + 2) % 3],
        );
        let (l_avd, l_vdb) = (
            self.lengths[3 * g + (d + 1) % 3],
            self.lengths[3 * g + (d + 2) % 3],
        );
        let diagonal = flipped_diagonal_length(l_ab, l_vca, l_bvc, l_avd, l_vdb);
        let (t_bvc, t_vca) = (
            self.twin[3 * f + (c + 1) % 3],
            self.twin[3 * f + (c + 2) % 3],
        );
        let (t_avd, t_vdb) = (
            self.twin[3 * g + (d + 1) % 3],
            self.twin[3 * g + (d + 2) % 3],
        );
        self.triangles[f] = [vc, a, vd];
        self.triangles[g] = [vd, b, vc];
        let set = |s: &mut Self, h: usize, len: f64, tw: usize| {
            s.lengths[h] = len;
            s.twin[h] = tw;
            if tw != NONE {
                s.twin[tw] = h;
            }
        };
        set(self, 3 * f, l_avd, t_avd);
        set(self, 3 * f + 2, l_vca, t_vca);
        set(self, 3 * g, l_bvc, t_bvc);
        set(self, 3 * g + 2, l_vdb, t_vdb);
        self.lengths[3 * f + 1] = diagonal;
        self.lengths[3 * g + 1] = diagonal;
        self.twin[3 * f + 1] = 3 * g + 1;
        self.twin[3 * g + 1] = 3 * f + 1;
        for face in [f, g] {
            let l = [
                self.lengths[3 * face],
                self.lengths[3 * face + 1],
                self.lengths[3 * face + 2],
            ];
            self.cotangents[face] = corner_cotangents_from_lengths(l);
            self.changed[face] = true;
        }
        self.flips += 1;
    }

    /// `½(cot α + cot β)` of every interior intrinsic edge, once per edge: the off-diagonal
    /// weights `−L_ij`, for tests and diagnostics. (A boundary edge's weight `½ cot α` can stay
    /// negative: it has no second triangle to flip with.)
    pub fn interior_edge_weights(&self) -> Vec<(usize, usize, f64)> {
        let mut out = Vec::new();
        for h in 0..self.twin.len() {
            let t = self.twin[h];
            if t != NONE && h < t {
                let (f, c) = (h / 3, h % 3);
                let tri = self.triangles[f];
                out.push((
                    tri[(c + 1) % 3],
                    tri[(c + 2) % 3],
                    0.5 * (self.cotangents[f][c] + self.cotangents[t / 3][t % 3]),
                ));
            }
        }
        out
    }
}

/// `twin[h]` of every halfedge (`3f + c`, opposite corner `c`): the halfedge of the other face
/// on the same edge, running the other way; [`NONE`] on a boundary edge, on an edge shared by
/// more than two faces and on two faces that disagree in orientation.
pub fn halfedge_twins(triangles: &[[usize; 3]]) -> Vec<usize> {
    let mut keyed: Vec<(usize, usize, usize)> = Vec::with_capacity(3 * triangles.len());
    for (f, tri) in triangles.iter().enumerate() {
        for c in 0..3 {
            let (a, b) = (tri[(c + 1) % 3], tri[(c + 2) % 3]);
            keyed.push((a.min(b), a.max(b), 3 * f + c));
        }
    }
    keyed.sort_unstable();
    let mut twin = vec![NONE; 3 * triangles.len()];
    let tail = |h: usize| triangles[h / 3][(h % 3 + 1) % 3];
    let mut start = 0;
    while start < keyed.len() {
        let mut end = start + 1;
        while end < keyed.len() && keyed[end].0 == keyed[start].0 && keyed[end].1 == keyed[start].1
        {
            end += 1;
        }
        if end - start == 2 {
            let (h, k) = (keyed[start].2, keyed[start + 1].2);
            if tail(h) != tail(k) {
                twin[h] = k;
                twin[k] = h;
            }
        }
        start = end;
    }
    twin
}

/// Area of a triangle from its side lengths (Heron's formula in the form that is stable for
/// needles: Kahan, "Miscalculating area and angles of a needle-like triangle", §2), the
/// radicand clamped at zero.
pub fn triangle_area_from_lengths(l: [f64; 3]) -> f64 {
    let mut s = l;
    s.sort_unstable_by(|x, y| y.total_cmp(x));
    let [a, b, c] = s;
    let r = (a + (b + c)) * (c - (a - b)) * (c + (a - b)) * (a + (b - c));
    0.25 * r.max(0.0).sqrt()
}

/// Cotangents of a triangle's corners from its side lengths, `l[c]` opposite corner `c`:
/// `cot θ_c = (l_{c+1}² + l_{c+2}² − l_c²) / 4A`. A degenerate triangle's area is floored as in
/// [`super::corner_cotangents_into`].
pub fn corner_cotangents_from_lengths(l: [f64; 3]) -> [f64; 3] {
    let area4 = 4.0 * triangle_area_from_lengths(l).max(f64::MIN_POSITIVE);
    let sq = [l[0] * l[0], l[1] * l[1], l[2] * l[2]];
    [
        (sq[1] + sq[2] - sq[0]) / area4,
        (sq[2] + sq[0] - sq[1]) / area4,
        (sq[0] + sq[1] - sq[2]) / area4,
    ]
}

/// Length of the new diagonal `vc–vd` when the edge `a–b` of the triangles `(vc, a, b)` and
/// `(vd, b, a)` is flipped: lay the pair out in the plane with `a` at the origin, `b` on the
/// x axis, `vc` above and `vd` below (Sharp et al. 2019, §3.2).
pub fn flipped_diagonal_length(l_ab: f64, l_vca: f64, l_bvc: f64, l_avd: f64, l_vdb: f64) -> f64 {
    let apex = |l_a: f64, l_b: f64| {
        let x = (l_ab * l_ab + l_a * l_a - l_b * l_b) / (2.0 * l_ab);
        (x, (l_a * l_a - x * x).max(0.0).sqrt())
    };
    let (xc, yc) = apex(l_vca, l_bvc);
    let (xd, yd) = apex(l_avd, l_vdb);
    ((xc - xd).powi(2) + (yc + yd).powi(2)).sqrt()
}

#[cfg(test)]
#[path = "intrinsic_tests.rs"]
mod tests;
