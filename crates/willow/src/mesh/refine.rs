//! Opt-in refinement before the flow (issue 26, item 5): Loop subdivision toward a target edge
//! length, for tessellations too coarse to represent a fairer shape.
//!
//! A coarse CAD part (a cylinder with fan caps, 130 vertices) has a discrete W below its
//! genus's bound, so the flow cannot lower it and the job ends `already_fair`. Subdividing
//! first gives the flow room to move. Each level splits every triangle 1-to-4 at its edge
//! midpoints (`V' = V + E`, `F' = 4F`), and places vertices by Loop's rules (Loop 1987; the
//! boundary rules of Hoppe et al. 1994, so an open boundary stays a curve of its own):
//!
//! - new (odd) vertex on an interior edge `ab` with opposite vertices `c`, `d`:
//!   `3/8 (a + b) + 1/8 (c + d)`; on a boundary edge: `(a + b) / 2`;
//! - old (even) vertex of valence `n` inside: `(1 − nβ) v + β Σ neighbours`, with
//!   `β = (5/8 − (3/8 + 1/4 cos 2π/n)²) / n`; on the boundary: `3/4 v + 1/8 (b₁ + b₂)`, its two
//!   boundary neighbours; a vertex where the boundary meets itself keeps its position.
//!
//! Loop's stencils are affine combinations, so a planar mesh stays planar, and the limit
//! surface is C² away from extraordinary vertices. The connectivity step ([`midpoint_split`])
//! is shared with [`io::Asset::refined`](super::io::Asset::refined), which splits the file's
//! own (UV-seamed) vertices the same way so textures survive.
//!
//! The work is decided before any is done ([`planned_levels`]): the default makes the fewest
//! levels that reach [`DEFAULT_REFINED_FACES`] triangles (16k–64k, whatever the triangles'
//! shape: the old rule, levels until the mean edge reached the length of a 16k-triangle
//! tiling's, made 327,680 triangles of a 12 KB stretched ellipsoid, whose long edges stay
//! long against its small area); a target edge makes `⌈log₂(mean edge / target)⌉` (each
//! level halves the edges). The plan's triangle count (`F · 4^levels`) is checked against the
//! caller's limits and [`MAX_REFINED_FACES`] before the first level ([`check_plan`]), so an
//! upload that would refine past them is refused at once, with a [`MeshError::TooLarge`]
//! naming `refine`, not after seconds of refining.

use super::generate::mean_edge_length;
use super::{Limits, Mesh, MeshError};
use std::collections::HashMap;
use std::f64::consts::PI;

/// Most triangles a refinement may make, whatever the server's limits: four levels of a
/// 100k-face upload, and far above the ~16k the default target aims at.
pub const MAX_REFINED_FACES: usize = 2_000_000;

/// The triangle count the default target edge length aims at ([`default_target_edge`]):
/// enough for a smooth surface to show, few enough for a step to take well under a second.
pub const DEFAULT_REFINED_FACES: f64 = 16_000.0;

/// No vertex: a boundary edge's missing opposite vertex.
const NONE: usize = usize::MAX;

/// The connectivity of one 1-to-4 split.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MidpointSplit {
    /// Four children per parent, in parent order: for parent `[a, b, c]` with midpoints
    /// `ab`, `bc`, `ca`: `[a, ab, ca]`, `[ab, b, bc]`, `[ca, bc, c]`, `[ab, bc, ca]`, so each
    /// child keeps its parent's winding.
    pub triangles: Vec<[usize; 3]>,
    /// New vertex `n + k` is the midpoint of `edges[k]` (vertex pair in the order first seen),
    /// where `n` is the vertex count before the split.
    pub edges: Vec<[usize; 2]>,
    /// Per edge, the corners opposite it in the (at most two) triangles sharing it; [`usize::MAX`]
    /// where a boundary edge has no second triangle.
    pub opposite: Vec<[usize; 2]>,
}

