//! Sparse linear algebra on the fixed vertex-graph patterns of a mesh.
//!
//! The flows never change connectivity, so every matrix they factor keeps one pattern for the
//! life of a flow: [`solver`] holds that pattern ([`solver::BlockPattern`]), the Cholesky
//! factorization whose symbolic analysis is done once and whose numeric factorization is
//! redone each step (and its mixed-precision form), [`supernodal`] the numeric kernels (with
//! the quaternionic path for the Dirac matrix), and [`ordering`] the fill-reducing orderings.

pub mod ordering;
pub mod solver;
pub mod supernodal;
