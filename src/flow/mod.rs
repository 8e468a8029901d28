//! Flows on a [`Mesh`], one step at a time.
//!
//! A [`Flow`] owns its state (positions, cached operators, factorizations) and no threads:
//! the caller drives it with [`Flow::step`] and decides between steps whether to go on
//! (cancellation, deadlines), which is how the CLI and the job service both use it.

pub mod classic;
pub mod constraints;
pub mod curve;
pub mod dirac;
pub mod dirichlet;
pub mod filter;
pub mod mobius;
pub mod scale;
pub mod solver;
pub mod willmore;

use crate::mesh::Mesh;
use crate::metrics::StepMetrics;
use serde::{Deserialize, Serialize};

/// Which flow to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Conformal Willmore flow in curvature space (the paper).
    #[default]
    Conformal,
    /// Implicit mean curvature flow (Desbrun et al. 1999, backward Euler): the yardstick.
    Mcf,
    /// Conformalized mean curvature flow (Kazhdan, Solomon, Ben-Chen 2012); genus 0 only.
    Cmcf,
    /// Implicit bi-Laplacian flow (backward Euler on `ḟ = −Δ²f`).
    Bilaplacian,
    /// Taubin λ|μ smoothing (Taubin 1995), explicit.
    Taubin,
}

/// What happens at the boundary of a surface with boundary (§6.3). Closed surfaces ignore it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Boundary {
    /// The boundary moves freely (§6.2: disks need no constraint).
    #[default]
    Free,
    /// Boundary positions stay exactly where they are (§6.3.2): λ = 1 on the boundary and a
    /// Dirichlet Poisson problem for the positions.
    Fixed,
}

/// Parameters of a flow run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FlowParams {
    pub method: Method,
    /// Time step. For the conformal flow it has the paper's meaning (§4: the curvature update
    /// is `u ← (1 − 2τ)u`, stable for τ < 1). For MCF it is unitless: the backward Euler step is
    /// `τ · area / 4π`, so τ = 0.1 moves a unit sphere's radius by about 10%; the same for
    /// cMCF, `τ · (area / 4π)²` for the bi-Laplacian flow, and Taubin's λ for λ|μ smoothing
    /// (see `classic`).
    pub tau: f64,
    /// Inverse power iterations per step for the smallest eigenvector (§6.4.2 uses one).
    pub iterations: usize,
    /// Exactness constraints for surfaces of genus > 0 (§6.2, Appendix C). Switching them off
    /// is only useful to see what they prevent (Figure 12).
    pub exactness: bool,
    /// Möbius balancing toward the input's area distribution (§6.2, Appendix E.1).
    pub mobius_balancing: bool,
    /// Spectral filter of the flow direction (§4); `None` is the paper's plain flow.
    pub filter: Option<filter::SpectralFilter>,
    /// Boundary condition for surfaces with boundary (§6.3).
    pub boundary: Boundary,
}

impl Default for FlowParams {
    fn default() -> Self {
        FlowParams {
            method: Method::Conformal,
            tau: 0.5,
            iterations: 1,
            exactness: true,
            mobius_balancing: false,
            filter: None,
            boundary: Boundary::Free,
        }
    }
}

/// Why a flow could not be built or could not go on.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum FlowError {
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    #[error("not yet supported: {0}")]
    Unsupported(String),
    #[error("numerical failure at step {step}: {reason}")]
    Numerical { step: usize, reason: String },
}

/// One running flow. Steps are explicit; nothing runs in the background.
pub trait Flow: Send {
    /// Advance one step and report the metrics of the new surface.
    fn step(&mut self) -> Result<StepMetrics, FlowError>;
    /// Current positions, in the vertex order of the mesh the flow was built from.
    fn positions(&self) -> &[[f64; 3]];
    /// The metrics of the input surface (step 0).
    fn initial_metrics(&self) -> StepMetrics;
}

/// Build the flow `params.method` names on `mesh` (validated: see [`Mesh::new`]).
pub fn new_flow(mesh: &Mesh, params: &FlowParams) -> Result<Box<dyn Flow>, FlowError> {
    Ok(match params.method {
        Method::Conformal => Box::new(willmore::ConformalFlow::new(mesh, params)?),
        Method::Mcf => Box::new(classic::ImplicitMeanCurvatureFlow::new(mesh, params)?),
        Method::Cmcf => Box::new(classic::ConformalizedMeanCurvatureFlow::new(mesh, params)?),
        Method::Bilaplacian => Box::new(classic::ImplicitBilaplacianFlow::new(mesh, params)?),
        Method::Taubin => Box::new(classic::TaubinSmoothing::new(mesh, params)?),
    })
}
