//! What every flow step reports.
//!
//! - Willmore energy `W = Σ_i H_i² A_i` with *barycentric* vertex areas `A_i` (one third of the
//!   incident triangle areas) and `H_i = ⟨(L f)_i, N_i⟩ / (2 A_i)`; a round sphere gives 4π.
//! - Quasi-conformal error Q of each triangle's affine map from the *input* surface to the
//!   current one: the ratio of the larger to the smaller singular value (paper §6.4.2, after
//!   Sander et al. 2001). Q = 1 for a similarity.
//! - Closure residual `|d f̃ − ẽ| / |ẽ|` over all half-edges: how far the edges produced by λ
//!   (Table 1 step VI) are from integrable; the Poisson solve (step VII) spreads this error.

use serde::{Deserialize, Serialize};

/// The metrics of the surface after one step (step 0 describes the input).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepMetrics {
    /// Steps taken so far; 0 is the input.
    pub step: usize,
    /// `Σ H² A` with barycentric areas (4π for a round sphere).
    pub willmore_energy: f64,
    /// Mean of the per-triangle quasi-conformal error Q against the input mesh.
    pub q_mean: f64,
    /// Area-weighted mean of Q (weights: current triangle areas).
    pub q_area_mean: f64,
    /// 95th percentile of Q over triangles.
    pub q_p95: f64,
    /// Largest Q over triangles.
    pub q_max: f64,
    /// `|d f̃ − ẽ| / |ẽ|` over all half-edges (0 for flows that do not integrate edges).
    pub closure_residual: f64,
    /// `|X λ − γ λ| / |λ|` of the inverse iteration, relative to the largest diagonal entry of
    /// X (0 for flows without an eigenproblem).
    pub eigen_residual: f64,
    /// Total surface area after the step.
    pub area: f64,
    /// Wall time of the step in milliseconds, metrics included.
    pub step_ms: f64,
}
