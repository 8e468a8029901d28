//! Resuming a flow from a checkpoint (issue 11): a flow built afresh on the same input and put
//! back on another flow's checkpoint takes the steps the first one would have taken. This is
//! what lets a job redelivered after a crash go on from its last checkpoint and still give the
//! result an uninterrupted run gives.
//!
//! Same τ, same retries, same step numbers; positions agree to rounding: a running conformal
//! flow rescales its cached geometry after the scale policy instead of recomputing it (one
//! pass saved per step), while a resumed one computes it from the checkpointed surface, so the
//! two differ in the last bits (measured: 6e-9 after five steps on a unit-size noisy torus).

use willow::flow::{new_flow, FlowParams, FlowState, Method};
use willow::mesh::generate::{pretzel, torus, with_noise};
use willow::mesh::Mesh;

/// Largest coordinate difference allowed between a resumed and an uninterrupted run, on
/// meshes of unit size: rounding, a thousand times below anything visible.
const ROUNDING: f64 = 1e-7;

/// Run `steps` steps uninterrupted, and again with a checkpoint after `at` steps taken by a
/// second flow built from scratch; return the largest coordinate difference of every step.
fn resumed_difference(mesh: &Mesh, params: &FlowParams, at: usize, steps: usize) -> f64 {
    let mut straight = new_flow(mesh, params).expect("flow");
    let mut first = new_flow(mesh, params).expect("flow");
    let mut worst = 0.0f64;
    let mut state: Option<FlowState> = None;
    for _ in 0..at {
        straight.step().expect("step");
        first.step().expect("step");
        state = first.checkpoint();
    }
    let state = state.expect("a safeguarded flow checkpoints");
    assert_eq!(state.metrics.step, at);
    if params.method == Method::Conformal && params.tau >= 0.5 {
        assert!(
            state.next_tau < params.tau && state.clean_steps > 0,
            "the checkpoint should hold a reduced τ, got {} after {} clean steps",
            state.next_tau,
            state.clean_steps
        );
    }
    drop(first); // the crashed worker
    let mut resumed = new_flow(mesh, params).expect("flow");
    resumed.resume(&state).expect("resume");
    assert_eq!(resumed.positions(), straight.positions());
    for _ in at..steps {
        let a = straight.step().expect("step");
        let b = resumed.step().expect("step");
        assert_eq!(a.step, b.step, "step numbers continue");
        assert_eq!(a.tau, b.tau, "the safeguard's τ control continues");
        assert_eq!(a.rejected, b.rejected);
        for (p, q) in straight.positions().iter().zip(resumed.positions()) {
            for k in 0..3 {
                worst = worst.max((p[k] - q[k]).abs());
            }
        }
    }
    worst
}

#[test]
fn a_resumed_conformal_flow_takes_the_same_steps_on_a_noisy_torus() {
    // At τ = 0.9 the safeguard takes step 5 of this noisy torus at τ/4 and step 6 at its
    // first try (measured), so the checkpoint after step 6 carries a reduced τ and a count
    // of clean steps. (The small torus this test used before takes its first steps whole
    // since the safeguard judges damage rather than Q, issue 26, then crawls.)
    let mesh = with_noise(torus(2.5, 1.0, 64, 32), 0.15, 3);
    let params = FlowParams {
        method: Method::Conformal,
        tau: 0.9,
        ..FlowParams::default()
    };
    let d = resumed_difference(&mesh, &params, 6, 11);
    assert!(d <= ROUNDING, "resumed steps differ by {d:e}");
}

#[test]
fn a_resumed_flow_with_exactness_and_balancing_takes_the_same_steps() {
    let mesh = with_noise(pretzel(2, 8), 0.1, 3);
    let params = FlowParams {
        method: Method::Conformal,
        tau: 0.3,
        exactness: true,
        mobius_balancing: true,
        ..FlowParams::default()
    };
    let d = resumed_difference(&mesh, &params, 3, 8);
    assert!(d <= ROUNDING, "resumed steps differ by {d:e}");
}

#[test]
fn a_resumed_mean_curvature_flow_takes_the_same_steps() {
    let mesh = with_noise(torus(1.0, 0.4, 24, 12), 0.1, 11);
    let params = FlowParams {
        method: Method::Mcf,
        tau: 1e-3,
        ..FlowParams::default()
    };
    let d = resumed_difference(&mesh, &params, 3, 8);
    assert!(d <= ROUNDING, "resumed steps differ by {d:e}");
}

#[test]
fn a_checkpoint_of_another_mesh_is_refused() {
    let mesh = torus(1.0, 0.4, 24, 12);
    let other = torus(1.0, 0.4, 12, 6);
    let params = FlowParams::default();
    let mut flow = new_flow(&other, &params).expect("flow");
    flow.step().expect("step");
    let state = flow.checkpoint().expect("checkpoint");
    let mut fresh = new_flow(&mesh, &params).expect("flow");
    let err = fresh.resume(&state).expect_err("a foreign checkpoint");
    assert!(err.to_string().contains("vertices"), "{err}");
    let mut nan = state.clone();
    nan.positions = vec![[f64::NAN; 3]; mesh.vertex_count()];
    assert!(fresh.resume(&nan).is_err(), "a non-finite checkpoint");
}
