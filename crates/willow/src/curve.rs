//! Isometric curvature flow of planar polylines (paper §5, Table 1 left column).
//!
//! The state is the polyline; the flow acts on its curvature κ and rebuilds positions from it:
//!
//! | Table 1 step | here |
//! |---|---|
//! | I. evaluate curvature | [`turning_angles`], [`curvature`]: κ_i = φ_i / ℓ*_i (§5.2) |
//! | II. flow direction | `v = −2κ` (§4 eq. 1–2; the gradient of `E_C = Σ κ_i² ℓ*_i`) |
//! | III. constraint basis | Gram–Schmidt of `{1, fˣ, fʸ}` in `⟨⟨·,·⟩⟩` (closed curves, §5, App. A): [`ConstraintBasis`] (reference MGS) |
//! | IV. project | [`project_out_closure_constraints`] (the same projection from moments; the flow uses this) |
//! | V. Euler step | `κ̃ = κ + τ v`, so unconstrained curvature decays as `(1 − 2τ)κ`, stable for τ < 1 |
//! | VI. tangents | [`tangent_angles`] (the cumulative sum of §5.2), [`tangents`] |
//! | VII. positions | [`divergence`] and [`CurvePoisson`]: `L f̃ = b` (§5.1–5.2) |
//!
//! The flow is *isometric*: the edge lengths ℓ of the **input** curve are the invariant. They
//! weight the curvature (dual lengths ℓ*), scale the new tangents and build the Poisson matrix,
//! which is therefore factored once per flow. Only the closed-curve constraints (the current
//! positions) and the turning angles change from step to step.
//!
//! Conventions:
//! - Vertices `0..n`; edge `i` goes from vertex `i` to `i + 1` (for a closed curve the last edge
//!   goes from `n − 1` back to `0`). An open curve has `n − 1` edges, a closed one `n`.
//! - φ_i is the signed turning angle at vertex i from edge `i − 1` to edge `i`, in (−π, π],
//!   positive for a left (counter-clockwise) turn; a counter-clockwise circle has κ = +1/r.
//! - The inner product on vertex functions is `⟨⟨a, b⟩⟩ = Σ a_i b_i ℓ*_i` (the discrete `∫ a b dl`).
//! - Open curves: the endpoints have no turning angle, so κ = 0 there and stays 0; no
//!   constraints apply (§5: "for open curves, the resulting flow can be integrated without
//!   modification"). The endpoints themselves are free and move as the curve straightens.
//! - Each step removes the mean change in position (vertex average) and in tangent angle
//!   (length-weighted average over edges), as §5.1 prescribes.
//! - κ is re-evaluated from the positions at the start of each step (Table 1 step I), with the
//!   input dual lengths, so closure errors do not accumulate in a separate curvature state.
//!
//! Cost: O(n) per step and no allocation. The Poisson factor is built once and solved from
//! both ends at once; the turning angles of the new curve are updated from the target ones by
//! an exact angle identity instead of an atan2 per vertex; the new tangents rotate the current
//! edges by their change of angle, with a short series instead of `sin_cos` when that change
//! is below π/4 ([`rotate_edges`]); the rest is about a dozen linear passes. Measured at 2 000
//! vertices (release, shared 2.5 GHz Xeon): about 0.08 ms per step once the curve has settled,
//! 0.12–0.14 ms for the first step of a very noisy curve (every edge turns by more than π/4).
//!
//! ```
//! use willow::curve::{Curve, CurveFlow, CurveParams};
//! // A wavy closed curve, r = 1 + 0.1 cos 3t, sampled at 100 points.
//! let points = (0..100)
//!     .map(|i| {
//!         let t = i as f64 * std::f64::consts::TAU / 100.0;
//!         let r = 1.0 + 0.1 * (3.0 * t).cos();
//!         [r * t.cos(), r * t.sin()]
//!     })
//!     .collect();
//! let curve = Curve::new(points, true)?;
//! let length = curve.length();
//! let mut flow = CurveFlow::new(curve, CurveParams::default())?;
//! for _ in 0..4 {
//!     flow.step();
//! }
//! let m = flow.last_metrics();
//! assert!(m.curvature_std_over_mean < 1e-2); // round
//! assert!((m.total_length / length - 1.0).abs() < 1e-3); // and as long as before
//! assert!((m.total_curvature - std::f64::consts::TAU).abs() < 1e-9); // turning number 1
//! # Ok::<(), willow::curve::CurveError>(())
//! ```

use serde::{Deserialize, Serialize};
use std::time::Instant;

/// An edge shorter than this fraction of the bounding-box diagonal counts as zero length: its
/// direction, hence the turning angles at its ends, would be rounding noise.
const ZERO_EDGE_RTOL: f64 = 1e-12;

/// A turning angle whose sine is below this (relative to the two edge lengths) while the edges
/// point in opposite directions is a cusp: the angle is ±π and its sign, hence the turning
/// number, is undefined.
const CUSP_SIN_RTOL: f64 = 1e-12;

/// A constraint function whose norm after orthogonalization falls below this fraction of its
/// norm before is linearly dependent on the earlier ones and is dropped (docs/algorithm.md §3).
const GRAM_SCHMIDT_DROP_RTOL: f64 = 1e-10;

/// OBJ `v` lines may carry a z coordinate; it must be 0 up to this fraction of the largest
/// |x|, |y| (or of 1, whichever is larger). Willow curves are planar, so a real z is an error
/// rather than something to drop silently.
const OBJ_Z_RTOL: f64 = 1e-9;

/// Why a curve or a curve flow could not be built.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum CurveError {
    /// A closed curve needs 3 points (a triangle), an open one 2 (a segment).
    #[error("a curve with closed = {closed} needs at least {min} points, got {got}")]
    TooFewPoints {
        closed: bool,
        min: usize,
        got: usize,
    },
    /// A coordinate is NaN or infinite.
    #[error("point {index} has a non-finite coordinate ({x}, {y})")]
    NonFinite { index: usize, x: f64, y: f64 },
    /// Edge `index` (from point `index` to the next, cyclically for closed curves) has zero
    /// length: two consecutive points coincide. A closed curve must not repeat its first point
    /// at the end.
    #[error(
        "edge {index} (point {index} to the next) has zero length: consecutive points coincide"
    )]
    ZeroLengthEdge { index: usize },
    /// The curve doubles back on itself at point `index` (turning angle ±π), so its curvature
    /// there and its turning number are undefined.
    #[error(
        "cusp at point {index}: the curve doubles back, so its turning angle (±π) is undefined"
    )]
    Cusp { index: usize },
    /// The JSON text is malformed or has the wrong shape.
    #[error("invalid JSON curve: {0}")]
    Json(String),
    /// The OBJ text is malformed, or is not a single planar polyline. `line` is 1-based; 0
    /// means the file as a whole.
    #[error("invalid OBJ curve (line {line}): {reason}")]
    Obj { line: usize, reason: String },
    /// A flow parameter is out of range.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    /// The working buffers of a flow could not be allocated.
    #[error("cannot allocate buffers for {points} points")]
    OutOfMemory { points: usize },
}

/// A planar polyline, open or closed. Build it with [`Curve::new`] (or the parsers), which
/// validates it; the fields are public for reading, and [`CurveFlow::new`] validates again.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Curve {
    /// Vertex positions in order. A closed curve does not repeat its first point at the end.
    pub points: Vec<[f64; 2]>,
    /// Whether an edge joins the last point back to the first.
    pub closed: bool,
}

/// The JSON object form of a curve: `{"points": [[x, y], ...], "closed": bool}`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CurveJson {
    points: Vec<[f64; 2]>,
    /// Missing means open, like a bare array.
    #[serde(default)]
    closed: bool,
}

impl Curve {
    /// Validate and wrap `points`. Errors, checked in this order: too few points, a non-finite
    /// coordinate, a zero-length edge, a cusp (see [`CurveError`]). Never panics.
    pub fn new(points: Vec<[f64; 2]>, closed: bool) -> Result<Curve, CurveError> {
        let curve = Curve { points, closed };
        curve.validate()?;
        Ok(curve)
    }

