//! The denoising stage as a flow ([`Method::Denoise`](super::Method::Denoise)): each step is
//! up to [`ITERATIONS_PER_STEP`] outer iterations of guided normal filtering and the vertex
//! update ([`crate::denoise`]), reported with the same metrics as every other flow, so a job
//! streams the noise going away frame by frame.
//!
//! `max_deviation` is a tolerance here, not a stop: every vertex is kept within it of its input
//! position, so the result is the cleanest surface the filter reaches inside the bound (each
//! point of a face moves by at most the largest move of its corners, in both directions).

use super::classic::ClassicSurface;
use super::{Flow, FlowError, FlowParams, FlowState};
use crate::denoise::Denoiser;
use crate::mesh::creases::detect_creases;
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use crate::metrics::StepMetrics;
use std::time::Instant;

/// Outer iterations per step: the automatic count takes up to 20, so a run of the CLI's
/// default 10 steps (the service's is 20) sees the whole stage. A forced count above twice
/// the steps is cut off where the run ends (`completed`, "ran its N steps").
pub const ITERATIONS_PER_STEP: usize = 2;

/// Feature-preserving denoising, one step at a time ([`crate::denoise::Denoiser`]).
pub struct DenoiseFlow {
    surface: ClassicSurface,
    denoiser: Denoiser,
    /// To rebuild the denoiser for [`Flow::resume`] (it replays its iterations).
    mesh: Mesh,
    topology: Topology,
    params: FlowParams,
    /// The metrics of the last step (the input's before any).
    last: StepMetrics,
    /// The creases of the current surface under `params.feature_angle` (vertex pairs),
    /// found again after every step: the filter sharpens them as the noise goes.
    creases: Vec<[usize; 2]>,
}

impl DenoiseFlow {
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        params.validate()?;
        let topology = Topology::new(mesh);
        let denoiser = Self::denoiser(mesh, &topology, params);
        let surface = ClassicSurface::new(mesh, &topology, None, params.deviation_threads());
        let creases = Self::find_creases(&mesh.positions, &mesh.triangles, &topology, params);
        Ok(DenoiseFlow {
            creases,
            last: surface.initial,
            surface,
            denoiser,
            mesh: mesh.clone(),
            topology,
            params: params.clone(),
        })
    }

    fn find_creases(
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        topology: &Topology,
        params: &FlowParams,
    ) -> Vec<[usize; 2]> {
        detect_creases(positions, triangles, topology, params.feature_angle).vertex_pairs(topology)
    }

    fn denoiser(mesh: &Mesh, topology: &Topology, params: &FlowParams) -> Denoiser {
        // A hair inside the bound, so that rounding in the distance measure never puts a
        // vertex that used all of it past it.
        let within = params.max_deviation.map(|d| d * (1.0 - 1e-9));
        Denoiser::new(mesh, topology, params.denoise, Vec::new(), within)
    }
}

