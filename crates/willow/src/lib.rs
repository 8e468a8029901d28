//! Willow: mesh fairing by conformal Willmore flow.
//!
//! Crane, Pinkall and Schröder, "Robust Fairing via Conformal Curvature Flow" (SIGGRAPH 2013).
//! The modules stack one way, each using only those above it (`curve` uses none of them):
//!
//! - [`mesh`]: the welded triangle surface the flow sees ([`mesh::Mesh`]), its topology and
//!   validation, and reading/writing OBJ, glTF, GLB, STL, PLY and OFF with UVs, textures and
//!   the file's own vertex numbering carried through ([`mesh::io::Asset`]).
//! - [`linalg`]: the sparse linear algebra every flow factors with: the fixed block pattern, the
//!   Cholesky factorization reused across steps (symbolic once, numeric per step), the
//!   supernodal kernels and the fill-reducing orderings.
//! - [`geometry`]: discrete operators on a `Mesh` (cotan Laplacian, vertex areas, normals,
//!   mean curvature, enclosed volume, the Hodge machinery of the exactness constraints, which
//!   factors with `linalg`), quaternions, and the distance between two surfaces through a
//!   bounding volume hierarchy ([`geometry::distance`]).
//! - [`metrics`]: what each step reports ([`metrics::StepMetrics`]): Willmore energy,
//!   quasi-conformal error Q, closure residual, enclosed volume, distance from the input.
//! - [`denoise`]: feature-preserving denoising (guided normal filtering and Sun et al.'s vertex
//!   update), the default method's numerics.
//! - [`flow`]: one step at a time of conformal Willmore flow (Table 1, right column), of the
//!   denoising stage and of the classic flows it is compared with; a [`flow::Flow`] owns no
//!   threads and never blocks. [`flow::stopping::Run`] drives one to its end and says why it
//!   stopped ([`flow::stopping::Outcome`]).
//! - [`curve`]: the isometric flow of planar curves (§5, Table 1, left column), a sibling of
//!   `flow`.
//!
//! Beside them, `parallel` runs two pieces of work on two threads when a flow's `threads`
//! allows (the symbolic analyses, the distance measure's two sides); the factorization's
//! subtrees and the ordering take threads of their own the same way, each joined before the
//! call returns.
//!
//! ```
//! use willow::flow::{new_flow, FlowParams};
//! use willow::mesh::io::{Asset, Format, Limits};
//!
//! // Spot (Keenan Crane's cow, public domain), with its UVs.
//! let bytes = include_bytes!("../tests/data/spot_triangulated.obj");
//! let asset = Asset::read(bytes, Format::Obj, &Limits::default())?;
//! let params = FlowParams { tau: 0.1, ..FlowParams::default() };
//! params.validate()?;
//! let mut flow = new_flow(asset.surface(), &params)?;
//! let first = flow.step()?;
//! let second = flow.step()?;
//! assert!(second.willmore_energy < first.willmore_energy);
//! println!("step {}: W = {:.3}, mean Q = {:.4}", second.step, second.willmore_energy, second.q_mean);
//! // The file comes back as it was (UVs, seams, materials), with the new positions.
//! let glb = asset.write(flow.positions(), Format::Glb)?;
//! assert!(glb.starts_with(b"glTF"));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! This crate has no async runtime, no transport, no database and no build script: a CAD
//! pipeline adds it in one line. The service (`willow-service`: jobs, HTTP, gRPC, the web page
//! and the CLI) is built on top of it.

// Geometry code indexes triangle corners as `c, c + 1, c + 2 (mod 3)`, exactly as the paper's
// formulas do; rewriting those loops as iterator chains would hide the math.
#![allow(clippy::needless_range_loop)]

pub mod curve;
pub mod denoise;
pub mod flow;
pub mod geometry;
pub mod linalg;
pub mod mesh;
pub mod metrics;
mod parallel;

// The README's library example compiles as a doctest of this crate.
#[cfg(doctest)]
#[doc = include_str!("../../../README.md")]
struct ReadmeExamples;