    /// Check the invariants [`Curve::new`] establishes (the fields are public, so a curve built
    /// by hand may break them).
    pub fn validate(&self) -> Result<(), CurveError> {
        let n = self.points.len();
        let min = if self.closed { 3 } else { 2 };
        if n < min {
            return Err(CurveError::TooFewPoints {
                closed: self.closed,
                min,
                got: n,
            });
        }
        for (index, p) in self.points.iter().enumerate() {
            if !(p[0].is_finite() && p[1].is_finite()) {
                return Err(CurveError::NonFinite {
                    index,
                    x: p[0],
                    y: p[1],
                });
            }
        }
        let (lo, hi) = bounding_box(&self.points);
        let diagonal = (hi[0] - lo[0]).hypot(hi[1] - lo[1]);
        let min_length = ZERO_EDGE_RTOL * diagonal;
        let m = edge_count(n, self.closed);
        for index in 0..m {
            let e = edge_vector(&self.points, index);
            if e[0].hypot(e[1]) <= min_length {
                return Err(CurveError::ZeroLengthEdge { index });
            }
        }
        for index in 0..n {
            if !self.closed && (index == 0 || index == n - 1) {
                continue;
            }
            let a = edge_vector(&self.points, (index + m - 1) % m);
            let b = edge_vector(&self.points, index);
            let cross = a[0] * b[1] - a[1] * b[0];
            let dot = a[0] * b[0] + a[1] * b[1];
            let scale = a[0].hypot(a[1]) * b[0].hypot(b[1]);
            if dot < 0.0 && cross.abs() <= CUSP_SIN_RTOL * scale {
                return Err(CurveError::Cusp { index });
            }
        }
        Ok(())
    }

    /// Number of edges: `n` for a closed curve, `n − 1` for an open one.
    pub fn edge_count(&self) -> usize {
        edge_count(self.points.len(), self.closed)
    }

    /// Edge lengths ℓ_{i,i+1}, edge `i` from point `i` to the next.
    pub fn edge_lengths(&self) -> Vec<f64> {
        let mut out = vec![0.0; self.edge_count()];
        edge_lengths(&self.points, self.closed, &mut out);
        out
    }

    /// Total length `Σ ℓ`.
    pub fn length(&self) -> f64 {
        self.edge_lengths().iter().sum()
    }

    /// Pointwise curvature κ_i = φ_i / ℓ*_i with this curve's own dual lengths (§5.2); 0 at
    /// the endpoints of an open curve.
    pub fn curvature(&self) -> Vec<f64> {
        let n = self.points.len();
        let lengths = self.edge_lengths();
        let mut dual = vec![0.0; n];
        dual_lengths(&lengths, self.closed, &mut dual);
        let mut phi = vec![0.0; n];
        turning_angles(&self.points, self.closed, &mut phi);
        let mut kappa = vec![0.0; n];
        curvature(&phi, &dual, &mut kappa);
        kappa
    }

    /// Total curvature `Σ φ_i = Σ κ_i ℓ*_i`: exactly `2π k` for a closed curve with turning
    /// number k (up to rounding).
    pub fn total_curvature(&self) -> f64 {
        let mut phi = vec![0.0; self.points.len()];
        turning_angles(&self.points, self.closed, &mut phi);
        phi.iter().sum()
    }

    /// Turning number `k = Σ φ / 2π` of a closed curve; `None` for an open one.
    pub fn turning_number(&self) -> Option<i64> {
        self.closed.then(|| turning_number(self.total_curvature()))
    }

    /// Parse `{"points": [[x, y], ...], "closed": bool}` (`closed` may be omitted: open) or a
    /// bare array `[[x, y], ...]`, which is an **open** polyline, like an OBJ `l` line that does
    /// not repeat its first index. Unknown fields are errors. The result is validated.
    pub fn from_json(bytes: &[u8]) -> Result<Curve, CurveError> {
        let first = bytes.iter().find(|b| !b.is_ascii_whitespace());
        let (points, closed) = match first {
            Some(b'[') => {
                let points: Vec<[f64; 2]> =
                    serde_json::from_slice(bytes).map_err(|e| CurveError::Json(e.to_string()))?;
                (points, false)
            }
            Some(b'{') => {
                let c: CurveJson =
                    serde_json::from_slice(bytes).map_err(|e| CurveError::Json(e.to_string()))?;
                (c.points, c.closed)
            }
            _ => {
                return Err(CurveError::Json(
                    "expected an object {\"points\": [[x, y], ...], \"closed\": bool} \
                     or an array of [x, y] points"
                        .to_string(),
                ))
            }
        };
        Curve::new(points, closed)
    }

    /// Write `{"points": [[x, y], ...], "closed": bool}` with the shortest round-tripping
    /// decimals. [`Curve::from_json`] reads it back to within an ulp, not always bit for bit:
    /// serde_json's default float parser is best effort (its `float_roundtrip` feature is off
    /// in this crate). Use OBJ for bit-exact round trips.
    pub fn to_json(&self) -> String {
        // Serializing a Vec of float pairs and a bool into a String cannot fail: there is no
        // I/O, no map with non-string keys, no custom Serialize. (Non-finite floats, possible
        // only in a hand-built invalid curve, become `null` rather than an error.)
        serde_json::to_string(self).expect("serializing plain floats into a String cannot fail")
    }

    /// Parse a Wavefront OBJ holding one polyline: `v x y [z [w]]` lines and exactly one `l`
    /// line of 1-based (or negative, relative) vertex indices; `l 1 2 3 1` (last index equal to
    /// the first) is a closed triangle. `z` must be 0 (up to 1e-9 of the largest |x|, |y|, or
    /// of 1): curves live in the xy-plane; `w` is ignored. Vertices the `l` line does not use are
    /// ignored; `vt/vn` suffixes on indices are ignored; `f` lines are errors (that is a mesh);
    /// other statements (`o`, `g`, `vt`, ...) and `#` comments are skipped. The result is
    /// validated.
    pub fn from_obj(bytes: &[u8]) -> Result<Curve, CurveError> {
        let mut vertices: Vec<[f64; 2]> = Vec::new();
        let mut max_xy: f64 = 0.0;
        // The largest |z| seen and its line, checked against the scale at the end.
        let mut worst_z: Option<(f64, usize)> = None;
        // The `l` line: its line number and its indices (0-based; positive ones are checked
        // against the vertex count at the end, since OBJ allows forward references).
        let mut polyline: Option<(usize, Vec<i64>)> = None;
        let obj_err = |line: usize, reason: String| CurveError::Obj { line, reason };

        for (i, raw) in bytes.split(|&b| b == b'\n').enumerate() {
            let line = i + 1;
            let text = std::str::from_utf8(raw)
                .map_err(|_| obj_err(line, "not valid UTF-8".to_string()))?;
            let text = text.split('#').next().unwrap_or("");
            let mut tokens = text.split_whitespace();
            let Some(keyword) = tokens.next() else {
                continue;
            };
            match keyword {
                "v" => {
                    let mut coords = [0.0f64; 4];
                    let mut count = 0;
                    for token in tokens {
                        if count == 4 {
                            return Err(obj_err(line, "`v` takes at most 4 numbers".into()));
                        }
                        coords[count] = token
                            .parse::<f64>()
                            .map_err(|_| obj_err(line, format!("`{token}` is not a number")))?;
                        count += 1;
                    }
                    if count < 2 {
                        return Err(obj_err(line, "`v` needs at least x and y".into()));
                    }
                    let z = coords[2];
                    if count >= 3 && (z != 0.0) && worst_z.is_none_or(|(w, _)| z.abs() > w) {
                        worst_z = Some((z.abs(), line));
                    }
                    if coords[0].is_finite() && coords[1].is_finite() {
                        max_xy = max_xy.max(coords[0].abs()).max(coords[1].abs());
                    }
                    vertices.push([coords[0], coords[1]]);
                }
                "l" => {
                    if let Some((first, _)) = polyline {
                        return Err(obj_err(
                            line,
                            format!(
                                "a second `l` line (the first is line {first}): a Willow curve \
                                 is a single polyline"
                            ),
                        ));
                    }
                    let mut indices = Vec::new();
                    for token in tokens {
                        let head = token.split('/').next().unwrap_or("");
                        let k: i64 = head.parse().map_err(|_| {
                            obj_err(line, format!("`{token}` is not a vertex index"))
                        })?;
                        let resolved = match k {
                            0 => {
                                return Err(obj_err(line, "vertex index 0 (OBJ is 1-based)".into()))
                            }
                            k if k > 0 => k - 1,
                            k => vertices.len() as i64 + k,
                        };
                        if resolved < 0 {
                            return Err(obj_err(
                                line,
                                format!("relative index {k} reaches before the first vertex"),
                            ));
                        }
                        indices.push(resolved);
                    }
                    if indices.len() < 2 {
                        return Err(obj_err(line, "`l` needs at least 2 vertex indices".into()));
                    }
                    polyline = Some((line, indices));
                }
                "f" => {
                    return Err(obj_err(
                        line,
                        "an `f` (face) line: this is a mesh, not a curve".into(),
                    ))
                }
                _ => {}
            }
        }

        if let Some((z, line)) = worst_z {
            if z.is_nan() || z > OBJ_Z_RTOL * max_xy.max(1.0) {
                return Err(obj_err(
                    line,
                    format!("z = {z} is not 0: Willow curves are planar (the xy-plane)"),
                ));
            }
        }
        let Some((l_line, mut indices)) = polyline else {
            return Err(obj_err(0, "no `l` line: expected one polyline".into()));
        };
        let closed = indices.len() >= 2 && indices.first() == indices.last();
        if closed {
            indices.pop();
        }
        let mut points = Vec::new();
        points
            .try_reserve_exact(indices.len())
            .map_err(|_| CurveError::OutOfMemory {
                points: indices.len(),
            })?;
        for &k in &indices {
            let p = usize::try_from(k)
                .ok()
                .and_then(|k| vertices.get(k))
                .ok_or_else(|| {
                    obj_err(
                        l_line,
                        format!(
                            "vertex index {} out of range (the file has {} vertices)",
                            k + 1,
                            vertices.len()
                        ),
                    )
                })?;
            points.push(*p);
        }
        Curve::new(points, closed)
    }

