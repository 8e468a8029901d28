//! Willow: mesh fairing by conformal Willmore flow.
//!
//! Crane, Pinkall and Schröder, "Robust Fairing via Conformal Curvature Flow" (SIGGRAPH 2013).
//! Data flows one way, from the edges into the numeric core:
//!
//! - [`mesh`]: the welded triangle surface the flow sees ([`mesh::Mesh`]), its topology and
//!   validation, and reading/writing OBJ, glTF and GLB with UVs and textures carried through
//!   ([`mesh::io::Asset`]).
//! - [`geometry`]: discrete operators on a `Mesh` (cotan Laplacian, vertex areas, normals,
//!   mean curvature) and quaternions.
//! - [`flow`]: one step at a time of conformal Willmore flow (Table 1, right column) and of the
//!   classic flows it is compared with; a [`flow::Flow`] owns no threads and never blocks.
//! - [`metrics`]: what each step reports ([`metrics::StepMetrics`]): Willmore energy,
//!   quasi-conformal error Q, closure residual.
//!
//! None of these modules knows about tokio, HTTP or gRPC: a CAD pipeline can call them directly.

// Geometry code indexes triangle corners as `c, c + 1, c + 2 (mod 3)`, exactly as the paper's
// formulas do; rewriting those loops as iterator chains would hide the math.
#![allow(clippy::needless_range_loop)]

pub mod api;
pub mod flow;
pub mod geometry;
pub mod jobs;
pub mod mesh;
pub mod metrics;
