//! Conformal flow on surfaces of genus > 0 (exactness constraints, App. C) and Möbius
//! balancing (App. E), issue 4.

mod mesh_support;
use mesh_support::shared_surface;

use std::f64::consts::PI;
use willow::flow::mobius::{area_distortion, log_area_spread};
use willow::flow::{new_flow, Flow, FlowParams, Method};
use willow::geometry::barycentric_vertex_areas;
use willow::mesh::generate::torus;
use willow::mesh::Mesh;
use willow::metrics::StepMetrics;

fn params(tau: f64) -> FlowParams {
    FlowParams {
        method: Method::Conformal,
        tau,
        // The raw method (Figure 18, §6.4): these tests measure what the flow itself does at a
        // fixed τ, so the safeguard (tests/flow_robust.rs) must not change the step.
        safeguard: false,
        ..FlowParams::default()
    }
}

/// A torus of revolution with R/r = √2 (the conformal class of the Clifford torus, whose
/// Willmore energy 2π² is the minimum over all tori) carrying smooth bumps.
fn bumpy_clifford_torus(u: usize, v: usize) -> Mesh {
    let mut mesh = torus(2f64.sqrt(), 1.0, u, v);
    for p in &mut mesh.positions {
        let bump = 1.0 + 0.08 * (3.0 * p[0]).sin() * (2.0 * p[1]).cos() + 0.05 * (5.0 * p[2]).sin();
        *p = [p[0] * bump, p[1] * bump, p[2] * bump];
    }
    mesh
}

fn run(flow: &mut dyn Flow, steps: usize) -> Vec<StepMetrics> {
    (0..steps).map(|_| flow.step().expect("step")).collect()
}

#[test]
fn bumpy_torus_flows_toward_the_clifford_torus() {
    let mesh = bumpy_clifford_torus(64, 32);
    let mut flow = new_flow(&mesh, &params(0.5)).expect("flow");
    let w0 = flow.initial_metrics().willmore_energy;
    let metrics = run(flow.as_mut(), 10);
    let mut previous = w0;
    for m in &metrics {
        eprintln!(
            "step {} W/2π² {:.4} Q {:.4} closure {:.2e}",
            m.step,
            m.willmore_energy / (2.0 * PI * PI),
            m.q_mean,
            m.closure_residual
        );
        assert!(m.willmore_energy.is_finite());
        assert!(
            m.willmore_energy <= previous * (1.0 + 1e-6),
            "W rose at step {}",
            m.step
        );
        previous = m.willmore_energy;
    }
    let last = metrics.last().expect("ten steps");
    let ratio = last.willmore_energy / (2.0 * PI * PI);
    assert!(
        ratio < 1.03,
        "W/2π² = {ratio} (started at {})",
        w0 / (2.0 * PI * PI)
    );
    assert!(
        last.closure_residual < 0.01,
        "closure {}",
        last.closure_residual
    );
    assert!(last.q_mean < 1.1, "mean Q {}", last.q_mean);
}

#[test]
fn exactness_constraint_keeps_the_torus_closed_and_conformal() {
    // Figure 12: without the exactness constraint the edges stop integrating.
    let mesh = bumpy_clifford_torus(48, 24);
    let with = run(new_flow(&mesh, &params(0.5)).expect("flow").as_mut(), 5);
    let off = FlowParams {
        exactness: false,
        ..params(0.5)
    };
    let without = run(new_flow(&mesh, &off).expect("flow").as_mut(), 5);
    let (a, b) = (with.last().expect("5"), without.last().expect("5"));
    eprintln!(
        "with: closure {:.3e} Q {:.4}; without: closure {:.3e} Q {:.4}",
        a.closure_residual, a.q_mean, b.closure_residual, b.q_mean
    );
    let max_closure =
        |ms: &[StepMetrics]| ms.iter().map(|m| m.closure_residual).fold(0.0, f64::max);
    assert!(
        max_closure(&without) > 3.0 * max_closure(&with),
        "closure with {} without {}",
        max_closure(&with),
        max_closure(&without)
    );
    assert!(
        b.q_mean - 1.0 > 1.5 * (a.q_mean - 1.0),
        "Q with {} without {}",
        a.q_mean,
        b.q_mean
    );
}

#[test]
fn real_meshes_of_genus_one_two_and_five_lose_energy() {
    // botijo_genus5_irregular.obj needs a smaller step: see the next test.
    for (name, steps) in [("bob_small.obj", 10), ("genus2_24.obj", 10)] {
        let mesh = shared_surface(name);
        let mut flow = new_flow(&mesh, &params(0.5)).expect("flow");
        let w0 = flow.initial_metrics().willmore_energy;
        let metrics = run(flow.as_mut(), steps);
        let last = metrics.last().expect("steps ran");
        eprintln!(
            "{name}: W {w0:.3} -> {:.3}, Q {:.4}, closure {:.2e}",
            last.willmore_energy, last.q_mean, last.closure_residual
        );
        assert!(metrics
            .iter()
            .all(|m| m.willmore_energy.is_finite() && m.q_mean.is_finite()));
        assert!(
            last.willmore_energy < w0,
            "{name}: W {w0} -> {}",
            last.willmore_energy
        );
        assert!(
            last.closure_residual < 0.2,
            "{name}: closure {}",
            last.closure_residual
        );
    }
}

