//! Robustness on what users upload (issue 10): noisy surfaces of genus 1, 2 and 3, real meshes
//! of genus > 0, at a small τ and at the default τ. W must never rise, Q must stay bounded and
//! no value may be non-finite; a step the surface cannot take at the requested τ is taken at a
//! smaller one, and the frames say so.

mod mesh_support;
use mesh_support::shared_surface;

use willow::flow::{new_flow, FlowError, FlowParams, Method};
use willow::mesh::generate::{bumpy_sphere, pretzel, torus, with_noise};
use willow::mesh::Mesh;
use willow::metrics::StepMetrics;

/// Largest rise of W over the lowest W seen so far that any step may show (the 0.1%).
const MAX_RISE: f64 = 1e-3;

struct Run {
    initial: StepMetrics,
    steps: Vec<StepMetrics>,
    /// Why the flow stopped early (the safeguard found no acceptable step), if it did.
    stopped: Option<FlowError>,
}

fn flow(mesh: &Mesh, tau: f64, steps: usize) -> Run {
    let params = FlowParams {
        method: Method::Conformal,
        tau,
        ..FlowParams::default()
    };
    let mut flow = new_flow(mesh, &params).expect("flow");
    let initial = flow.initial_metrics();
    let mut out = Vec::new();
    let mut stopped = None;
    for _ in 0..steps {
        match flow.step() {
            Ok(m) => {
                assert!(
                    flow.positions().iter().flatten().all(|x| x.is_finite()),
                    "non-finite position after step {}",
                    m.step
                );
                out.push(m);
            }
            Err(e @ FlowError::NoProgress { .. }) => {
                // The flow stays on the last accepted surface: still finite.
                assert!(flow.positions().iter().flatten().all(|x| x.is_finite()));
                stopped = Some(e);
                break;
            }
            Err(e) => panic!("step failed: {e}"),
        }
    }
    Run {
        initial,
        steps: out,
        stopped,
    }
}

/// W never rises more than [`MAX_RISE`] above its running minimum, every metric is finite,
/// Q max stays below `q_bound`, and each frame's τ is at most the requested one. Returns the
/// last W.
fn assert_descends(name: &str, run: &Run, tau: f64, q_bound: f64) -> f64 {
    let mut lowest = run.initial.willmore_energy;
    for m in &run.steps {
        for (what, x) in [
            ("W", m.willmore_energy),
            ("Q max", m.q_max),
            ("closure", m.closure_residual),
            ("area", m.area),
        ] {
            assert!(
                x.is_finite(),
                "{name}: {what} not finite at step {}",
                m.step
            );
        }
        assert!(
            m.willmore_energy <= lowest * (1.0 + MAX_RISE),
            "{name} τ={tau}: W rose from {lowest} to {} at step {}",
            m.willmore_energy,
            m.step
        );
        lowest = lowest.min(m.willmore_energy);
        assert!(
            m.q_max < q_bound,
            "{name} τ={tau}: Q max {} at step {}",
            m.q_max,
            m.step
        );
        assert!(m.tau > 0.0 && m.tau <= tau, "{name}: frame τ {}", m.tau);
    }
    let last = run
        .steps
        .last()
        .map_or(run.initial.willmore_energy, |m| m.willmore_energy);
    let rejected: u32 = run.steps.iter().map(|m| m.rejected).sum();
    eprintln!(
        "{name} τ={tau}: W {:.3} → {last:.3} in {} steps, Q max {:.2}, {rejected} rejected tries{}",
        run.initial.willmore_energy,
        run.steps.len(),
        run.steps.iter().fold(1.0f64, |q, m| q.max(m.q_max)),
        run.stopped
            .as_ref()
            .map(|e| format!(", stopped: {e}"))
            .unwrap_or_default()
    );
    last
}

/// A torus of revolution with centre radius `ratio` and tube radius 1, with Gaussian noise of
/// `noise` × the mean edge length per coordinate.
fn noisy_torus(ratio: f64, noise: f64, seed: u64) -> Mesh {
    let m = with_noise(torus(ratio, 1.0, 64, 32), noise, seed);
    Mesh::new(m.positions, m.triangles).expect("valid")
}

#[test]
fn noisy_tori_descend_at_small_and_default_tau() {
    for (ratio, noise) in [(2.5, 0.05), (2.5, 0.15), (2f64.sqrt(), 0.1)] {
        let mesh = noisy_torus(ratio, noise, 11);
        for tau in [0.05, 0.5] {
            let run = flow(&mesh, tau, 40);
            let name = format!("torus {ratio:.2}:1, noise {noise}");
            // Q max is the worst triangle against a noisy input; at τ = 0.5 a few slivers of
            // the 10% noise Clifford-class torus reach ~100 (measured), at τ = 0.05 ~3.
            let q_bound = if tau < 0.1 { 10.0 } else { 250.0 };
            let last = assert_descends(&name, &run, tau, q_bound);
            assert_eq!(
                run.steps.len(),
                40,
                "{name} τ={tau} stopped: {:?}",
                run.stopped
            );
            // Fairing, not just not diverging: a real share of the noise's energy is gone.
            // 0.85, not 0.8, since folds are judged against the input (issue 26): genus 3 at
            // τ = 0.5 ends at 0.82 (W 329 → 270, measured), its flow pushing a face toward a
            // fold that the safeguard no longer lets happen over two steps.
            assert!(
                last < 0.85 * run.initial.willmore_energy,
                "{name} τ={tau}: W only {} → {last}",
                run.initial.willmore_energy
            );
        }
    }
}

