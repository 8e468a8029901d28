//! The large-mesh paths of the conformal flow (issue 14) give the flow the exact paths give:
//! the single-precision factor kept across steps and solved to double precision by conjugate
//! gradients, and factorizations split over threads.

use willow::flow::{new_flow, FlowParams, Method, Precision};
use willow::mesh::generate::{bumpy_sphere, with_noise};
use willow::mesh::Mesh;
use willow::metrics::StepMetrics;

fn run(mesh: &Mesh, params: &FlowParams, steps: usize) -> (Vec<StepMetrics>, Vec<[f64; 3]>, f64) {
    let mut flow = new_flow(mesh, params).expect("flow");
    let mut metrics = Vec::new();
    let mut kept = 0.0;
    for _ in 0..steps {
        metrics.push(flow.step().expect("step"));
        kept += flow
            .profile()
            .and_then(|p| p.counts().iter().find(|(n, _)| *n == "X factor kept"))
            .map_or(0.0, |&(_, c)| c);
    }
    (metrics, flow.positions().to_vec(), kept)
}

fn relative(a: f64, b: f64) -> f64 {
    (a - b).abs() / a.abs().max(b.abs()).max(f64::MIN_POSITIVE)
}

/// A noisy bumpy sphere (shuffled by noise, not generated clean), flowed with X factored in
/// double precision every step and in single precision kept across steps: W and Q agree per
/// step to 1e-8 relative (measured: 1e-12; the issue asks 1e-6), far inside the eigen-residual
/// the flow accepts, and the mixed path
/// really kept its factor (so the test covers the reuse, not only fresh factors).
#[test]
fn mixed_precision_flow_matches_the_double_precision_flow() {
    let mesh = with_noise(bumpy_sphere(5, 0.15), 0.1, 7);
    let params = |precision| FlowParams {
        method: Method::Conformal,
        tau: 0.05,
        safeguard: false,
        precision,
        ..FlowParams::default()
    };
    let (double, _, kept_double) = run(&mesh, &params(Precision::Double), 6);
    let (mixed, _, kept_mixed) = run(&mesh, &params(Precision::Mixed), 6);
    assert_eq!(kept_double, 0.0);
    assert!(
        kept_mixed >= 1.0,
        "the single-precision factor was never kept"
    );
    for (d, m) in double.iter().zip(&mixed) {
        for (name, a, b, tolerance) in [
            ("W", d.willmore_energy, m.willmore_energy, 1e-8),
            ("Q mean", d.q_mean, m.q_mean, 1e-8),
            ("Q max", d.q_max, m.q_max, 1e-8),
            ("closure", d.closure_residual, m.closure_residual, 1e-6),
        ] {
            assert!(
                relative(a, b) < tolerance,
                "step {}: {name} {a} (double) vs {b} (mixed)",
                d.step
            );
        }
        assert!(
            (d.eigen_residual - m.eigen_residual).abs() < 1e-6,
            "step {}: eigen-residual {} vs {}",
            d.step,
            d.eigen_residual,
            m.eigen_residual
        );
    }
    // The flow moved: the comparison is not between two unchanged surfaces.
    let w0 = double[0].willmore_energy;
    assert!(double[5].willmore_energy < 0.9 * w0);
}

/// Threads change when subtrees are factored, never what: on a mesh large enough for nested
/// dissection (41k vertices), two threads give bitwise the same surface as one.
#[test]
fn threads_give_the_same_flow_bit_for_bit() {
    let mesh = bumpy_sphere(6, 0.15);
    let params = |threads| FlowParams {
        method: Method::Conformal,
        safeguard: false,
        precision: Precision::Double,
        threads,
        ..FlowParams::default()
    };
    let (_, one, _) = run(&mesh, &params(1), 2);
    let (_, two, _) = run(&mesh, &params(2), 2);
    assert!(one == two, "the surfaces differ");
}

/// On a round sphere X is singular up to its 1e-9 shift (ρ = 0 is integrable), far beyond
/// what a single-precision factor resolves on its own; conjugate gradients still solve to
/// double precision, and the sphere stays a sphere (W = 4π to discretization error).
#[test]
fn mixed_precision_solves_the_nearly_singular_x_of_a_round_sphere() {
    let mesh = willow::mesh::generate::icosphere(4);
    let params = |precision| FlowParams {
        method: Method::Conformal,
        safeguard: false,
        precision,
        ..FlowParams::default()
    };
    let (double, _, _) = run(&mesh, &params(Precision::Double), 3);
    let (mixed, _, _) = run(&mesh, &params(Precision::Mixed), 3);
    let four_pi = 4.0 * std::f64::consts::PI;
    for (d, m) in double.iter().zip(&mixed) {
        assert!((m.willmore_energy - four_pi).abs() < 0.01 * four_pi);
        assert!(relative(d.willmore_energy, m.willmore_energy) < 1e-8);
        assert!(relative(d.q_max, m.q_max) < 1e-8);
    }
}

/// Two separate surfaces in one mesh (two elimination trees, nested dissection on a
/// disconnected graph): two threads still give bitwise the same flow, and the mixed path the
/// double one's W.
#[test]
fn two_components_flow_alike_on_any_thread_count_and_precision() {
    let a = with_noise(bumpy_sphere(5, 0.15), 0.05, 1);
    let b = bumpy_sphere(5, 0.1);
    let offset = a.positions.len();
    let mut mesh = a.clone();
    mesh.positions
        .extend(b.positions.iter().map(|p| [p[0] + 5.0, p[1], p[2]]));
    mesh.triangles.extend(
        b.triangles
            .iter()
            .map(|t| [t[0] + offset, t[1] + offset, t[2] + offset]),
    );
    assert!(mesh.vertex_count() >= willow::linalg::ordering::ND_MIN_VERTICES);
    let params = |threads, precision| FlowParams {
        method: Method::Conformal,
        tau: 0.1,
        safeguard: false,
        threads,
        precision,
        ..FlowParams::default()
    };
    let (double_one, one, _) = run(&mesh, &params(1, Precision::Double), 2);
    let (_, two, _) = run(&mesh, &params(2, Precision::Double), 2);
    assert!(one == two, "the surfaces differ");
    let (mixed, _, _) = run(&mesh, &params(2, Precision::Mixed), 2);
    for (d, m) in double_one.iter().zip(&mixed) {
        assert!(relative(d.willmore_energy, m.willmore_energy) < 1e-8);
    }
}