    /// Write `v x y 0` lines and one `l` line (repeating the first index at the end when
    /// closed); [`Curve::from_obj`] reads it back bit for bit.
    pub fn to_obj(&self) -> String {
        use std::fmt::Write;
        let n = self.points.len();
        let mut out = String::new();
        // Writing into a String cannot fail; the results are ignored for that reason.
        let _ = writeln!(
            out,
            "# willow curve: {n} points, {}",
            if self.closed { "closed" } else { "open" }
        );
        for p in &self.points {
            let _ = writeln!(out, "v {} {} 0", p[0], p[1]);
        }
        out.push('l');
        for k in 1..=n {
            let _ = write!(out, " {k}");
        }
        if self.closed && n > 0 {
            out.push_str(" 1");
        }
        out.push('\n');
        out
    }
}

/// Axis-aligned bounding box `(min, max)` of finite points.
fn bounding_box(points: &[[f64; 2]]) -> ([f64; 2], [f64; 2]) {
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for p in points {
        for c in 0..2 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    (lo, hi)
}

/// Edge vector `T_i = f_{i+1} − f_i` (cyclic index for the closing edge).
#[inline]
fn edge_vector(points: &[[f64; 2]], i: usize) -> [f64; 2] {
    let a = points[i];
    let b = points[if i + 1 == points.len() { 0 } else { i + 1 }];
    [b[0] - a[0], b[1] - a[1]]
}

/// Number of edges of a polyline with `point_count` points: `n` if closed, `n − 1` if open.
pub fn edge_count(point_count: usize, closed: bool) -> usize {
    if closed {
        point_count
    } else {
        point_count.saturating_sub(1)
    }
}

/// Turning number `round(total_curvature / 2π)`.
pub fn turning_number(total_curvature: f64) -> i64 {
    (total_curvature / std::f64::consts::TAU).round() as i64
}

/// Edge lengths `ℓ_{i,i+1} = |f_{i+1} − f_i|` (§5.2) into `out` (length [`edge_count`]).
pub fn edge_lengths(points: &[[f64; 2]], closed: bool, out: &mut [f64]) {
    debug_assert_eq!(out.len(), edge_count(points.len(), closed));
    for (l, w) in out.iter_mut().zip(points.windows(2)) {
        let e = [w[1][0] - w[0][0], w[1][1] - w[0][1]];
        *l = (e[0] * e[0] + e[1] * e[1]).sqrt();
    }
    if closed && !points.is_empty() {
        let e = edge_vector(points, points.len() - 1);
        out[points.len() - 1] = (e[0] * e[0] + e[1] * e[1]).sqrt();
    }
}

/// Dual lengths `ℓ*_i = ½(ℓ_{i−1,i} + ℓ_{i,i+1})` (§5.2), the length element of the vertex
/// inner product `⟨⟨a, b⟩⟩ = Σ a_i b_i ℓ*_i`. An open curve's endpoints get half of their one
/// edge, so `Σ ℓ* = Σ ℓ` in both cases. `out` has one entry per vertex.
pub fn dual_lengths(edge_lengths: &[f64], closed: bool, out: &mut [f64]) {
    let n = out.len();
    let m = edge_lengths.len();
    debug_assert_eq!(m, edge_count(n, closed));
    for (i, d) in out.iter_mut().enumerate() {
        let before = if i > 0 {
            edge_lengths[i - 1]
        } else if closed {
            edge_lengths[m - 1]
        } else {
            0.0
        };
        let after = if i < m { edge_lengths[i] } else { 0.0 };
        *d = 0.5 * (before + after);
    }
}

/// Signed turning angles `φ_i = atan2(T_{i−1} × T_i, T_{i−1} · T_i) ∈ (−π, π]` from edge
/// `i − 1` to edge `i`, positive for a counter-clockwise turn (§5.2: `φ_i = κ_i ℓ*_i` is the
/// exterior angle). An open curve's endpoints get 0. For a closed curve `Σ φ = 2π k` exactly,
/// k the turning number.
pub fn turning_angles(points: &[[f64; 2]], closed: bool, out: &mut [f64]) {
    let n = points.len();
    debug_assert_eq!(out.len(), n);
    if n < 2 {
        out.fill(0.0);
        return;
    }
    let (first, last) = if closed { (0, n) } else { (1, n - 1) };
    if !closed {
        out[0] = 0.0;
        out[n - 1] = 0.0;
    }
    // `prev` is the edge into vertex i; walking forward reuses each edge vector once.
    let mut prev = edge_vector(points, if first == 0 { n - 1 } else { first - 1 });
    for (i, phi) in out.iter_mut().enumerate().take(last).skip(first) {
        let next = edge_vector(points, i);
        let cross = prev[0] * next[1] - prev[1] * next[0];
        let dot = prev[0] * next[0] + prev[1] * next[1];
        *phi = cross.atan2(dot);
        prev = next;
    }
}

/// Pointwise curvature `κ_i = φ_i / ℓ*_i` (§5.2: turning angle over dual length).
pub fn curvature(turning_angles: &[f64], dual_lengths: &[f64], out: &mut [f64]) {
    for ((k, &phi), &d) in out.iter_mut().zip(turning_angles).zip(dual_lengths) {
        *k = phi / d;
    }
}

/// Weighted inner product `⟨⟨a, b⟩⟩ = Σ a_i b_i ℓ*_i` (§4, §5), the discrete `∫ a b dl`.
#[inline]
pub fn dual_inner(a: &[f64], b: &[f64], dual_lengths: &[f64]) -> f64 {
    let n = a.len().min(b.len()).min(dual_lengths.len());
    let (a, b, w) = (&a[..n], &b[..n], &dual_lengths[..n]);
    sum4(n, |i| a[i] * b[i] * w[i])
}

/// Curve fairing energy `E_C = Σ κ_i² ℓ*_i = ‖κ‖²` (§5).
pub fn curvature_energy(kappa: &[f64], dual_lengths: &[f64]) -> f64 {
    dual_inner(kappa, kappa, dual_lengths)
}

/// Length-weighted standard deviation of κ over its length-weighted mean, `σ(κ) / |κ̄|`:
/// 0 for a circle. A straight curve (σ = 0) gives 0; a curve with κ̄ = 0 but σ > 0 (an open
/// wiggle, a figure-eight) gives `+∞`.
pub fn curvature_std_over_mean(kappa: &[f64], dual_lengths: &[f64]) -> f64 {
    let n = kappa.len().min(dual_lengths.len());
    let (k, w) = (&kappa[..n], &dual_lengths[..n]);
    let total = sum4(n, |i| w[i]);
    let mean = sum4(n, |i| w[i] * k[i]) / total;
    // Two passes: `E/L − κ̄²` would cancel catastrophically near a circle, where σ/κ̄ ~ 1e-8.
    let variance = sum4(n, |i| w[i] * (k[i] - mean) * (k[i] - mean)) / total;
    let std = variance.sqrt();
    if std == 0.0 {
        0.0
    } else {
        std / mean.abs()
    }
}

/// Orthonormal basis (in `⟨⟨·,·⟩⟩`) of the closed-curve constraint functions `{1, fˣ, fʸ}`
/// (§5, Appendix A): the flow keeps `∫ κ̇ dl = 0` (tangents close up: total curvature stays
/// `2πk`) and `∫ κ̇ f dl = 0` (positions close up, to first order). Built by modified
/// Gram–Schmidt in that order (Table 1 step III); buffers are allocated once.
#[derive(Clone, Debug)]
pub struct ConstraintBasis {
    vectors: [Vec<f64>; 3],
    len: usize,
}

impl ConstraintBasis {
    /// Buffers for curves of `n` vertices, fallibly allocated.
    pub fn with_len(n: usize) -> Result<Self, CurveError> {
        Ok(ConstraintBasis {
            vectors: [zeroed(n)?, zeroed(n)?, zeroed(n)?],
            len: 0,
        })
    }

    /// Refill from the current positions (Table 1 step III). A function that is (numerically)
    /// in the span of the earlier ones is dropped (relative norm below 1e-10), which cannot
    /// happen for a valid closed curve but keeps the projection exact if it does.
    pub fn rebuild(&mut self, points: &[[f64; 2]], dual_lengths: &[f64]) {
        self.len = 0;
        for candidate in 0..3 {
            let (done, rest) = self.vectors.split_at_mut(self.len);
            let c = &mut rest[0];
            for (ci, p) in c.iter_mut().zip(points) {
                *ci = match candidate {
                    0 => 1.0,
                    1 => p[0],
                    _ => p[1],
                };
            }
            let before = dual_inner(c, c, dual_lengths).sqrt();
            for q in done.iter() {
                let a = dual_inner(c, q, dual_lengths);
                for (ci, qi) in c.iter_mut().zip(q) {
                    *ci -= a * qi;
                }
            }
            let after = dual_inner(c, c, dual_lengths).sqrt();
            if after > GRAM_SCHMIDT_DROP_RTOL * before {
                let inv = 1.0 / after;
                c.iter_mut().for_each(|ci| *ci *= inv);
                self.len += 1;
            }
        }
    }

    /// Number of basis functions kept (3 for any valid closed curve).
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether no function was kept (only before the first [`ConstraintBasis::rebuild`]).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The i-th orthonormal function.
    pub fn vector(&self, i: usize) -> &[f64] {
        &self.vectors[i][..]
    }

    /// `v ← v − Σ_i ⟨⟨v, ĉ_i⟩⟩ ĉ_i` (§4; Table 1 step IV), applied one function at a time.
    pub fn project_out(&self, v: &mut [f64], dual_lengths: &[f64]) {
        for q in &self.vectors[..self.len] {
            let a = dual_inner(v, q, dual_lengths);
            for (vi, qi) in v.iter_mut().zip(q) {
                *vi -= a * qi;
            }
        }
    }
}

/// Table 1 steps III–IV for a closed curve in closed form: `v ← v − Σ ⟨⟨v, ĉ_i⟩⟩ ĉ_i` with
/// `{ĉ_i}` the Gram–Schmidt orthonormalization of `{1, fˣ, fʸ}` in that order, as
/// [`ConstraintBasis`] builds it, but from weighted moments instead of stored basis vectors:
///
/// - `ĉ_0 = 1/√L` (L = Σ ℓ*);
/// - `ĉ_1 = x̂/σ_x` with the centred `x̂ = fˣ − x̄`, `σ_x² = ⟨⟨x̂, x̂⟩⟩`;
/// - `ĉ_2 = (ŷ − β x̂)/σ_2` with `β = ⟨⟨ŷ, x̂⟩⟩/σ_x²`, `σ_2² = ⟨⟨ŷ, ŷ⟩⟩ − β ⟨⟨ŷ, x̂⟩⟩`.
///
/// Three passes (means; centred moments; update) instead of about twenty. Centring first
/// keeps the moments free of the cancellation `Σ x² − L x̄²` would suffer far from the origin.
/// A function whose norm falls below 1e-10 of its centred size is skipped, as in
/// [`ConstraintBasis::rebuild`]. The tests check this against [`ConstraintBasis`].
pub fn project_out_closure_constraints(points: &[[f64; 2]], dual_lengths: &[f64], v: &mut [f64]) {
    let n = points.len().min(dual_lengths.len()).min(v.len());
    if n == 0 {
        return;
    }
    let (p, w, v) = (&points[..n], &dual_lengths[..n], &mut v[..n]);
    // Pass 1: L and the weighted means. Pass 2: the six centred moments, each its own
    // accumulator, so the additions overlap.
    let (mut total, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for (q, wi) in p.iter().zip(w) {
        total += wi;
        sx += wi * q[0];
        sy += wi * q[1];
    }
    let (mx, my) = (sx / total, sy / total);
    let (mut sxx, mut sxy, mut syy, mut sv, mut svx, mut svy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for ((q, wi), vi) in p.iter().zip(w).zip(v.iter()) {
        let (x, y) = (q[0] - mx, q[1] - my);
        let (wx, wy, wv) = (wi * x, wi * y, wi * vi);
        sxx += wx * x;
        sxy += wx * y;
        syy += wy * y;
        sv += wv;
        svx += wv * x;
        svy += wv * y;
    }
    // v −= a_0 + a_x x̂ + a_y ŷ, collecting the three projections.
    let a0 = sv / total;
    let (mut ax, mut ay) = (0.0, 0.0);
    if sxx > (GRAM_SCHMIDT_DROP_RTOL * GRAM_SCHMIDT_DROP_RTOL) * (sxx + syy) {
        // ⟨⟨v, ĉ_1⟩⟩ ĉ_1 = (svx/sxx) x̂.
        ax = svx / sxx;
        let beta = sxy / sxx;
        let s2 = syy - beta * sxy;
        if s2 > (GRAM_SCHMIDT_DROP_RTOL * GRAM_SCHMIDT_DROP_RTOL) * syy {
            // ⟨⟨v, ŷ − βx̂⟩⟩/σ_2² · (ŷ − βx̂).
            let c = (svy - beta * svx) / s2;
            ay = c;
            ax -= c * beta;
        }
    } else if syy > 0.0 {
        ay = svy / syy;
    }
    for (vi, q) in v.iter_mut().zip(p) {
        *vi -= a0 + ax * (q[0] - mx) + ay * (q[1] - my);
    }
}

/// Edge tangent angles by the cumulative sum of §5.2,
/// `θ_k = θ_0 + Σ_{i=1}^{k} ½(ℓ_{i−1,i} + ℓ_{i,i+1}) κ_i` for `k = 0..out.len()` (one per
/// edge; the angle of edge k, from vertex k to k + 1). For a closed curve vertex 0's curvature
/// does not enter: it is the closing turn, fixed by the total curvature.
pub fn tangent_angles(theta0: f64, kappa: &[f64], dual_lengths: &[f64], out: &mut [f64]) {
    let mut theta = theta0;
    for (k, t) in out.iter_mut().enumerate() {
        if k > 0 {
            theta += dual_lengths[k] * kappa[k];
        }
        *t = theta;
    }
}

/// New edge vectors `T̃_ij = ℓ_ij (cos θ_i, sin θ_i)` (§5.2) with the input lengths ℓ.
pub fn tangents(theta: &[f64], edge_lengths: &[f64], out: &mut [[f64; 2]]) {
    for ((t, &th), &l) in out.iter_mut().zip(theta).zip(edge_lengths) {
        let (s, c) = th.sin_cos();
        *t = [l * c, l * s];
    }
}

/// Discrete divergence `b_i = T̃_{i−1,i}/ℓ_{i−1,i} − T̃_{i,i+1}/ℓ_{i,i+1}` (§5.2), the right-hand
/// side of `L f̃ = b`; an open curve's endpoints keep only their one edge. `Σ b = 0` in both
/// cases, so the singular system is consistent. `inv_edge_lengths` holds `1/ℓ`.
pub fn divergence(
    tangents: &[[f64; 2]],
    inv_edge_lengths: &[f64],
    closed: bool,
    out: &mut [[f64; 2]],
) {
    let n = out.len();
    let m = tangents.len();
    debug_assert_eq!(m, edge_count(n, closed));
    if n == 0 || m == 0 {
        out.fill([0.0, 0.0]);
        return;
    }
    let unit = |e: usize| {
        [
            tangents[e][0] * inv_edge_lengths[e],
            tangents[e][1] * inv_edge_lengths[e],
        ]
    };
    // Interior vertices 1..m have an edge on both sides; vertex 0 and, for open curves,
    // vertex n − 1 are handled after.
    let mut before = unit(0);
    for (i, b) in out.iter_mut().enumerate().take(m).skip(1) {
        let after = unit(i);
        *b = [before[0] - after[0], before[1] - after[1]];
        before = after;
    }
    let first = unit(0);
    let last = unit(m - 1);
    if closed {
        out[0] = [last[0] - first[0], last[1] - first[1]];
    } else {
        out[0] = [-first[0], -first[1]];
        out[n - 1] = last;
    }
}

/// The 1D Poisson system `L f̃ = b` of §5.2, factored once.
///
/// `L` is the positive semidefinite graph Laplacian with `L_ij = −1/ℓ_ij` on edges and
/// `L_ii = Σ_j 1/ℓ_ij`; `f̃` minimizes `Σ_ij |f̃_j − f̃_i − T̃_ij|² / ℓ_ij` (§5.1). Its kernel is
/// the constants, which we remove by **pinning** `f̃_0 = 0` (the mean translation is restored
/// afterwards anyway). Pinning vertex 0 of a path *or of a cycle* leaves a path on vertices
/// `1..n`, so the reduced matrix A is tridiagonal, symmetric positive definite and weakly
/// diagonally dominant: Gaussian elimination without pivoting is stable, costs O(n) once, and
/// each solve is O(n) with no fill, no ordering and no workspace. That is why this does not go
/// through faer's general sparse Cholesky, which would compute the same factor with symbolic
/// analysis, a permutation and a scratch stack per solve. Because `Σ b = 0`, the dropped row 0
/// is satisfied too; [`poisson_residual`] checks the full system.
///
/// The elimination is *twisted* (a "burn at both ends" factorization): it runs from vertex 1
/// down and from vertex n − 1 up, meeting at the middle vertex k. Each sweep of a tridiagonal
/// solve is one chain of dependent multiply-subtracts; two half-length chains, interleaved,
/// overlap in the CPU and halve the solve time. Row j < k becomes `P_j x_j + o_j x_{j+1} = z_j`,
/// row j > k becomes `Q_j x_j + o_{j−1} x_{j−1} = z_j`, and row k, with both neighbours
/// eliminated, `γ x_k = z_k`.
#[derive(Clone, Debug)]
pub struct CurvePoisson {
    /// The meeting vertex k.
    twist: usize,
    /// Forward multipliers: `o_{j−1}/P_{j−1}` for `2 ≤ j < k`, `o_j/Q_{j+1}` for `k < j ≤ n−2`.
    forward: Vec<f64>,
    /// The two multipliers of row k (0 where the neighbour is missing or pinned).
    twist_multipliers: [f64; 2],
    /// `1/P_j` (j < k), `1/γ` (j = k), `1/Q_j` (j > k); index 0 unused.
    inv_pivot: Vec<f64>,
    /// Back-substitution couplings: `o_j/P_j` for `1 ≤ j < k`, `o_{j−1}/Q_j` for `j > k`.
    backward: Vec<f64>,
}

impl CurvePoisson {
    /// Factor the pinned Laplacian of a curve with these edge lengths (all > 0), `n` vertices.
    pub fn new(edge_lengths: &[f64], closed: bool) -> Result<Self, CurveError> {
        let m = edge_lengths.len();
        let n = if closed { m } else { m + 1 };
        let mut forward = zeroed(n)?;
        let mut inv_pivot = zeroed(n)?;
        let mut backward = zeroed(n)?;
        let twist = (n / 2).max(1);
        let mut factor = CurvePoisson {
            twist,
            forward: Vec::new(),
            twist_multipliers: [0.0, 0.0],
            inv_pivot: Vec::new(),
            backward: Vec::new(),
        };
        if n < 2 {
            factor.inv_pivot = inv_pivot;
            return Ok(factor);
        }
        // Reduced diagonal a_j for vertex j ≥ 1: the edge into j always exists; the edge out
        // of j exists unless j is the last vertex of an open curve. Off-diagonal o_j = A_{j,j+1}
        // = −1/ℓ_j for 1 ≤ j ≤ n − 2 (edges touching the pinned vertex 0 drop out).
        let diagonal =
            |j: usize| 1.0 / edge_lengths[j - 1] + if j < m { 1.0 / edge_lengths[j] } else { 0.0 };
        let off = |j: usize| -1.0 / edge_lengths[j];
        let k = twist;
        let mut gamma = diagonal(k);
        if k > 1 {
            let mut pivot = diagonal(1);
            for j in 2..k {
                forward[j] = off(j - 1) / pivot;
                backward[j - 1] = off(j - 1) / pivot;
                inv_pivot[j - 1] = 1.0 / pivot;
                pivot = diagonal(j) - forward[j] * off(j - 1);
                debug_assert!(
                    pivot > 0.0,
                    "a pinned connected Laplacian is positive definite"
                );
            }
            inv_pivot[k - 1] = 1.0 / pivot;
            backward[k - 1] = off(k - 1) / pivot;
            factor.twist_multipliers[0] = off(k - 1) / pivot;
            gamma -= off(k - 1) * off(k - 1) / pivot;
        }
        if k < n - 1 {
            let mut pivot = diagonal(n - 1);
            for j in (k + 1..n - 1).rev() {
                forward[j] = off(j) / pivot;
                backward[j + 1] = off(j) / pivot;
                inv_pivot[j + 1] = 1.0 / pivot;
                pivot = diagonal(j) - forward[j] * off(j);
                debug_assert!(
                    pivot > 0.0,
                    "a pinned connected Laplacian is positive definite"
                );
            }
            inv_pivot[k + 1] = 1.0 / pivot;
            backward[k + 1] = off(k) / pivot;
            factor.twist_multipliers[1] = off(k) / pivot;
            gamma -= off(k) * off(k) / pivot;
        }
        debug_assert!(
            gamma > 0.0,
            "a pinned connected Laplacian is positive definite"
        );
        inv_pivot[k] = 1.0 / gamma;
        factor.forward = forward;
        factor.inv_pivot = inv_pivot;
        factor.backward = backward;
        Ok(factor)
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.inv_pivot.len()
    }

    /// Whether there are no vertices (never, for a factored curve).
    pub fn is_empty(&self) -> bool {
        self.inv_pivot.is_empty()
    }

    /// Solve `L f = b` with `f_0 = 0` (both coordinates at once), writing into `f`.
    pub fn solve(&self, b: &[[f64; 2]], f: &mut [[f64; 2]]) {
        let n = self.len();
        debug_assert!(b.len() == n && f.len() == n);
        if n == 0 {
            return;
        }
        f[0] = [0.0, 0.0];
        if n < 2 {
            return;
        }
        let k = self.twist;
        let (mul, inv, back) = (&self.forward, &self.inv_pivot, &self.backward);
        // Forward elimination from both ends: rows 1..k and n−1 down to k+1, interleaved.
        f[1] = b[1];
        f[n - 1] = b[n - 1];
        let top = 2..k;
        let bottom = (k + 1..n - 1).rev();
        let common = top.len().min(bottom.len());
        for (j, i) in top.clone().zip(bottom.clone()) {
            f[j] = [
                b[j][0] - mul[j] * f[j - 1][0],
                b[j][1] - mul[j] * f[j - 1][1],
            ];
            f[i] = [
                b[i][0] - mul[i] * f[i + 1][0],
                b[i][1] - mul[i] * f[i + 1][1],
            ];
        }
        for j in top.skip(common) {
            f[j] = [
                b[j][0] - mul[j] * f[j - 1][0],
                b[j][1] - mul[j] * f[j - 1][1],
            ];
        }
        for i in bottom.skip(common) {
            f[i] = [
                b[i][0] - mul[i] * f[i + 1][0],
                b[i][1] - mul[i] * f[i + 1][1],
            ];
        }
        // The twist row; f[0] = 0 stands in for a missing upper neighbour.
        let [mu, ml] = self.twist_multipliers;
        let below = if k + 1 < n { f[k + 1] } else { [0.0, 0.0] };
        let above = if k > 1 { f[k - 1] } else { [0.0, 0.0] };
        let z = [
            b[k][0] - mu * above[0] - ml * below[0],
            b[k][1] - mu * above[1] - ml * below[1],
        ];
        f[k] = [z[0] * inv[k], z[1] * inv[k]];
        // Back substitution outwards from k, interleaved: x_j = z_j/P_j − (o_j/P_j) x_{j+1}.
        let up = (1..k).rev();
        let down = k + 1..n;
        let common = up.len().min(down.len());
        for (j, i) in up.clone().zip(down.clone()) {
            f[j] = [
                f[j][0] * inv[j] - back[j] * f[j + 1][0],
                f[j][1] * inv[j] - back[j] * f[j + 1][1],
            ];
            f[i] = [
                f[i][0] * inv[i] - back[i] * f[i - 1][0],
                f[i][1] * inv[i] - back[i] * f[i - 1][1],
            ];
        }
        for j in up.skip(common) {
            f[j] = [
                f[j][0] * inv[j] - back[j] * f[j + 1][0],
                f[j][1] * inv[j] - back[j] * f[j + 1][1],
            ];
        }
        for i in down.skip(common) {
            f[i] = [
                f[i][0] * inv[i] - back[i] * f[i - 1][0],
                f[i][1] * inv[i] - back[i] * f[i - 1][1],
            ];
        }
    }
}

/// Relative residual `max_i |(L f)_i − b_i| / max_i |b_i|` of the full (unpinned) system of
/// [`CurvePoisson`], rows of both coordinates; 0 when `b = 0` and `L f = 0`.
pub fn poisson_residual(
    inv_edge_lengths: &[f64],
    closed: bool,
    f: &[[f64; 2]],
    b: &[[f64; 2]],
) -> f64 {
    let n = f.len().min(b.len());
    let m = inv_edge_lengths.len();
    if n < 2 || m == 0 {
        return 0.0;
    }
    let (f, b, inv) = (&f[..n], &b[..n], inv_edge_lengths);
    // Row i of L f − b, for any vertex, from the edges on each side (if present).
    let row = |i: usize| {
        let mut r = [-b[i][0], -b[i][1]];
        let before = if i > 0 {
            Some((i - 1, i - 1))
        } else {
            closed.then_some((m - 1, n - 1))
        };
        if let Some((e, j)) = before {
            r[0] += (f[i][0] - f[j][0]) * inv[e];
            r[1] += (f[i][1] - f[j][1]) * inv[e];
        }
        if i < m {
            let j = if i + 1 == n { 0 } else { i + 1 };
            r[0] += (f[i][0] - f[j][0]) * inv[i];
            r[1] += (f[i][1] - f[j][1]) * inv[i];
        }
        r[0].abs().max(r[1].abs())
    };
    // Vertices 1..n−1 have both neighbours at i ± 1 on either kind of curve: branch-free,
    // with separate running maxima for x and y.
    let mut interior = [0.0f64; 2];
    for ((w, il), bi) in f.windows(3).zip(inv.windows(2)).zip(&b[1..n - 1]) {
        for c in 0..2 {
            let r = (w[1][c] - w[0][c]) * il[0] + (w[1][c] - w[2][c]) * il[1] - bi[c];
            interior[c] = larger(interior[c], r.abs());
        }
    }
    let interior = interior[0].max(interior[1]);
    let worst = interior.max(row(0)).max(row(n - 1));
    let mut scale = [0.0f64; 2];
    for bi in b {
        scale[0] = larger(scale[0], bi[0].abs());
        scale[1] = larger(scale[1], bi[1].abs());
    }
    let scale = scale[0].max(scale[1]);
    if scale > 0.0 {
        worst / scale
    } else {
        worst
    }
}

/// Wrap an angle into (−π, π], the range of [`turning_angles`].
#[inline]
fn wrap_angle(a: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    if a > PI {
        a - TAU
    } else if a <= -PI {
        a + TAU
    } else {
        a
    }
}

/// `atan x = x − x³/3 + x⁵/5 − … − x¹⁵/15` for |x| ≤ 1/16, where the first omitted term is
/// below `2⁻⁶⁴|x|`. No branch, so a loop of it vectorizes.
#[inline(always)]
fn atan_small(x: f64) -> f64 {
    // 1/(2j + 1), j = 1..=7: multiplications, since a division per term would cost more than
    // the whole series.
    const INV_ODD: [f64; 7] = [
        1.0 / 3.0,
        1.0 / 5.0,
        1.0 / 7.0,
        1.0 / 9.0,
        1.0 / 11.0,
        1.0 / 13.0,
        1.0 / 15.0,
    ];
    let x2 = x * x;
    let mut p = INV_ODD[6];
    for &a in INV_ODD[..6].iter().rev() {
        p = a - x2 * p;
    }
    x * (1.0 - x2 * p)
}

/// `(sin x, cos x)` by their Taylor series through x¹⁷ and x¹⁶, for |x| ≤ π/4, where the first
/// omitted terms are below 1e-19. No branch, so a loop of it vectorizes.
#[inline(always)]
fn sin_cos_small(x: f64) -> (f64, f64) {
    // (−1)ʲ/(2j + 1)! and (−1)ʲ/(2j)!, j = 1..=8.
    const SIN: [f64; 8] = [
        -1.0 / 6.0,
        1.0 / 120.0,
        -1.0 / 5040.0,
        1.0 / 362_880.0,
        -1.0 / 39_916_800.0,
        1.0 / 6_227_020_800.0,
        -1.0 / 1_307_674_368_000.0,
        1.0 / 355_687_428_096_000.0,
    ];
    const COS: [f64; 8] = [
        -1.0 / 2.0,
        1.0 / 24.0,
        -1.0 / 720.0,
        1.0 / 40_320.0,
        -1.0 / 3_628_800.0,
        1.0 / 479_001_600.0,
        -1.0 / 87_178_291_200.0,
        1.0 / 20_922_789_888_000.0,
    ];
    let z = x * x;
    let (mut s, mut c) = (SIN[7], COS[7]);
    for j in (0..7).rev() {
        s = SIN[j] + z * s;
        c = COS[j] + z * c;
    }
    (x + x * z * s, 1.0 + z * c)
}

/// Largest |x| for which [`sin_cos_small`] is used.
const SIN_COS_SMALL_MAX: f64 = std::f64::consts::FRAC_PI_4;

/// New tangents `T̃_k = ℓ_k R(Δ_k) e_k/|e_k|`: each current edge, rotated by its change of
/// angle Δ_k and scaled to its input length ℓ_k. Equal to [`tangents`] of the §5.2 angles
/// `θ_k = arg e_k + Δ_k`. A first pass uses Taylor series of sin and cos for every edge;
/// edges with |Δ_k| > π/4 (common in the first steps of a noisy curve, rare later) are redone
/// with the library `sin_cos`.
pub fn rotate_edges(
    points: &[[f64; 2]],
    angle_changes: &[f64],
    edge_lengths: &[f64],
    out: &mut [[f64; 2]],
) {
    let m = out.len().min(angle_changes.len()).min(edge_lengths.len());
    let (delta, ell, out) = (&angle_changes[..m], &edge_lengths[..m], &mut out[..m]);
    let rotate = |e: [f64; 2], l: f64, (s, c): (f64, f64)| {
        let scale = l / (e[0] * e[0] + e[1] * e[1]).sqrt();
        [scale * (c * e[0] - s * e[1]), scale * (s * e[0] + c * e[1])]
    };
    let mut all_small = true;
    for (k, (t, w)) in out.iter_mut().zip(points.windows(2)).enumerate() {
        all_small &= delta[k].abs() <= SIN_COS_SMALL_MAX;
        let e = [w[1][0] - w[0][0], w[1][1] - w[0][1]];
        *t = rotate(e, ell[k], sin_cos_small(delta[k]));
    }
    // The closing edge of a closed curve (windows stop at the last point).
    if m == points.len() && m > 0 {
        let e = edge_vector(points, m - 1);
        out[m - 1] = rotate(e, ell[m - 1], delta[m - 1].sin_cos());
    }
    if !all_small {
        for (k, t) in out.iter_mut().enumerate() {
            if delta[k].abs() > SIN_COS_SMALL_MAX {
                *t = rotate(edge_vector(points, k), ell[k], delta[k].sin_cos());
            }
        }
    }
}

/// Largest |x| = |tan α| for which [`atan_small`] is used.
const ATAN_SMALL_MAX: f64 = 0.0625;

/// Signed angle `α_k` from the target tangent `T̃_k` to the edge `f̃_{k+1} − f̃_k` the Poisson
/// solve produced: how much the projection onto closed curves (§5.1) rotated each edge. These
/// are small (of the order of the length distortion), so a first pass uses [`atan_small`] on
/// `tan α = (T̃ × e)/(T̃ · e)` for every edge, and only edges outside its range (rare) are
/// redone with the library `atan2`.
fn edge_rotations(tangents: &[[f64; 2]], points: &[[f64; 2]], out: &mut [f64]) {
    let m = out.len().min(tangents.len());
    let (t, out) = (&tangents[..m], &mut out[..m]);
    let sine_cosine = |k: usize, e: [f64; 2]| {
        (
            t[k][0] * e[1] - t[k][1] * e[0],
            t[k][0] * e[0] + t[k][1] * e[1],
        )
    };
    let mut all_small = true;
    for (k, (a, w)) in out.iter_mut().zip(points.windows(2)).enumerate() {
        let (s, c) = sine_cosine(k, [w[1][0] - w[0][0], w[1][1] - w[0][1]]);
        let x = s / c;
        all_small &= c > 0.0 && x.abs() <= ATAN_SMALL_MAX;
        *a = atan_small(x);
    }
    // The closing edge of a closed curve (windows stop at the last point).
    if m == points.len() && m > 0 {
        let (s, c) = sine_cosine(m - 1, edge_vector(points, m - 1));
        out[m - 1] = s.atan2(c);
    }
    if !all_small {
        for (k, a) in out.iter_mut().enumerate() {
            let (s, c) = sine_cosine(k, edge_vector(points, k));
            if !(c > 0.0 && s.abs() <= ATAN_SMALL_MAX * c) {
                *a = s.atan2(c);
            }
        }
    }
}

/// Turning angles of the curve the Poisson solve produced, from the target ones: the turn
/// from edge `i − 1` to edge `i` is the turn back to the target tangent, the target turn, and
/// the turn out to the new edge, `φ_i = φ̃_i + α_i − α_{i−1}` (mod 2π, wrapped into (−π, π]),
/// with `φ̃_i = ℓ*_i κ̃_i` (the cumulative sum of §5.2 advances θ by exactly this). This is an
/// identity of angles, not an approximation; it replaces an atan2 per vertex by a short
/// series per edge (debug builds check it against [`turning_angles`]). For a closed curve the
/// target turn at vertex 0 is the closing one, `2πk − Σ_{i≥1} φ̃_i`, k the turning number.
fn update_turning_angles(
    kappa: &[f64],
    dual_lengths: &[f64],
    edge_rotations: &[f64],
    closed: bool,
    out: &mut [f64],
) {
    let n = out.len();
    let m = edge_rotations.len();
    if closed {
        let rest: f64 = (1..n).map(|i| dual_lengths[i] * kappa[i]).sum();
        let k = turning_number(rest + dual_lengths[0] * kappa[0]);
        let closing = std::f64::consts::TAU * k as f64 - rest;
        out[0] = wrap_angle(closing + edge_rotations[0] - edge_rotations[m - 1]);
    } else {
        out[0] = 0.0;
        out[n - 1] = 0.0;
    }
    let last = if closed { n } else { n - 1 };
    for i in 1..last {
        let target = dual_lengths[i] * kappa[i];
        out[i] = wrap_angle(target + edge_rotations[i] - edge_rotations[i - 1]);
    }
}

/// `Σ_{i<n} g(i)` in four interleaved partial sums. A plain left fold is one chain of
/// dependent additions, each waiting for the last (about 4 cycles per element); four chains
/// overlap, and the per-step reductions are most of the flow's time at a few thousand
/// vertices. The result differs from the sequential sum only by rounding.
#[inline(always)]
fn sum4(n: usize, g: impl Fn(usize) -> f64) -> f64 {
    let mut acc = [0.0f64; 4];
    let full = n - n % 4;
    let mut i = 0;
    while i < full {
        acc[0] += g(i);
        acc[1] += g(i + 1);
        acc[2] += g(i + 2);
        acc[3] += g(i + 3);
        i += 4;
    }
    while i < n {
        acc[0] += g(i);
        i += 1;
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3])
}

/// `max(a, b)` by one comparison. `f64::max` also orders NaN, which costs a compare-unordered
/// and a blend per element in the hot reductions; here a NaN `b` is skipped. The flow cannot
/// produce NaN from a validated curve (finite input, positive definite factor).
#[inline(always)]
fn larger(a: f64, b: f64) -> f64 {
    if b > a {
        b
    } else {
        a
    }
}

/// `max_{i<n} g(i)` (0 when n = 0 or all values are negative), four chains like [`sum4`].
#[inline(always)]
fn max4(n: usize, g: impl Fn(usize) -> f64) -> f64 {
    let mut acc = [0.0f64; 4];
    let full = n - n % 4;
    let mut i = 0;
    while i < full {
        acc[0] = larger(acc[0], g(i));
        acc[1] = larger(acc[1], g(i + 1));
        acc[2] = larger(acc[2], g(i + 2));
        acc[3] = larger(acc[3], g(i + 3));
        i += 4;
    }
    while i < n {
        acc[0] = larger(acc[0], g(i));
        i += 1;
    }
    acc[0].max(acc[1]).max(acc[2].max(acc[3]))
}

/// Fallibly allocate `n` zeros (STYLE: user-sized buffers use `try_reserve`).
fn zeroed<T: Copy + Default>(n: usize) -> Result<Vec<T>, CurveError> {
    let mut v = Vec::new();
    v.try_reserve_exact(n)
        .map_err(|_| CurveError::OutOfMemory { points: n })?;
    v.resize(n, T::default());
    Ok(v)
}

/// Parameters of a curve flow.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CurveParams {
    /// Time step with the paper's meaning (§4 eq. 2): unconstrained curvature is updated as
    /// `κ ← (1 − 2τ)κ`, stable for `0 < τ < 1`. The default 0.5 removes all curvature outside
    /// the constraint span `{1, fˣ, fʸ}` in one step, the fastest descent: the noisy test curve
    /// (r = 1 + 0.2 sin 5t + jitter, 256 vertices) has σ(κ)/κ̄ ≈ 2e-3 after one step (§5 says
    /// "about six" steps to the minimum). At τ = 0.9 the same curve still has σ/κ̄ ≈ 1.9 after
    /// ten steps: the factor (1 − 2τ) = −0.8 overshoots and decays slowly.
    pub tau: f64,
}

impl Default for CurveParams {
    fn default() -> Self {
        CurveParams { tau: 0.5 }
    }
}

/// What a curve flow step reports about the curve it produced (step 0 is the input).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurveStepMetrics {
    /// Steps taken so far; 0 is the input.
    pub step: usize,
    /// `E_C = Σ κ_i² ℓ*_i` (§5), κ from the turning angles and the input dual lengths.
    pub energy: f64,
    /// Length-weighted `σ(κ)/|κ̄|` (see [`curvature_std_over_mean`]): 0 for a circle; `+∞` when
    /// κ̄ = 0 but κ varies (serialized as JSON `null`).
    pub curvature_std_over_mean: f64,
    /// `max_ij |ℓ̃_ij / ℓ_ij − 1|` against the input lengths: the isometry error (Figure 11).
    pub max_edge_length_distortion: f64,
    /// Closed curves: `|Σ T̃_ij| / Σ ℓ_ij`, how far the integrated tangents fail to close before
    /// the Poisson projection (Figure 11, top center). 0 for open curves and at step 0.
    pub closure_gap: f64,
    /// Relative residual of the Poisson solve, [`poisson_residual`]. 0 at step 0.
    pub poisson_residual: f64,
    /// `Σ ℓ̃`, the current length (the input length, up to the isometry error).
    pub total_length: f64,
    /// `Σ φ_i = Σ κ_i ℓ*_i`; `2πk` for a closed curve of turning number k.
    pub total_curvature: f64,
    /// Wall time of the step in milliseconds, metrics included. 0 at step 0.
    pub step_ms: f64,
}