/// Splits every triangle over `n` vertices into four at its edge midpoints. Edges are keyed
/// by their unordered vertex pair, so two triangles sharing an edge share its midpoint, and
/// two triangles that only share a *position* (a UV seam: different vertex numbers) do not.
pub fn midpoint_split(triangles: &[[usize; 3]], n: usize) -> MidpointSplit {
    let mut index: HashMap<(usize, usize), usize> = HashMap::with_capacity(triangles.len() * 2);
    let mut edges = Vec::with_capacity(triangles.len() * 2);
    let mut opposite: Vec<[usize; 2]> = Vec::with_capacity(triangles.len() * 2);
    let mut out = Vec::with_capacity(triangles.len() * 4);
    for t in triangles {
        let mut mid = [0usize; 3];
        for k in 0..3 {
            let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
            let e = *index.entry((a.min(b), a.max(b))).or_insert_with(|| {
                edges.push([a, b]);
                opposite.push([NONE, NONE]);
                edges.len() - 1
            });
            let slot = &mut opposite[e];
            if slot[0] == NONE {
                slot[0] = c;
            } else {
                slot[1] = c;
            }
            mid[k] = n + e;
        }
        let [a, b, c] = *t;
        let [ab, bc, ca] = mid;
        out.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
    }
    MidpointSplit {
        triangles: out,
        edges,
        opposite,
    }
}

/// Loop's β for an interior vertex of valence `n` (module docs).
pub fn loop_beta(n: usize) -> f64 {
    let n = n as f64;
    let c = 3.0 / 8.0 + 0.25 * (2.0 * PI / n).cos();
    (5.0 / 8.0 - c * c) / n
}

/// Positions after one Loop level: the old vertices moved by the even rules, then one new
/// vertex per edge of `split` by the odd rules (module docs).
pub fn loop_positions(positions: &[[f64; 3]], split: &MidpointSplit) -> Vec<[f64; 3]> {
    let n = positions.len();
    // Per vertex: Σ neighbours and valence; Σ boundary neighbours and their count.
    let mut sum = vec![[0.0f64; 3]; n];
    let mut valence = vec![0usize; n];
    let mut bsum = vec![[0.0f64; 3]; n];
    let mut bcount = vec![0usize; n];
    for (e, op) in split.edges.iter().zip(&split.opposite) {
        let boundary = op[1] == NONE;
        for (v, w) in [(e[0], e[1]), (e[1], e[0])] {
            add(&mut sum[v], positions[w], 1.0);
            valence[v] += 1;
            if boundary {
                add(&mut bsum[v], positions[w], 1.0);
                bcount[v] += 1;
            }
        }
    }
    let mut out = Vec::with_capacity(n + split.edges.len());
    for v in 0..n {
        let p = positions[v];
        let moved = match bcount[v] {
            0 if valence[v] > 0 => {
                let beta = loop_beta(valence[v]);
                let mut q = [0.0; 3];
                add(&mut q, p, 1.0 - valence[v] as f64 * beta);
                add(&mut q, sum[v], beta);
                q
            }
            2 => {
                let mut q = [0.0; 3];
                add(&mut q, p, 0.75);
                add(&mut q, bsum[v], 0.125);
                q
            }
            // Where the boundary touches itself (or an unused vertex): no smooth rule applies.
            _ => p,
        };
        out.push(moved);
    }
    for (e, op) in split.edges.iter().zip(&split.opposite) {
        let (a, b) = (positions[e[0]], positions[e[1]]);
        let mut q = [0.0; 3];
        if op[1] == NONE {
            add(&mut q, a, 0.5);
            add(&mut q, b, 0.5);
        } else {
            add(&mut q, a, 0.375);
            add(&mut q, b, 0.375);
            add(&mut q, positions[op[0]], 0.125);
            add(&mut q, positions[op[1]], 0.125);
        }
        out.push(q);
    }
    out
}

fn add(acc: &mut [f64; 3], p: [f64; 3], w: f64) {
    for k in 0..3 {
        acc[k] += w * p[k];
    }
}

/// One Loop level of a welded mesh: the split and the new positions. The result keeps the
/// winding, so it is a valid oriented surface whenever `mesh` is.
pub fn loop_subdivide(mesh: &Mesh) -> (Mesh, MidpointSplit) {
    let split = midpoint_split(&mesh.triangles, mesh.vertex_count());
    let positions = loop_positions(&mesh.positions, &split);
    let refined = Mesh {
        positions,
        triangles: split.triangles.clone(),
    };
    (refined, split)
}

/// The default target: the edge of an equilateral triangle such that the surface's area
/// holds [`DEFAULT_REFINED_FACES`] of them (`A = F √3/4 ℓ²`).
pub fn default_target_edge(mesh: &Mesh) -> f64 {
    let area: f64 = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|v| mesh.positions[v]);
            let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let w = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let x = [
                u[1] * w[2] - u[2] * w[1],
                u[2] * w[0] - u[0] * w[2],
                u[0] * w[1] - u[1] * w[0],
            ];
            0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
        })
        .sum();
    (4.0 * area / (3f64.sqrt() * DEFAULT_REFINED_FACES)).sqrt()
}