#[test]
fn botijo_genus5_irregular_flows_and_needs_its_exactness_constraint() {
    // Genus 5 with needles (a 0.005°/179.6° face on its flat bottom, min angle 0.01°). Two
    // causes made it diverge within three steps at any τ:
    // - the new edges were integrated edge by edge, which does not close a face; on a needle
    //   the gap is far wider than the face, so each step folded needles out of their plane
    //   and W rose even at τ = 0.02 (557 → 628 → 675 → 690). Fixed in willmore.rs: each face
    //   maps its edges by the face average of λ̄ e λ (the Galerkin form of Eq. 6);
    // - the exactness constraint solved X₀ Z = M v (Z ≈ D⁻²v) instead of D Z = v.
    // What remains is the step size: W/4π is 44 here (a sphere has 1), so a step of τ moves
    // the potential ρ² of X(ρ) by ~4τ²·44 against a spectral gap of X₀ of 0.044 (both at area
    // 4π): the smallest eigenvector is then far from λ ≡ 1 and the step's second-order error
    // grows. Measured (10 steps): τ = 0.0125 is stable (W 557 → 458, Q 1.07, closure 5e-3),
    // τ = 0.025 runs away after 8 steps, τ = 0.05 after 4.
    let mesh = shared_surface("botijo_genus5_irregular.obj");
    let tau = 0.0125;
    let mut flow = new_flow(&mesh, &params(tau)).expect("flow");
    let w0 = flow.initial_metrics().willmore_energy;
    let with = run(flow.as_mut(), 10);
    let mut previous = w0;
    for m in &with {
        eprintln!(
            "botijo step {}: W {:.3} Q {:.4} Q max {:.3} closure {:.2e} eigen {:.2e}",
            m.step, m.willmore_energy, m.q_mean, m.q_max, m.closure_residual, m.eigen_residual
        );
        assert!(m.willmore_energy.is_finite() && m.q_mean.is_finite());
        assert!(
            m.willmore_energy < previous,
            "W rose at step {}: {previous} -> {}",
            m.step,
            m.willmore_energy
        );
        previous = m.willmore_energy;
        assert!(m.closure_residual < 0.01, "closure {}", m.closure_residual);
        assert!(m.q_max < 2.0, "Q max {}", m.q_max);
    }
    let last = with.last().expect("ten steps");
    assert!(
        last.willmore_energy < 0.9 * w0,
        "W {w0} -> {}",
        last.willmore_energy
    );

    // Figure 12: without the constraint the edges stop integrating (measured: closure 2.9e-2
    // from the first step, Q 1.37 after three, W rising; it diverges after five).
    let off = FlowParams {
        exactness: false,
        ..params(tau)
    };
    let mut flow = new_flow(&mesh, &off).expect("flow");
    let without = run(flow.as_mut(), 3);
    let max_closure =
        |ms: &[StepMetrics]| ms.iter().map(|m| m.closure_residual).fold(0.0, f64::max);
    let (a, b) = (&with[2], &without[2]);
    eprintln!(
        "botijo after 3 steps: with closure {:.2e} Q {:.4}; without closure {:.2e} Q {:.4}",
        max_closure(&with[..3]),
        a.q_mean,
        max_closure(&without),
        b.q_mean
    );
    assert!(max_closure(&without) > 3.0 * max_closure(&with[..3]));
    assert!(b.q_mean - 1.0 > 5.0 * (a.q_mean - 1.0));
}

#[test]
fn mobius_balancing_reduces_area_distortion() {
    // Figure 13: sphere inversions cost no Willmore energy but distort area; balancing pulls
    // the area distribution back toward the input's.
    // A sphere with one large bulge: rounding it off redistributes area from one side to the
    // other, which is what an inversion can undo.
    let mut mesh = willow::mesh::generate::icosphere(3);
    for p in &mut mesh.positions {
        let d2 = p[0] * p[0] + p[1] * p[1] + (p[2] - 1.0) * (p[2] - 1.0);
        let r = 1.0 + 0.8 * (-d2 / 0.5).exp();
        *p = [p[0] * r, p[1] * r, p[2] * r];
    }
    let input_areas = barycentric_vertex_areas(&mesh);
    let distortion = |balancing: bool| {
        let p = FlowParams {
            mobius_balancing: balancing,
            ..params(0.5)
        };
        let mut flow = new_flow(&mesh, &p).expect("flow");
        run(flow.as_mut(), 6);
        let now = Mesh {
            positions: flow.positions().to_vec(),
            triangles: mesh.triangles.clone(),
        };
        let areas = barycentric_vertex_areas(&now);
        (
            area_distortion(&areas, &input_areas),
            log_area_spread(&areas, &input_areas),
        )
    };
    let (without, with) = (distortion(false), distortion(true));
    eprintln!("max/min area ratio and log spread: without {without:?} with {with:?}");
    assert!(with.1 < without.1, "balancing: {with:?} vs {without:?}");
}