/// One running isometric curve flow (§5). Build it once, then call [`CurveFlow::step`]; each
/// step is O(n) and allocation-free (all buffers and the Poisson factor are made in `new`).
#[derive(Clone, Debug)]
pub struct CurveFlow {
    curve: Curve,
    tau: f64,
    step: usize,
    /// ℓ of the input curve, the invariant of the flow (§5.2).
    edge_lengths: Vec<f64>,
    /// `1/ℓ`, used by the divergence and the residual.
    inv_edge_lengths: Vec<f64>,
    /// `ℓ*` from the input lengths.
    dual_lengths: Vec<f64>,
    /// `1/ℓ*`.
    inv_dual_lengths: Vec<f64>,
    /// `Σ ℓ`, the input length.
    length: f64,
    /// `R_i = Σ_{k≥i} ℓ_k`, for the mean change of angle (index 0 unused).
    suffix_lengths: Vec<f64>,
    /// Pinned Poisson factor; depends only on ℓ, so it is built once.
    poisson: CurvePoisson,
    /// φ of the current curve (kept from the last step's metrics, so each step calls atan2
    /// once per vertex).
    turning: Vec<f64>,
    /// κ of the current curve, then (during a step) the flow direction v.
    kappa: Vec<f64>,
    velocity: Vec<f64>,
    theta: Vec<f64>,
    /// ℓ̃ of the current curve, for the metrics.
    current_lengths: Vec<f64>,
    /// α_k of [`edge_rotations`], one per edge.
    edge_rotation: Vec<f64>,
    tangents: Vec<[f64; 2]>,
    rhs: Vec<[f64; 2]>,
    /// The next positions; swapped with `curve.points` at the end of a step.
    /// (`theta` holds the change of each edge angle, Δ_k, during a step.)
    next: Vec<[f64; 2]>,
    initial: CurveStepMetrics,
    last: CurveStepMetrics,
}

