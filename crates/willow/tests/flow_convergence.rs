//! Paper §6.4.1 and Figure 16: the conformal distortion of the flow converges linearly under
//! temporal and spatial refinement, on a surface of genus > 0 (issue 4).
//!
//! What is temporal and what is spatial (measured on the bumpy Clifford-class torus below):
//! - Spatial: the discrete edges `λ̄ e λ` are not exactly closed, and the Poisson solve spreads
//!   the mismatch. Per step it is first order in ρ (one step's closure residual on a sphere
//!   halves with τ), so over a fixed flow time it adds up to a floor that does not depend on
//!   the step and shrinks linearly with the mesh size (after 16 steps of total time 0.5, mean
//!   Q − 1 = 2.0e-2, 1.6e-2, 8.6e-3, 4.4e-3 on 24×12 … 192×96; the sphere does the same).
//! - Temporal: the exactness constraint (App. C) holds to first order in ρ only, so every step
//!   leaves a period error of order τ²: one step's closure residual on the torus falls about
//!   4× when τ halves at large τ (3.0e-2, 9.2e-3, 3.3e-3 for τ = 0.5, 0.25, 0.125 on 64×32).
//!   Over a fixed time T that is `n τ² = T τ`: linear in the step, as the paper says. More
//!   inverse iterations change nothing measurable (Q − 1 equal to three digits for 1, 3 and 8
//!   iterations), and the eigenvalue γ only shifts ρ by a constant, which keeps `λ̄ df λ`
//!   closed: neither is the temporal error here.
//!
//! Q is the per-triangle singular-value ratio of an affine map between two versions of the
//! mesh. Against the *input*, the spatial floor (1.2e-2 on 64×32) dominates the temporal part
//! at any step we can afford, and since Q − 1 is a per-triangle norm, a small temporal error
//! on top of a larger spatial one adds only quadratically: for 1, 2, 4, 8 steps mean Q − 1
//! against the input is 3.0e-2, 1.8e-2, 1.4e-2, 1.3e-2 (fitted slope 0.39), which says little
//! about the rate. The paper's genus-3 pretzel is coarse and takes huge steps, so its plot is
//! temporal-dominated. We therefore show the two halves of the claim separately, each on the
//! paper's quantity (mean Q − 1):
//! 1. temporal: Q of the map from a time-converged run (64 steps of the same total time) to
//!    the n-step result. Both carry the same spatial error up to O(τ), and composing two
//!    conformal maps is conformal, so what remains is the error of time stepping;
//! 2. spatial and temporal together: Q against the input when mesh size and step are halved
//!    together.
//!
//! Both would fail if the flow stopped being conformal: a non-conformal map keeps Q against
//! the input away from 1 under refinement (test 2), and test 1 also bounds Q against the input.

use willow::flow::{new_flow, FlowParams};
use willow::mesh::generate::torus;
use willow::mesh::Mesh;
use willow::metrics::ConformalReference;

/// A torus of revolution with R/r = √2 (the conformal class of the Clifford torus) carrying
/// smooth bumps: the surface of tests/flow_genus.rs, at any resolution.
fn bumpy_clifford_torus(u: usize, v: usize) -> Mesh {
    let mut mesh = torus(2f64.sqrt(), 1.0, u, v);
    for p in &mut mesh.positions {
        let bump = 1.0 + 0.08 * (3.0 * p[0]).sin() * (2.0 * p[1]).cos() + 0.05 * (5.0 * p[2]).sin();
        *p = [p[0] * bump, p[1] * bump, p[2] * bump];
    }
    mesh
}

/// Positions after `steps` steps of the conformal flow at `tau` (the paper's single inverse
/// iteration, exactness on).
fn flow(mesh: &Mesh, tau: f64, steps: usize) -> Vec<[f64; 3]> {
    let params = FlowParams {
        tau,
        // The raw method (Figure 18, §6.4): these tests measure what the flow itself does at a
        // fixed τ, so the safeguard (tests/flow_robust.rs) must not change the step.
        safeguard: false,
        ..FlowParams::default()
    };
    let mut flow = new_flow(mesh, &params).expect("flow");
    for _ in 0..steps {
        let m = flow.step().expect("step");
        assert!(m.willmore_energy.is_finite(), "W not finite");
    }
    flow.positions().to_vec()
}

/// Mean over triangles of Q − 1 for the map `from → to` (same connectivity).
fn mean_q_minus_one(from: &[[f64; 3]], to: &[[f64; 3]], triangles: &[[usize; 3]]) -> f64 {
    let reference = ConformalReference::new(from, triangles);
    let mut q = vec![0.0; triangles.len()];
    reference.quasi_conformal_errors_into(to, triangles, &mut q);
    q.iter().map(|q| q - 1.0).sum::<f64>() / q.len() as f64
}

