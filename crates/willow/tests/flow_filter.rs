//! The spectral filter of §4 (Figures 8 and 19), issue 4.

use willow::flow::filter::SpectralFilter;
use willow::flow::{new_flow, FlowParams};
use willow::mesh::generate::{bumpy_sphere, icosphere};
use willow::mesh::Mesh;

fn filtered(tau: f64, filter: Option<SpectralFilter>) -> FlowParams {
    FlowParams {
        tau,
        filter,
        ..FlowParams::default()
    }
}

#[test]
fn every_filter_order_gives_a_stable_and_different_flow() {
    let mesh = bumpy_sphere(3, 0.2);
    let mut finals: Vec<Vec<[f64; 3]>> = Vec::new();
    for k in 0..=3 {
        let p = filtered(0.5, Some(SpectralFilter { sigma: 0.01, k }));
        let mut flow = new_flow(&mesh, &p).expect("flow");
        let w0 = flow.initial_metrics().willmore_energy;
        let mut w = w0;
        for _ in 0..5 {
            let m = flow.step().expect("step");
            assert!(
                m.willmore_energy.is_finite() && m.q_mean < 1.2,
                "k = {k}: {m:?}"
            );
            assert!(
                m.willmore_energy <= w * (1.0 + 1e-6),
                "k = {k}: W rose at step {}",
                m.step
            );
            w = m.willmore_energy;
        }
        assert!(w < w0, "k = {k}");
        finals.push(flow.positions().to_vec());
    }
    for a in 0..finals.len() {
        for b in a + 1..finals.len() {
            let d = finals[a]
                .iter()
                .zip(&finals[b])
                .map(|(p, q)| (p[0] - q[0]).abs() + (p[1] - q[1]).abs() + (p[2] - q[2]).abs())
                .fold(0.0, f64::max);
            assert!(d > 1e-4, "k = {a} and k = {b} give the same flow");
        }
    }
}

/// Least-squares amplitudes of the radial deviation on two shapes: a large (degree-2) and a
/// small (high-frequency) bump pattern.
fn amplitudes(mesh: &Mesh) -> (f64, f64) {
    let (mut gll, mut gls, mut gss, mut bl, mut bs) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let c = centroid(mesh);
    let radii: Vec<f64> = mesh
        .positions
        .iter()
        .map(|p| ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt())
        .collect();
    let mean = radii.iter().sum::<f64>() / radii.len() as f64;
    for (p, r) in mesh.positions.iter().zip(&radii) {
        let n = [(p[0] - c[0]) / r, (p[1] - c[1]) / r, (p[2] - c[2]) / r];
        let (l, s) = (large(n), small(n));
        let d = r / mean - 1.0;
        gll += l * l;
        gls += l * s;
        gss += s * s;
        bl += l * d;
        bs += s * d;
    }
    let det = gll * gss - gls * gls;
    ((gss * bl - gls * bs) / det, (gll * bs - gls * bl) / det)
}

fn centroid(mesh: &Mesh) -> [f64; 3] {
    let n = mesh.positions.len() as f64;
    let s = mesh
        .positions
        .iter()
        .fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]);
    [s[0] / n, s[1] / n, s[2] / n]
}

fn large(n: [f64; 3]) -> f64 {
    1.5 * n[2] * n[2] - 0.5
}

fn small(n: [f64; 3]) -> f64 {
    (6.0 * n[0]).sin() * (6.0 * n[1]).sin() * (6.0 * n[2]).cos()
}

#[test]
fn with_k_two_large_features_shrink_more_slowly_than_small_bumps() {
    // Figure 19: the plain flow scales every feature alike; filtering with k = 2 keeps the
    // large ones longer, like position-based Willmore flow.
    let mut mesh = icosphere(4);
    for p in &mut mesh.positions {
        let n = *p;
        let r = 1.0 + 0.15 * large(n) + 0.02 * small(n);
        *p = [n[0] * r, n[1] * r, n[2] * r];
    }
    let (l0, s0) = amplitudes(&mesh);
    let kept = |filter: Option<SpectralFilter>| {
        let mut flow = new_flow(&mesh, &filtered(0.1, filter)).expect("flow");
        flow.step().expect("step");
        let now = Mesh {
            positions: flow.positions().to_vec(),
            triangles: mesh.triangles.clone(),
        };
        let (l, s) = amplitudes(&now);
        (l / l0, s / s0)
    };
    let plain = kept(None);
    let k2 = kept(Some(SpectralFilter {
        sigma: 1.0 / 400.0,
        k: 2,
    }));
    eprintln!("fraction kept (large, small): plain {plain:?}, k = 2 {k2:?}");
    // Plain: both shrink at a similar rate. Filtered: the large feature keeps clearly more.
    assert!(
        k2.0 > 0.97 && plain.0 < 0.9,
        "large feature kept: plain {plain:?}, k = 2 {k2:?}"
    );
    assert!(
        k2.0 - k2.1 > 2.0 * (plain.0 - plain.1).abs(),
        "plain {plain:?} vs k = 2 {k2:?}"
    );
}

#[test]
fn bad_filter_parameters_are_refused() {
    let mesh = icosphere(1);
    for f in [
        SpectralFilter { sigma: 0.0, k: 2 },
        SpectralFilter {
            sigma: f64::NAN,
            k: 1,
        },
        SpectralFilter { sigma: 1.0, k: 4 },
    ] {
        let err = new_flow(&mesh, &filtered(0.5, Some(f)))
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(err.contains("filter"), "{f:?}: {err}");
    }
}