impl CurveFlow {
    /// Validate the curve and the parameters (`0 < τ < 1`, §4), allocate every buffer and
    /// factor the Poisson matrix.
    pub fn new(curve: Curve, params: CurveParams) -> Result<Self, CurveError> {
        curve.validate()?;
        let tau = params.tau;
        if !(tau > 0.0 && tau < 1.0) {
            return Err(CurveError::InvalidParameter {
                name: "tau",
                reason: format!("{tau} is outside (0, 1), where the flow is stable (§4)"),
            });
        }
        let n = curve.points.len();
        let m = curve.edge_count();
        let mut edge_lengths_buf = zeroed(m)?;
        edge_lengths(&curve.points, curve.closed, &mut edge_lengths_buf);
        let mut inv_edge_lengths = zeroed(m)?;
        for (inv, l) in inv_edge_lengths.iter_mut().zip(&edge_lengths_buf) {
            *inv = 1.0 / l;
        }
        let mut dual = zeroed(n)?;
        dual_lengths(&edge_lengths_buf, curve.closed, &mut dual);
        let poisson = CurvePoisson::new(&edge_lengths_buf, curve.closed)?;
        let length: f64 = edge_lengths_buf.iter().sum();
        let mut inv_dual_lengths = zeroed(n)?;
        for (inv, d) in inv_dual_lengths.iter_mut().zip(&dual) {
            *inv = 1.0 / d;
        }
        let mut suffix_lengths = zeroed(m)?;
        let mut suffix = 0.0;
        for (r, l) in suffix_lengths.iter_mut().zip(&edge_lengths_buf).rev() {
            suffix += l;
            *r = suffix;
        }
        let mut turning = zeroed(n)?;
        turning_angles(&curve.points, curve.closed, &mut turning);
        let zero_metrics = CurveStepMetrics {
            step: 0,
            energy: 0.0,
            curvature_std_over_mean: 0.0,
            max_edge_length_distortion: 0.0,
            closure_gap: 0.0,
            poisson_residual: 0.0,
            total_length: 0.0,
            total_curvature: 0.0,
            step_ms: 0.0,
        };
        let mut flow = CurveFlow {
            tau,
            step: 0,
            edge_lengths: edge_lengths_buf,
            inv_edge_lengths,
            dual_lengths: dual,
            poisson,
            length,
            inv_dual_lengths,
            suffix_lengths,
            turning,
            kappa: zeroed(n)?,
            velocity: zeroed(n)?,
            theta: zeroed(m)?,
            current_lengths: zeroed(m)?,
            edge_rotation: zeroed(m)?,
            tangents: zeroed(m)?,
            rhs: zeroed(n)?,
            next: zeroed(n)?,
            initial: zero_metrics,
            last: zero_metrics,
            curve,
        };
        flow.initial = flow.measure(0.0, 0.0, 0.0);
        flow.last = flow.initial;
        Ok(flow)
    }

