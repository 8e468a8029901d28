//! Discrete differential geometry on a [`crate::mesh::Mesh`]: small pure functions, one
//! operator each, named as in the paper and in Crane's DDG notes.
//!
//! Conventions: faces wind counter-clockwise seen from outside; the cotan Laplacian `L` is
//! positive semidefinite (`(L f)_i = Σ_j w_ij (f_i − f_j)`), so `L f ≈ 2 H N A` with `H > 0` on
//! an outward sphere.

pub mod bvh;
pub mod cache;
pub mod distance;
pub mod hodge;
pub mod intrinsic;
pub mod operators;
pub mod quaternion;
pub mod stratified;
pub mod vec3;

pub use operators::*;
pub use quaternion::Quaternion;
