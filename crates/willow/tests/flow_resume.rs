//! Resuming a flow from a checkpoint (issue 11): a flow built afresh on the same input and put
//! back on another flow's checkpoint takes the steps the first one would have taken. This is
//! what lets a job redelivered after a crash go on from its last checkpoint and still give the
//! result an uninterrupted run gives.
//!
//! Same τ, same retries, same step numbers; positions agree to rounding: a running conformal
//! flow rescales its cached geometry after the scale policy instead of recomputing it (one
//! pass saved per step), while a resumed one computes it from the checkpointed surface, so the
//! two differ in the last bits (measured: 6e-9 after five steps on a unit-size noisy torus).

use willow::flow::region::{Region, Seam};
use willow::flow::{new_flow, FlowParams, FlowState, Method};
use willow::mesh::generate::{pretzel, torus, with_noise};
use willow::mesh::io::{Asset, Format, Limits};
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

/// Spot's right ear (as in `flow_region`).
const EAR: Region = Region::Sphere {
    center: [0.40, 0.72, -0.20],
    radius: 0.15,
};

/// `steps` steps of `params` on `mesh` by one flow, and by a flow resumed from another's
/// checkpoint after `at` steps, that checkpoint passed through `edit` first; the largest
/// coordinate difference of any later step, and the checkpoint as taken.
fn resumed_region_difference(
    mesh: &Mesh,
    params: &FlowParams,
    at: usize,
    steps: usize,
    edit: impl Fn(&mut FlowState),
) -> (f64, FlowState) {
    let mut straight = new_flow(mesh, params).expect("flow");
    for _ in 0..at {
        straight.step().expect("step");
    }
    let taken = straight.checkpoint().expect("a region flow checkpoints");
    let mut state = taken.clone();
    edit(&mut state);
    let mut resumed = new_flow(mesh, params).expect("flow");
    resumed.resume(&state).expect("resume");
    let mut worst = 0.0f64;
    for _ in at..steps {
        let a = straight.step().expect("step");
        let b = resumed.step().expect("step");
        assert_eq!((a.step, a.tau, a.rejected), (b.step, b.tau, b.rejected));
        for (p, q) in straight.positions().iter().zip(resumed.positions()) {
            for k in 0..3 {
                worst = worst.max((p[k] - q[k]).abs());
            }
        }
    }
    (worst, taken)
}

/// A region's flow carries the curvature change its held border cannot realize from step
/// to step (`flow/willmore/pinned.rs`, ABSORB_MEMORY): the checkpoint holds it, so spot's
/// ear with a smooth seam resumed after 5 of 12 steps takes the uninterrupted run's steps.
/// Resumed without it (as a checkpoint written before it was kept resumes: nothing
/// absorbed) the steps differ far beyond rounding: the carried state is what makes them
/// the same.
#[test]
fn a_resumed_region_flow_takes_the_same_steps() {
    let asset = Asset::read(
        include_bytes!("data/spot_triangulated.obj"),
        Format::Obj,
        &Limits::default(),
    )
    .expect("spot reads");
    let mesh = asset.surface().clone();
    let params = FlowParams {
        regions: vec![EAR],
        seam: Seam::Smooth,
        ..FlowParams::default()
    };
    let (d, state) = resumed_region_difference(&mesh, &params, 5, 12, |_| {});
    let absorbed = &state.carried.absorbed;
    let largest = absorbed.iter().fold(0.0f64, |m, d| m.max(d.abs()));
    eprintln!(
        "ear: {} absorbed values, largest {largest:.3e}; resumed steps differ by {d:e}",
        absorbed.len()
    );
    assert!(largest > 1e-3, "the checkpoint holds the absorbed change");
    // Whole-mesh positions; the absorbed change is the submesh's, not the mesh's.
    assert_eq!(state.positions.len(), mesh.vertex_count());
    assert!(absorbed.len() < mesh.vertex_count());
    assert!(d <= ROUNDING, "resumed steps differ by {d:e}");
    let (forgot, _) =
        resumed_region_difference(&mesh, &params, 5, 12, |s| s.carried.absorbed.clear());
    eprintln!("resumed without the absorbed change: steps differ by {forgot:e}");
    assert!(
        forgot > 1e3 * ROUNDING,
        "without the absorbed change the steps differ by only {forgot:e}"
    );
    // A checkpoint of another region (another submesh) does not fit.
    let mut foreign = state.clone();
    foreign.carried.absorbed.push(0.0);
    let mut fresh = new_flow(&mesh, &params).expect("flow");
    let err = fresh
        .resume(&foreign)
        .expect_err("a foreign absorbed change");
    assert!(err.to_string().contains("absorbed"), "{err}");
}
