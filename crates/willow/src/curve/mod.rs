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

mod operators;
pub use operators::*;
mod poisson;
pub use poisson::*;
mod numerics;
pub use numerics::*;
mod flow;
pub use flow::*;

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