/// Least-squares slope of `ln y` against `ln x`.
fn log_log_slope(x: &[f64], y: &[f64]) -> f64 {
    let lx: Vec<f64> = x.iter().map(|v| v.ln()).collect();
    let ly: Vec<f64> = y.iter().map(|v| v.ln()).collect();
    let n = lx.len() as f64;
    let (mx, my) = (lx.iter().sum::<f64>() / n, ly.iter().sum::<f64>() / n);
    let sxy: f64 = lx.iter().zip(&ly).map(|(a, b)| (a - mx) * (b - my)).sum();
    let sxx: f64 = lx.iter().map(|a| (a - mx).powi(2)).sum();
    sxy / sxx
}

/// Figure 16, temporal refinement: flow a fixed total time T = 0.25 in 1, 2, 4 and 8 steps on
/// the bumpy torus (64×32, genus 1) and measure mean Q − 1 of the map from a 64-step run of
/// the same time to each result. Measured: 5.06e-3, 2.10e-3, 9.41e-4, 4.24e-4 (ratios 2.4,
/// 2.2, 2.2), fitted log-log slope 1.19. Part of the excess over 1 is the reference's own
/// step (the errors are ∝ τ − τ_ref); the rest is higher order at large τ: with T = 0.5 the
/// slope is 1.32, with T = 0.8 (τ up to 0.8) 1.47. Against the input the same runs give mean
/// Q − 1 = 1.20e-2, 9.36e-3, 8.37e-3, 7.95e-3, approaching the 64-step run's spatial floor
/// 7.62e-3 from above.
#[test]
fn fixed_time_distortion_is_first_order_in_the_step() {
    let mesh = bumpy_clifford_torus(64, 32);
    let total = 0.25;
    let reference = flow(&mesh, total / 64.0, 64);
    let floor = mean_q_minus_one(&mesh.positions, &reference, &mesh.triangles);
    let mut taus = Vec::new();
    let mut temporal = Vec::new();
    let mut against_input = Vec::new();
    for steps in [1usize, 2, 4, 8] {
        let tau = total / steps as f64;
        let positions = flow(&mesh, tau, steps);
        let e = mean_q_minus_one(&reference, &positions, &mesh.triangles);
        let q = mean_q_minus_one(&mesh.positions, &positions, &mesh.triangles);
        eprintln!("{steps} steps, τ {tau:.4}: Q − 1 against the 64-step run {e:.3e}, against the input {q:.3e}");
        taus.push(tau);
        temporal.push(e);
        against_input.push(q);
    }
    let slope = log_log_slope(&taus, &temporal);
    eprintln!("fitted slope {slope:.3}; spatial floor (64 steps against the input) {floor:.3e}");
    assert!(
        (0.7..=1.5).contains(&slope),
        "temporal distortion {temporal:?} has slope {slope}, not about 1"
    );
    for pair in temporal.windows(2) {
        assert!(
            pair[1] < 0.7 * pair[0],
            "halving the step must shrink the temporal distortion: {temporal:?}"
        );
    }
    // The flow is conformal: every result is within a few percent of the input's angles, and
    // none is far below the time-converged run's floor. (With the discrete exactness of
    // flow::exactness the 8-step run lands 1% below it: 7.22e-3 against 7.28e-3.)
    for &q in &against_input {
        assert!(q < 0.03, "mean Q − 1 against the input {against_input:?}");
        assert!(
            q > 0.9 * floor,
            "Q − 1 {q} far below the 64-step floor {floor}"
        );
    }
    assert!(floor < 0.015, "spatial floor {floor}");
}

/// §6.4.1, "converges linearly under temporal and spatial refinement", on the quantity Figure
/// 16 plots (mean Q − 1 against the input): the bumpy torus at 48×24, 96×48 and 192×96 flowed
/// for T = 0.5 in 2, 4 and 8 steps (mesh size and step halved together). Measured: 2.21e-2,
/// 1.01e-2, 4.72e-3, fitted slope against the step 1.11. Before the exactness constraint
/// solved `D Z = v` in the least-squares sense (it solved `X₀ Z = M v`, i.e. Z ≈ D⁻²v), the
/// period error stayed first order and this floor stagnated near 1.2e-2–1.8e-2.
#[test]
fn distortion_against_the_input_converges_under_joint_refinement() {
    let total = 0.5;
    let mut taus = Vec::new();
    let mut distortion = Vec::new();
    for (u, v, steps) in [(48usize, 24usize, 2usize), (96, 48, 4), (192, 96, 8)] {
        let mesh = bumpy_clifford_torus(u, v);
        let tau = total / steps as f64;
        let positions = flow(&mesh, tau, steps);
        let q = mean_q_minus_one(&mesh.positions, &positions, &mesh.triangles);
        eprintln!("{u}×{v}, {steps} steps (τ {tau}): mean Q − 1 against the input {q:.3e}");
        taus.push(tau);
        distortion.push(q);
    }
    let slope = log_log_slope(&taus, &distortion);
    eprintln!("fitted slope {slope:.3}");
    assert!(
        (0.7..=1.5).contains(&slope),
        "distortion {distortion:?} has slope {slope} under joint refinement, not about 1"
    );
    assert!(distortion[2] < 0.007, "finest level: {distortion:?}");
}