impl Flow for DenoiseFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let start = Instant::now();
        for _ in 0..ITERATIONS_PER_STEP {
            if self.denoiser.finished() {
                break;
            }
            self.denoiser.iterate(&mut self.surface.positions);
        }
        self.last = self.surface.finish_step(start, "denoising")?;
        self.creases = Self::find_creases(
            &self.surface.positions,
            &self.mesh.triangles,
            &self.topology,
            &self.params,
        );
        self.last = super::creases::with_crease_count(self.last, &self.creases);
        Ok(self.last)
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.surface.positions
    }

    fn initial_metrics(&self) -> StepMetrics {
        super::creases::with_crease_count(self.surface.initial, &self.creases)
    }

    fn creases(&self) -> &[[usize; 2]] {
        &self.creases
    }

    fn finished(&self) -> Option<String> {
        if !self.denoiser.finished() {
            return None;
        }
        let n = self.denoiser.iterations_done();
        Some(if self.denoiser.found_clean() {
            "no noise found: one filtering iteration barely changed the mesh's dihedral angles, \
             so the input is left as it is (denoise.iterations forces a count)"
                .into()
        } else {
            format!("denoised in {n} filtering iterations")
        })
    }

    fn checkpoint(&self) -> Option<FlowState> {
        Some(FlowState {
            metrics: self.last,
            positions: self.surface.positions.clone(),
            next_tau: self.params.tau,
            clean_steps: 0,
            carried: Default::default(),
        })
    }

    /// The denoiser is deterministic: a fresh one replays the steps to `state`'s, which must
    /// land on its surface.
    fn resume(&mut self, state: &FlowState) -> Result<(), FlowError> {
        self.denoiser = Self::denoiser(&self.mesh, &self.topology, &self.params);
        let mut positions = self.mesh.positions.clone();
        for _ in 0..state.metrics.step * ITERATIONS_PER_STEP {
            if self.denoiser.finished() {
                break;
            }
            self.denoiser.iterate(&mut positions);
        }
        if positions != state.positions {
            return Err(FlowError::Unsupported(
                "the checkpoint is not a surface this denoising run reaches".into(),
            ));
        }
        self.surface.restore(&positions, state.metrics.step);
        self.creases = Self::find_creases(
            &positions,
            &self.mesh.triangles,
            &self.topology,
            &self.params,
        );
        self.last = state.metrics;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::denoise::score::mean_normal_angle;
    use crate::flow::stopping::{Event, Outcome, Run};
    use crate::flow::{new_flow, Method};
    use crate::mesh::generate::{icosphere, with_noise};

    fn params() -> FlowParams {
        FlowParams {
            method: Method::Denoise,
            ..FlowParams::default()
        }
    }

    fn run(mesh: &Mesh, params: &FlowParams) -> (Vec<[f64; 3]>, Outcome, usize) {
        let flow = new_flow(mesh, params).expect("flow");
        let mut run = Run::new(flow, params, 50).expect("run");
        let mut steps = 0;
        loop {
            match run.advance().expect("advance") {
                Event::Step(_) => steps += 1,
                Event::Stopped { outcome, reason } => {
                    eprintln!("{outcome:?}: {reason}");
                    return (run.flow().positions().to_vec(), outcome, steps);
                }
            }
        }
    }

    #[test]
    fn a_run_ends_when_the_denoiser_is_done_and_the_sphere_is_smoother() {
        let clean = icosphere(4);
        let noisy = with_noise(clean.clone(), 0.3, 3);
        let (out, outcome, steps) = run(&noisy, &params());
        assert_eq!(outcome, Outcome::Completed);
        assert!((2..=10).contains(&steps), "{steps}");
        let before = mean_normal_angle(&noisy.positions, &clean.positions, &clean.triangles);
        let after = mean_normal_angle(&out, &clean.positions, &clean.triangles);
        assert!(after < before / 3.0, "θ {before} → {after}");
    }

    #[test]
    fn a_clean_mesh_ends_at_step_zero_unchanged() {
        let clean = icosphere(4);
        let (out, outcome, steps) = run(&clean, &params());
        assert_eq!((outcome, steps), (Outcome::AlreadyFair, 0));
        assert_eq!(out, clean.positions);
    }

    #[test]
    fn max_deviation_is_a_tolerance_every_vertex_keeps() {
        let clean = icosphere(4);
        let noisy = with_noise(clean.clone(), 0.3, 4);
        let bound = 0.3 * crate::mesh::generate::mean_edge_length(&clean) * 0.5;
        let p = FlowParams {
            max_deviation: Some(bound),
            ..params()
        };
        let (out, outcome, _) = run(&noisy, &p);
        assert_eq!(outcome, Outcome::Completed);
        let mut largest: f64 = 0.0;
        for (a, b) in out.iter().zip(&noisy.positions) {
            let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
            largest = largest.max(d);
        }
        assert!(largest <= bound * (1.0 + 1e-12), "{largest} > {bound}");
        // The bound is used, not avoided.
        assert!(largest > 0.9 * bound, "{largest} of {bound}");
    }

    #[test]
    fn a_checkpoint_resumes_onto_the_same_steps() {
        let noisy = with_noise(icosphere(3), 0.3, 5);
        let p = params();
        let mut a = new_flow(&noisy, &p).expect("flow");
        a.step().expect("step");
        let state = a.checkpoint().expect("checkpoint");
        let next = a.step().expect("step");
        let mut b = new_flow(&noisy, &p).expect("flow");
        b.resume(&state).expect("resume");
        let again = b.step().expect("step");
        assert_eq!(b.positions(), a.positions());
        assert_eq!(again.willmore_energy, next.willmore_energy);
    }
}