    /// Advance one step (Table 1, left column) and report the metrics of the new curve.
    pub fn step(&mut self) -> CurveStepMetrics {
        let start = Instant::now();
        let closed = self.curve.closed;
        let n = self.curve.points.len();

        // I. Curvature of the current curve: `measure`, at the end of the last step (or in
        // `new`), left it in `self.kappa`.

        // II. Flow direction v = −2κ (§4 eq. 1).
        for (v, k) in self.velocity.iter_mut().zip(&self.kappa) {
            *v = -2.0 * k;
        }
        // III–IV. Closed curves: project out {1, fˣ, fʸ} (§5, App. A).
        if closed {
            project_out_closure_constraints(
                &self.curve.points,
                &self.dual_lengths,
                &mut self.velocity,
            );
        }
        // V. κ̃ = κ + τ v (§4 eq. 2 with the projected direction).
        for (k, v) in self.kappa.iter_mut().zip(&self.velocity) {
            *k += self.tau * v;
        }

        // VI. New tangents. §5.2 sums θ_k = θ_0 + Σ_{i≤k} ℓ*_i κ̃_i ([`tangent_angles`]) and
        // sets T̃_k = ℓ_k (cos θ_k, sin θ_k) ([`tangents`]). The current edge angles are the
        // same sum over the current turning angles φ_i, so θ_k is the current angle plus the
        // change Δ_k = Σ_{1≤i≤k} δ_i, δ_i = ℓ*_i κ̃_i − φ_i, and we rotate each current unit
        // edge by Δ_k ([`rotate_edges`]): the same tangents, with a short series instead of
        // sin_cos once the flow is near its minimum and the changes are small.
        //
        // §5.1: remove the mean change of angle, length-weighted over edges. Swapping sums,
        // `Σ_k ℓ_k Δ_k = Σ_{i≥1} δ_i R_i` with the suffix lengths `R_i = Σ_{k≥i} ℓ_k` (fixed,
        // since ℓ is): one dot product. (Vertex 0 does not enter: for a closed curve its turn
        // is the closing one.)
        let m = self.theta.len();
        let mean_change = {
            let (d, k, phi, r) = (
                &self.dual_lengths[1..m],
                &self.kappa[1..m],
                &self.turning[1..m],
                &self.suffix_lengths[1..m],
            );
            sum4(m - 1, |i| (d[i] * k[i] - phi[i]) * r[i]) / self.length
        };
        let mut change = -mean_change;
        for (k, delta) in self.theta.iter_mut().enumerate() {
            if k > 0 {
                change += self.dual_lengths[k] * self.kappa[k] - self.turning[k];
            }
            *delta = change;
        }
        rotate_edges(
            &self.curve.points,
            &self.theta,
            &self.edge_lengths,
            &mut self.tangents,
        );
        let closure_gap = if closed {
            let t = &self.tangents[..];
            let gap_x = sum4(t.len(), |i| t[i][0]);
            let gap_y = sum4(t.len(), |i| t[i][1]);
            gap_x.hypot(gap_y) / self.length
        } else {
            0.0
        };

        // VII. Positions: L f̃ = ∇·T̃ (§5.2), then restore the mean position (§5.1).
        divergence(
            &self.tangents,
            &self.inv_edge_lengths,
            closed,
            &mut self.rhs,
        );
        self.poisson.solve(&self.rhs, &mut self.next);
        let residual = poisson_residual(&self.inv_edge_lengths, closed, &self.next, &self.rhs);
        let shift = {
            let (old, new) = (&self.curve.points[..n], &self.next[..n]);
            let inv_n = 1.0 / n as f64;
            [
                sum4(n, |i| old[i][0] - new[i][0]) * inv_n,
                sum4(n, |i| old[i][1] - new[i][1]) * inv_n,
            ]
        };
        for p in &mut self.next {
            p[0] += shift[0];
            p[1] += shift[1];
        }
        std::mem::swap(&mut self.curve.points, &mut self.next);
        self.step += 1;

        // Turning angles of the new curve, for the metrics and the next step, without an atan2
        // per vertex: see `update_turning_angles`.
        edge_rotations(&self.tangents, &self.curve.points, &mut self.edge_rotation);
        update_turning_angles(
            &self.kappa,
            &self.dual_lengths,
            &self.edge_rotation,
            closed,
            &mut self.turning,
        );
        #[cfg(debug_assertions)]
        self.debug_check_turning();
        self.last = self.measure(closure_gap, residual, 0.0);
        // Measured last, so the metrics pass counts as part of the step.
        self.last.step_ms = start.elapsed().as_secs_f64() * 1e3;
        self.last
    }

