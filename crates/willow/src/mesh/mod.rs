//! The triangle surface the flow works on, its topology, validation and file formats.
//!
//! [`Mesh`] is the *welded* surface: one vertex per distinct position, triangles consistently
//! oriented. File formats split vertices at UV seams; [`io::Asset`] keeps the map from the
//! file's vertices to the welded ones so new positions scatter back without opening seams.
//!
//! - [`Mesh::new`] is the door: it validates (finite, in range, non-degenerate, manifold,
//!   orientable, within [`Limits`]) and orients (closed components outward), or returns a
//!   [`MeshError`] naming the rule, the count and the first offending indices.
//! - [`Topology`]: edges, boundary loops, connected components with χ and genus.
//! - [`io`]: OBJ, glTF, GLB, STL, PLY and OFF in and out ([`io::Asset`], [`io::Format`]).
//! - [`generate`]: meshes made in code for tests and benchmarks.

pub mod creases;
pub mod error;
pub mod generate;
pub mod holes;
pub mod io;
pub mod refine;
pub mod topology;
mod validate;

pub use error::MeshError;
pub use topology::Topology;
pub use validate::Limits;

/// A welded, consistently oriented triangle surface in world space.
///
/// Connectivity never changes under the flows in this crate: only `positions` move.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f64; 3]>,
    pub triangles: Vec<[usize; 3]>,
}

impl Mesh {
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    pub fn face_count(&self) -> usize {
        self.triangles.len()
    }
}