/// What [`refine`] did.
#[derive(Clone, Debug)]
pub struct Refined {
    pub mesh: Mesh,
    /// The splits, first level first (empty when the mesh was already fine enough).
    pub levels: Vec<MidpointSplit>,
}

/// Checks a target edge length: finite and positive. The error names `refine`.
pub fn check_target(target: f64) -> Result<(), MeshError> {
    if target.is_finite() && target > 0.0 {
        Ok(())
    } else {
        Err(MeshError::Unsupported {
            detail: format!("refine: the target edge length must be finite and > 0, got {target}"),
        })
    }
}

/// Whether one more level may be built from `faces` triangles under `limits` and
/// [`MAX_REFINED_FACES`] (checked before the level is allocated); the error names `refine`.
pub fn check_level(faces: usize, limits: &Limits) -> Result<(), MeshError> {
    let cap = limits.max_faces.min(MAX_REFINED_FACES);
    let next = faces.saturating_mul(4);
    if next > cap {
        return Err(MeshError::TooLarge {
            what: "triangles after `refine` (subdivide less: a longer target edge)",
            value: next,
            limit: cap,
        });
    }
    Ok(())
}

/// How many levels a refinement of `mesh` toward `target` (default: [`DEFAULT_REFINED_FACES`]
/// triangles) makes (module docs); a bad target is refused, naming `refine`.
pub fn planned_levels(mesh: &Mesh, target: Option<f64>) -> Result<usize, MeshError> {
    let levels = match target {
        None => {
            let faces = mesh.face_count().max(1) as f64;
            (DEFAULT_REFINED_FACES / faces).log(4.0).ceil().max(0.0)
        }
        Some(t) => {
            check_target(t)?;
            (mean_edge_length(mesh) / t).log2().ceil().max(0.0)
        }
    };
    // At most 64 levels: past a handful the plan is refused by its size anyway.
    Ok(levels.min(64.0) as usize)
}

/// Whether `levels` 1-to-4 splits of `faces` triangles stay within `limits` and
/// [`MAX_REFINED_FACES`] (checked before the first level is built); the error names `refine`
/// and the triangle count the plan would make.
pub fn check_plan(faces: usize, levels: usize, limits: &Limits) -> Result<(), MeshError> {
    let cap = limits.max_faces.min(MAX_REFINED_FACES);
    let planned = faces.saturating_mul(4usize.saturating_pow(levels as u32));
    if levels > 0 && planned > cap {
        return Err(MeshError::TooLarge {
            what: "triangles `refine` would make (subdivide less: a longer target edge)",
            value: planned,
            limit: cap,
        });
    }
    Ok(())
}

/// Whether a split's vertex count (`V + E`) is within `limits`; the error names `refine`.
pub fn check_vertices(vertices: usize, limits: &Limits) -> Result<(), MeshError> {
    if vertices > limits.max_vertices {
        return Err(MeshError::TooLarge {
            what: "vertices after `refine` (subdivide less: a longer target edge)",
            value: vertices,
            limit: limits.max_vertices,
        });
    }
    Ok(())
}

/// Loop subdivision, [`planned_levels`] times: until the mean edge length
/// ([`mean_edge_length`]) is about `target`, or by default to [`DEFAULT_REFINED_FACES`]
/// triangles. Refuses, before any work, a plan past `limits` or [`MAX_REFINED_FACES`].
pub fn refine(mesh: &Mesh, target: Option<f64>, limits: &Limits) -> Result<Refined, MeshError> {
    let planned = planned_levels(mesh, target)?;
    check_plan(mesh.face_count(), planned, limits)?;
    let mut current = mesh.clone();
    let mut levels = Vec::new();
    while levels.len() < planned {
        check_level(current.face_count(), limits)?;
        let split = midpoint_split(&current.triangles, current.vertex_count());
        check_vertices(current.vertex_count() + split.edges.len(), limits)?;
        current = Mesh {
            positions: loop_positions(&current.positions, &split),
            triangles: split.triangles.clone(),
        };
        levels.push(split);
    }
    Ok(Refined {
        mesh: current,
        levels,
    })
}

#[cfg(test)]
#[path = "refine_tests.rs"]
mod tests;