    /// Debug builds: the incrementally updated turning angles equal atan2 of the edges.
    #[cfg(debug_assertions)]
    fn debug_check_turning(&self) {
        let p = &self.curve.points;
        let (n, m) = (p.len(), self.edge_lengths.len());
        for i in 0..n {
            if !self.curve.closed && (i == 0 || i == n - 1) {
                continue;
            }
            let a = edge_vector(p, (i + m - 1) % m);
            let b = edge_vector(p, i);
            let direct = (a[0] * b[1] - a[1] * b[0]).atan2(a[0] * b[0] + a[1] * b[1]);
            let diff = wrap_angle(self.turning[i] - direct);
            debug_assert!(
                diff.abs() < 1e-9,
                "turning angle {i}: updated {} vs atan2 {direct}",
                self.turning[i]
            );
        }
    }

    /// Metrics of the current curve; `self.turning` must be current. Leaves `self.kappa`
    /// holding κ of the current curve.
    fn measure(
        &mut self,
        closure_gap: f64,
        poisson_residual: f64,
        step_ms: f64,
    ) -> CurveStepMetrics {
        // κ = φ/ℓ* as in [`curvature`], by a multiplication: a division per vertex is the
        // slowest arithmetic left in the step.
        for ((k, phi), inv) in self
            .kappa
            .iter_mut()
            .zip(&self.turning)
            .zip(&self.inv_dual_lengths)
        {
            *k = phi * inv;
        }
        let current = &mut self.current_lengths;
        edge_lengths(&self.curve.points, self.curve.closed, current);
        let m = current.len();
        let (current, inv) = (&current[..m], &self.inv_edge_lengths[..m]);
        let total_length = sum4(m, |i| current[i]);
        let distortion = max4(m, |i| (current[i] * inv[i] - 1.0).abs());
        let turning = &self.turning[..];
        CurveStepMetrics {
            step: self.step,
            energy: curvature_energy(&self.kappa, &self.dual_lengths),
            curvature_std_over_mean: curvature_std_over_mean(&self.kappa, &self.dual_lengths),
            max_edge_length_distortion: distortion,
            closure_gap,
            poisson_residual,
            total_length,
            total_curvature: sum4(turning.len(), |i| turning[i]),
            step_ms,
        }
    }

    /// Current positions, in input order.
    pub fn points(&self) -> &[[f64; 2]] {
        &self.curve.points
    }

    /// The current curve.
    pub fn curve(&self) -> &Curve {
        &self.curve
    }

    /// κ of the current curve: its turning angles over the **input** dual lengths.
    pub fn curvature(&self) -> &[f64] {
        &self.kappa
    }

    /// The input edge lengths ℓ, which the flow preserves.
    pub fn edge_lengths(&self) -> &[f64] {
        &self.edge_lengths
    }

    /// The time step τ.
    pub fn tau(&self) -> f64 {
        self.tau
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> usize {
        self.step
    }

    /// Metrics of the input curve (step 0).
    pub fn initial_metrics(&self) -> CurveStepMetrics {
        self.initial
    }

    /// Metrics of the current curve (the last step's, or the input's before any step).
    pub fn last_metrics(&self) -> CurveStepMetrics {
        self.last
    }
}