#[test]
fn a_torus_of_revolution_stays_at_its_own_energy() {
    // The 2.5:1 torus of revolution is the Willmore minimizer of its conformal class (and the
    // constrained flow must not leave the class): W stays, Q stays 1.
    let mesh = torus(2.5, 1.0, 64, 32);
    for tau in [0.05, 0.5] {
        let run = flow(&mesh, tau, 20);
        let w0 = run.initial.willmore_energy;
        for m in &run.steps {
            assert!(
                (m.willmore_energy - w0).abs() < 1e-5 * w0,
                "τ={tau}: W {w0} → {} at step {}",
                m.willmore_energy,
                m.step
            );
            assert!(m.q_max < 1.0 + 1e-4, "τ={tau}: Q max {}", m.q_max);
        }
    }
}

#[test]
fn noisy_genus_two_and_three_descend() {
    for holes in [2, 3] {
        let m = with_noise(pretzel(holes, 4), 0.1, 5);
        let mesh = Mesh::new(m.positions, m.triangles).expect("valid");
        for tau in [0.05, 0.5] {
            let run = flow(&mesh, tau, 40);
            let name = format!("noisy genus {holes}");
            let last = assert_descends(&name, &run, tau, 200.0);
            // 0.85, not 0.8, since folds are judged against the input (issue 26): genus 3 at
            // τ = 0.5 ends at 0.82 (W 329 → 270, measured), its flow pushing a face toward a
            // fold that the safeguard no longer lets happen over two steps.
            assert!(
                last < 0.85 * run.initial.willmore_energy,
                "{name} τ={tau}: W only {} → {last}",
                run.initial.willmore_energy
            );
        }
    }
}

#[test]
fn shared_meshes_of_higher_genus_descend() {
    for name in ["bob_small.obj", "genus2_24.obj"] {
        let mesh = shared_surface(name);
        for tau in [0.05, 0.5] {
            let run = flow(&mesh, tau, 40);
            let last = assert_descends(name, &run, tau, 20.0);
            assert!(last < 0.9 * run.initial.willmore_energy, "{name} τ={tau}");
            if let Some(FlowError::NoProgress { step, .. }) = &run.stopped {
                // Stopping is allowed only near the end of the descent: the last few steps
                // moved W by less than 1% (genus2_24 at τ = 0.5 stalls at W ≈ 37.5, where
                // even τ/1024 raises W by ~1e-6: see the closing note of issue 10).
                let n = run.steps.len();
                assert!(n >= 3, "{name} τ={tau}: stopped at step {step}");
                let (a, b) = (
                    run.steps[n - 3].willmore_energy,
                    run.steps[n - 1].willmore_energy,
                );
                assert!(
                    (a - b).abs() < 1e-2 * a,
                    "{name} τ={tau}: stopped while W moved {a} → {b}"
                );
            }
        }
    }
}

#[test]
fn a_step_too_large_is_taken_smaller_and_says_so() {
    // A heavily noisy torus at τ = 0.9: steps at the requested τ overshoot.
    let mesh = noisy_torus(2.5, 0.15, 3);
    let run = flow(&mesh, 0.9, 12);
    assert_descends("torus noise 0.15", &run, 0.9, 100.0);
    let smaller: Vec<&StepMetrics> = run.steps.iter().filter(|m| m.tau < 0.9).collect();
    assert!(
        !smaller.is_empty(),
        "some steps must be taken below τ = 0.9"
    );
    assert!(
        run.steps.iter().any(|m| m.rejected > 0),
        "the frames must count the rejected tries"
    );
    // The same flow unguarded goes uphill (or breaks down): that is what the safeguard stops.
    let params = FlowParams {
        tau: 0.9,
        safeguard: false,
        ..FlowParams::default()
    };
    let mut unguarded = new_flow(&mesh, &params).expect("flow");
    let mut lowest = unguarded.initial_metrics().willmore_energy;
    let mut went_wrong = false;
    for _ in 0..12 {
        match unguarded.step() {
            Ok(m) => {
                assert_eq!(m.tau, 0.9);
                assert_eq!(m.rejected, 0);
                let within = m.willmore_energy <= lowest * (1.0 + MAX_RISE);
                if !within {
                    went_wrong = true;
                    break;
                }
                lowest = lowest.min(m.willmore_energy);
            }
            Err(_) => {
                went_wrong = true;
                break;
            }
        }
    }
    assert!(
        went_wrong,
        "the unguarded flow should misbehave on this input"
    );
}

#[test]
fn mean_curvature_flow_is_safeguarded_too() {
    // Implicit MCF at a large step pinches a bumpy sphere; safeguarded it either descends at a
    // smaller τ or stops on its last good surface, never streaming garbage.
    let mesh = bumpy_sphere(3, 0.4);
    let params = FlowParams {
        method: Method::Mcf,
        tau: 2.0,
        ..FlowParams::default()
    };
    let mut flow = new_flow(&mesh, &params).expect("flow");
    let mut lowest = flow.initial_metrics().willmore_energy;
    for _ in 0..15 {
        match flow.step() {
            Ok(m) => {
                assert!(m.willmore_energy <= lowest * (1.0 + MAX_RISE));
                assert!(m.q_max.is_finite() && m.tau <= 2.0);
                lowest = lowest.min(m.willmore_energy);
            }
            Err(FlowError::NoProgress { .. }) => break,
            Err(e) => panic!("{e}"),
        }
        assert!(flow.positions().iter().flatten().all(|x| x.is_finite()));
    }
}
