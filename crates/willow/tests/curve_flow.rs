//! Isometric curve flow (paper §5): each test asserts a number the math predicts.

use std::f64::consts::{PI, TAU};
use willow::curve::{
    dual_inner, dual_lengths, edge_lengths, project_out_closure_constraints, rotate_edges,
    tangent_angles, tangents, turning_angles, ConstraintBasis, Curve, CurveError, CurveFlow,
    CurveParams, CurvePoisson,
};

/// Deterministic xorshift64* in [−1, 1): the tests need reproducible jitter, not a crate.
struct Jitter(u64);

impl Jitter {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let bits = self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11;
        bits as f64 / (1u64 << 52) as f64 - 1.0
    }
}

fn circle(n: usize, radius: f64, center: [f64; 2]) -> Curve {
    let points = (0..n)
        .map(|i| {
            let t = TAU * i as f64 / n as f64;
            [center[0] + radius * t.cos(), center[1] + radius * t.sin()]
        })
        .collect();
    Curve::new(points, true).expect("a uniform circle is a valid curve")
}

/// `r = 1 + 0.2 sin 5t` plus radial jitter of ±0.01, 256 vertices, counter-clockwise.
fn noisy_closed_curve() -> Curve {
    let n = 256;
    let mut jitter = Jitter(0x5eed_1234_abcd_0001);
    let points = (0..n)
        .map(|i| {
            let t = TAU * i as f64 / n as f64;
            let r = 1.0 + 0.2 * (5.0 * t).sin() + 0.01 * jitter.next();
            [r * t.cos(), r * t.sin()]
        })
        .collect();
    Curve::new(points, true).expect("the noisy curve is valid")
}

/// Least-squares slope of `log y` against `log x`.
fn log_log_slope(x: &[f64], y: &[f64]) -> f64 {
    let lx: Vec<f64> = x.iter().map(|v| v.ln()).collect();
    let ly: Vec<f64> = y.iter().map(|v| v.ln()).collect();
    let mx = lx.iter().sum::<f64>() / lx.len() as f64;
    let my = ly.iter().sum::<f64>() / ly.len() as f64;
    let sxy: f64 = lx.iter().zip(&ly).map(|(a, b)| (a - mx) * (b - my)).sum();
    let sxx: f64 = lx.iter().map(|a| (a - mx) * (a - mx)).sum();
    sxy / sxx
}

fn flow(curve: Curve, tau: f64) -> CurveFlow {
    CurveFlow::new(curve, CurveParams { tau }).expect("valid curve and tau")
}

#[test]
fn uniform_circle_is_a_fixed_point() {
    let radius = 2.0;
    let curve = circle(128, radius, [3.0, -1.0]);
    let before = curve.points.clone();
    let mut f = flow(curve, 0.5);
    // κ_i = φ/ℓ* = (2π/n) / (2r sin(π/n)) = (1/r)(1 + O(1/n²)), positive counter-clockwise.
    for &k in f.curvature() {
        assert!(
            (k - 1.0 / radius).abs() < 1e-3,
            "κ = {k}, 1/r = {}",
            1.0 / radius
        );
    }
    for _ in 0..3 {
        let m = f.step();
        assert!(m.curvature_std_over_mean < 1e-10);
        assert!(m.max_edge_length_distortion < 1e-12);
    }
    let moved = f
        .points()
        .iter()
        .zip(&before)
        .map(|(a, b)| (a[0] - b[0]).hypot(a[1] - b[1]))
        .fold(0.0, f64::max);
    assert!(moved < 1e-12 * radius, "a circle moved by {moved}");
}

#[test]
fn noisy_closed_curve_becomes_round_within_eight_steps() {
    let curve = noisy_closed_curve();
    let length = curve.length();
    let mut f = flow(curve, 0.5);
    let start = f.initial_metrics();
    assert!(start.curvature_std_over_mean > 1.0, "{start:?}");
    let mut steps = 0;
    while f.last_metrics().curvature_std_over_mean >= 1e-2 {
        assert!(steps < 8, "not round after 8 steps: {:?}", f.last_metrics());
        f.step();
        steps += 1;
    }
    // The isometric minimizer of E = ∫κ² with turning number 1 is the circle of the same
    // length: κ = 2π/L, E = 4π²/L.
    let m = f.last_metrics();
    let circle_energy = 4.0 * PI * PI / length;
    assert!(
        (m.energy / circle_energy - 1.0).abs() < 1e-3,
        "E = {} after {steps} steps, circle {circle_energy}",
        m.energy
    );
    assert!(m.energy < start.energy / 50.0);
}

#[test]
fn edge_length_distortion_converges_quadratically_in_tau() {
    // Figure 11: the worst edge-length distortion of one step is O(τ²), because the closure
    // constraints are exact to first order (App. A) and the Poisson solve spreads the rest.
    let taus = [0.4, 0.2, 0.1, 0.05];
    let mut distortion = Vec::new();
    let mut gap = Vec::new();
    for &tau in &taus {
        let m = flow(noisy_closed_curve(), tau).step();
        distortion.push(m.max_edge_length_distortion);
        gap.push(m.closure_gap);
    }
    let slope = log_log_slope(&taus, &distortion);
    assert!(
        (1.6..=2.4).contains(&slope),
        "distortion {distortion:?} has log-log slope {slope}"
    );
    let gap_slope = log_log_slope(&taus, &gap);
    assert!(
        (1.6..=2.4).contains(&gap_slope),
        "closure gap {gap:?} has log-log slope {gap_slope}"
    );
    assert!(distortion[0] < 0.05, "{distortion:?}");
}

/// `z(t) = e^{2it} + 0.3 e^{it}`: a curve with an inner loop and turning number 2.
fn double_loop() -> Curve {
    let n = 240;
    let points = (0..n)
        .map(|i| {
            let t = TAU * i as f64 / n as f64;
            [
                (2.0 * t).cos() + 0.3 * t.cos(),
                (2.0 * t).sin() + 0.3 * t.sin(),
            ]
        })
        .collect();
    Curve::new(points, true).expect("valid")
}

/// Lemniscate of Gerono `(sin t, sin t cos t)`: a figure-eight, turning number 0.
fn figure_eight() -> Curve {
    let n = 240;
    let points = (0..n)
        .map(|i| {
            let t = TAU * i as f64 / n as f64;
            [t.sin(), t.sin() * t.cos()]
        })
        .collect();
    Curve::new(points, true).expect("valid")
}

#[test]
fn turning_number_is_preserved() {
    for (curve, k) in [(figure_eight(), 0), (double_loop(), 2)] {
        assert_eq!(curve.turning_number(), Some(k));
        let mut f = flow(curve, 0.5);
        let e0 = f.initial_metrics().energy;
        for _ in 0..20 {
            let m = f.step();
            assert!(
                (m.total_curvature - TAU * k as f64).abs() < 1e-9,
                "k = {k}: total curvature {} at step {}",
                m.total_curvature,
                m.step
            );
            assert_eq!(f.curve().turning_number(), Some(k));
        }
        assert!(
            f.last_metrics().energy < e0,
            "k = {k}: the flow did not fair"
        );
    }
}

#[test]
fn open_curve_keeps_its_length_and_straightens() {
    // A wavy open arc. With no constraints the interior curvature is scaled exactly by
    // (1 − 2τ) each step and the Poisson solve on a path integrates the tangents exactly, so:
    // lengths are kept to rounding, E falls by exactly (1 − 2τ)² per step, κ stays 0 at the
    // endpoints, and the endpoints move apart until their distance equals the length.
    let n = 200;
    let mut jitter = Jitter(42);
    let points: Vec<[f64; 2]> = (0..n)
        .map(|i| {
            let x = i as f64 / (n - 1) as f64 * 3.0;
            [x, 0.3 * (3.0 * x).sin() + 0.005 * jitter.next()]
        })
        .collect();
    let curve = Curve::new(points, false).expect("valid");
    let length = curve.length();
    let tau = 0.25;
    let mut f = flow(curve, tau);
    let mut energy = f.initial_metrics().energy;
    let chord = |f: &CurveFlow| {
        let p = f.points();
        let (a, b) = (p[0], p[p.len() - 1]);
        (b[0] - a[0]).hypot(b[1] - a[1])
    };
    let mut distance = chord(&f);
    assert!(distance < 0.9 * length);
    for _ in 0..12 {
        let m = f.step();
        assert!((m.total_length / length - 1.0).abs() < 1e-6, "{m:?}");
        assert!(m.max_edge_length_distortion < 1e-9, "{m:?}");
        let ratio = m.energy / energy;
        assert!(
            (ratio - (1.0 - 2.0 * tau).powi(2)).abs() < 1e-6,
            "energy ratio {ratio} at step {}",
            m.step
        );
        energy = m.energy;
        let kappa = f.curvature();
        assert_eq!((kappa[0], kappa[n - 1]), (0.0, 0.0));
        let d = chord(&f);
        assert!(d > distance, "endpoints came closer at step {}", m.step);
        distance = d;
    }
    assert!(distance > (1.0 - 1e-4) * length, "{distance} vs {length}");
}

#[test]
fn closed_curve_closes_after_every_step() {
    let curve = noisy_closed_curve();
    let centroid = |p: &[[f64; 2]]| {
        let n = p.len() as f64;
        let s = p.iter().fold([0.0, 0.0], |s, q| [s[0] + q[0], s[1] + q[1]]);
        [s[0] / n, s[1] / n]
    };
    let c0 = centroid(&curve.points);
    let mut f = flow(curve, 0.5);
    for _ in 0..10 {
        let m = f.step();
        assert!(m.poisson_residual < 1e-10, "{m:?}");
        assert!(m.closure_gap < 0.05, "{m:?}");
        assert!(m.max_edge_length_distortion < 0.05, "{m:?}");
        assert!((m.total_curvature - TAU).abs() < 1e-9, "{m:?}");
        let c = centroid(f.points());
        assert!(
            (c[0] - c0[0]).hypot(c[1] - c0[1]) < 1e-12,
            "the centroid moved"
        );
    }
    // Once round, little is left to close. (Not nothing: a polygon with these unequal edge
    // lengths and κ exactly constant does not close, and the gap left by one step feeds the
    // next one's tangents; at τ = 0.5 it halves each step.)
    let m = f.last_metrics();
    assert!(
        m.closure_gap < 1e-4 && m.max_edge_length_distortion < 1e-4,
        "{m:?}"
    );
}

#[test]
fn poisson_solve_satisfies_the_full_laplacian() {
    // Truth: build the dense Laplacian of §5.2 (L_ij = −1/ℓ_ij, L_ii = Σ 1/ℓ) and check
    // L f = b for a right-hand side summing to zero, on cycles and paths of every small size
    // (the twisted elimination meets in the middle, so odd and even sizes differ).
    for closed in [true, false] {
        for n in 2..14usize {
            if closed && n < 3 {
                continue;
            }
            let m = if closed { n } else { n - 1 };
            let ell: Vec<f64> = (0..m).map(|e| 0.3 + (e as f64 * 2.3).sin().abs()).collect();
            let mut dense = vec![vec![0.0; n]; n];
            for (e, &l) in ell.iter().enumerate() {
                let (i, j) = (e, (e + 1) % n);
                dense[i][i] += 1.0 / l;
                dense[j][j] += 1.0 / l;
                dense[i][j] -= 1.0 / l;
                dense[j][i] -= 1.0 / l;
            }
            let mut b: Vec<[f64; 2]> = (0..n)
                .map(|i| [(i as f64 * 1.7).sin(), (i as f64 * 0.9).cos()])
                .collect();
            let mean = b.iter().fold([0.0, 0.0], |s, q| [s[0] + q[0], s[1] + q[1]]);
            for q in &mut b {
                q[0] -= mean[0] / n as f64;
                q[1] -= mean[1] / n as f64;
            }
            let solver = CurvePoisson::new(&ell, closed).expect("small");
            let mut f = vec![[0.0; 2]; n];
            solver.solve(&b, &mut f);
            assert_eq!(f[0], [0.0, 0.0], "vertex 0 is pinned");
            for i in 0..n {
                for c in 0..2 {
                    let lf: f64 = (0..n).map(|j| dense[i][j] * f[j][c]).sum();
                    assert!(
                        (lf - b[i][c]).abs() < 1e-12,
                        "closed = {closed}, n = {n}, row {i}: {lf} vs {}",
                        b[i][c]
                    );
                }
            }
        }
    }
}

#[test]
fn closed_form_projection_matches_modified_gram_schmidt() {
    // The flow projects with moments; ConstraintBasis is the textbook MGS of {1, fˣ, fʸ}.
    // Far from the origin on purpose: centring must keep the moments accurate.
    let mut curve = noisy_closed_curve();
    for p in &mut curve.points {
        p[0] = 1e3 + 0.5 * p[0];
        p[1] = -2e3 + 2.0 * p[1];
    }
    let n = curve.points.len();
    let mut dual = vec![0.0; n];
    dual_lengths(&curve.edge_lengths(), true, &mut dual);
    let mut basis = ConstraintBasis::with_len(n).expect("small");
    basis.rebuild(&curve.points, &dual);
    assert_eq!(basis.len(), 3);
    for i in 0..3 {
        for j in 0..3 {
            let g = dual_inner(basis.vector(i), basis.vector(j), &dual);
            assert!(
                (g - if i == j { 1.0 } else { 0.0 }).abs() < 1e-9,
                "<<c{i}, c{j}>> = {g}"
            );
        }
    }
    let v0: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin() + 3.0).collect();
    let mut by_mgs = v0.clone();
    basis.project_out(&mut by_mgs, &dual);
    let mut by_moments = v0.clone();
    project_out_closure_constraints(&curve.points, &dual, &mut by_moments);
    let scale = v0.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    for (a, b) in by_mgs.iter().zip(&by_moments) {
        assert!((a - b).abs() < 1e-9 * scale, "{a} vs {b}");
    }
    // And the result is orthogonal to 1, fˣ, fʸ.
    let ones = vec![1.0; n];
    let xs: Vec<f64> = curve.points.iter().map(|p| p[0]).collect();
    let ys: Vec<f64> = curve.points.iter().map(|p| p[1]).collect();
    for c in [&ones, &xs, &ys] {
        let norm = dual_inner(c, c, &dual).sqrt();
        assert!(dual_inner(&by_moments, c, &dual).abs() < 1e-9 * norm * scale);
    }
}

#[test]
fn smallest_curves_are_fixed_points() {
    // A segment has no interior vertex, so nothing to flow. A closed triangle has 3 vertices
    // and 3 independent constraints {1, fˣ, fʸ}: the projected direction is 0, so any
    // triangle, even a scalene one, stays put.
    for curve in [
        Curve::new(vec![[0.0, 0.0], [2.0, 1.0]], false).expect("valid"),
        Curve::new(vec![[0.0, 0.0], [3.0, 0.0], [0.5, 1.0]], true).expect("valid"),
    ] {
        let before = curve.points.clone();
        let mut f = flow(curve, 0.5);
        for _ in 0..3 {
            let m = f.step();
            assert!(m.max_edge_length_distortion < 1e-12, "{m:?}");
        }
        for (a, b) in f.points().iter().zip(&before) {
            assert!((a[0] - b[0]).hypot(a[1] - b[1]) < 1e-12, "{a:?} vs {b:?}");
        }
    }
}

#[test]
fn a_step_removes_the_mean_translation_and_rotation() {
    // §5.1: "we simply remove the mean change in position and angle". The vertex centroid is
    // kept exactly; the length-weighted mean change of edge angle is zero for the target
    // tangents, and the Poisson projection's own rotations (of the order of the length
    // distortion, 2e-3 here) barely move it.
    for (curve, tau) in [(noisy_closed_curve(), 0.5), (double_loop(), 0.3)] {
        let before = curve.clone();
        let mut f = flow(curve, tau);
        f.step();
        let after = f.curve();
        let (ell_old, ell_new) = (before.edge_lengths(), after.edge_lengths());
        let m = ell_old.len();
        let mut weighted = 0.0;
        for k in 0..m {
            let j = (k + 1) % m;
            let a = [
                before.points[j][0] - before.points[k][0],
                before.points[j][1] - before.points[k][1],
            ];
            let b = [
                after.points[j][0] - after.points[k][0],
                after.points[j][1] - after.points[k][1],
            ];
            let turn = (a[0] * b[1] - a[1] * b[0]).atan2(a[0] * b[0] + a[1] * b[1]);
            weighted += f.edge_lengths()[k] * turn;
        }
        let mean_turn = weighted / ell_old.iter().sum::<f64>();
        let changed = ell_old.iter().zip(&ell_new).any(|(a, b)| a != b);
        assert!(changed, "the step did something");
        assert!(mean_turn.abs() < 1e-3, "mean rotation {mean_turn}");
    }
}

#[test]
fn rotating_edges_equals_the_cumulative_angle_tangents() {
    // The flow rotates current edges by Δ_k; §5.2 writes T̃_k = ℓ_k (cos θ_k, sin θ_k) with the
    // cumulative θ. Same vectors, for small and large Δ (both code paths).
    let curve = noisy_closed_curve();
    let n = curve.points.len();
    let ell: Vec<f64> = (0..n).map(|k| 0.01 + 0.001 * (k % 7) as f64).collect();
    let delta: Vec<f64> = (0..n)
        .map(|k| {
            if k % 5 == 0 {
                2.5
            } else {
                0.3 * (k as f64).sin()
            }
        })
        .collect();
    let mut rotated = vec![[0.0; 2]; n];
    rotate_edges(&curve.points, &delta, &ell, &mut rotated);
    // θ_k = arg e_k + Δ_k, built the §5.2 way: θ_0 plus the sum of turning angles, with the
    // Δ differences folded into the "curvature" so that θ_k − θ_{k−1} = φ_k + Δ_k − Δ_{k−1}.
    let mut phi = vec![0.0; n];
    turning_angles(&curve.points, true, &mut phi);
    let mut dual = vec![0.0; n];
    dual_lengths(&curve.edge_lengths(), true, &mut dual);
    let kappa: Vec<f64> = (0..n)
        .map(|k| {
            let step = if k > 0 { delta[k] - delta[k - 1] } else { 0.0 };
            (phi[k] + step) / dual[k]
        })
        .collect();
    let e0 = [
        curve.points[1][0] - curve.points[0][0],
        curve.points[1][1] - curve.points[0][1],
    ];
    let mut theta = vec![0.0; n];
    tangent_angles(e0[1].atan2(e0[0]) + delta[0], &kappa, &dual, &mut theta);
    let mut direct = vec![[0.0; 2]; n];
    tangents(&theta, &ell, &mut direct);
    for (k, (a, b)) in rotated.iter().zip(&direct).enumerate() {
        assert!(
            (a[0] - b[0]).hypot(a[1] - b[1]) < 1e-12 * ell[k],
            "edge {k}: {a:?} vs {b:?}"
        );
    }
}

#[test]
fn discrete_curvature_follows_the_paper() {
    // A unit square traversed counter-clockwise turns by π/2 at each corner; ℓ* = 1.
    let square =
        Curve::new(vec![[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], true).expect("valid");
    assert_eq!(square.curvature(), vec![PI / 2.0; 4]);
    assert_eq!(square.turning_number(), Some(1));
    // Clockwise: κ < 0, turning number −1.
    let mut cw = square.points.clone();
    cw.reverse();
    let cw = Curve::new(cw, true).expect("valid");
    assert_eq!(cw.turning_number(), Some(-1));
    // Open: endpoints have κ = 0; dual lengths sum to the length.
    let open = Curve::new(vec![[0.0, 0.0], [2.0, 0.0], [2.0, 1.0]], false).expect("valid");
    let mut phi = vec![9.0; 3];
    turning_angles(&open.points, false, &mut phi);
    assert_eq!(phi, vec![0.0, PI / 2.0, 0.0]);
    let mut ell = vec![0.0; 2];
    edge_lengths(&open.points, false, &mut ell);
    let mut dual = vec![0.0; 3];
    dual_lengths(&ell, false, &mut dual);
    assert_eq!(dual, vec![1.0, 1.5, 0.5]);
    assert_eq!(open.curvature(), vec![0.0, PI / 3.0, 0.0]);
    assert_eq!(open.turning_number(), None);
}

#[test]
fn bad_input_gives_the_specific_error() {
    let nan = Curve::new(
        vec![[0.0, 0.0], [1.0, 0.0], [1.0, f64::NAN], [0.0, 1.0]],
        true,
    );
    assert!(
        matches!(nan, Err(CurveError::NonFinite { index: 2, .. })),
        "{nan:?}"
    );
    assert_eq!(
        Curve::new(vec![[0.0, 0.0], [1.0, 0.0]], true),
        Err(CurveError::TooFewPoints {
            closed: true,
            min: 3,
            got: 2
        })
    );
    assert_eq!(
        Curve::new(vec![[0.0, 0.0]], false),
        Err(CurveError::TooFewPoints {
            closed: false,
            min: 2,
            got: 1
        })
    );
    assert_eq!(
        Curve::new(vec![[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]], false),
        Err(CurveError::ZeroLengthEdge { index: 1 })
    );
    // A closed curve must not repeat its first point: the closing edge has zero length.
    assert_eq!(
        Curve::new(vec![[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 0.0]], true),
        Err(CurveError::ZeroLengthEdge { index: 3 })
    );
    assert_eq!(
        Curve::new(vec![[0.0, 0.0], [2.0, 0.0], [1.0, 0.0]], false),
        Err(CurveError::Cusp { index: 1 })
    );
    // A hand-built invalid curve is caught by the flow too, and so is τ outside (0, 1).
    let bad = Curve {
        points: vec![[0.0, 0.0]],
        closed: true,
    };
    assert!(matches!(
        CurveFlow::new(bad, CurveParams::default()),
        Err(CurveError::TooFewPoints { .. })
    ));
    for tau in [0.0, 1.0, -0.1, f64::NAN] {
        assert!(matches!(
            CurveFlow::new(circle(8, 1.0, [0.0, 0.0]), CurveParams { tau }),
            Err(CurveError::InvalidParameter { name: "tau", .. })
        ));
    }

    for json in [
        &b"{\"points\": [[0, 0], [1, 0]"[..],
        b"{\"points\": [[0, 0, 1], [1, 0, 1]]}",
        b"{\"points\": [[0, 0], [1, 0]], \"closed\": true, \"colour\": 3}",
        b"\"a curve\"",
        b"",
    ] {
        let r = Curve::from_json(json);
        assert!(matches!(r, Err(CurveError::Json(_))), "{r:?}");
    }
    // Well-formed JSON with an invalid curve gives the curve error, not a JSON error.
    assert_eq!(
        Curve::from_json(b"{\"points\": [[0, 0], [1, 0]], \"closed\": true}"),
        Err(CurveError::TooFewPoints {
            closed: true,
            min: 3,
            got: 2
        })
    );

    let obj_line = |text: &str| match Curve::from_obj(text.as_bytes()) {
        Err(CurveError::Obj { line, .. }) => line,
        other => panic!("expected an OBJ error for {text:?}, got {other:?}"),
    };
    assert_eq!(obj_line("v 0 0 0\nv 1 0 0\n"), 0, "no `l` line");
    assert_eq!(obj_line("v 0 0 0\nv 1 x 0\nl 1 2\n"), 2, "bad number");
    assert_eq!(
        obj_line("v 0 0 0\nv 1 0 0\nl 1 3\n"),
        3,
        "index out of range"
    );
    assert_eq!(obj_line("v 0 0 0\nv 1 0 0\nl 1 0\n"), 3, "index 0");
    assert_eq!(
        obj_line("v 0 0\nv 1 0\nv 0 1\nl 1 2\nl 2 3\n"),
        5,
        "two polylines"
    );
    assert_eq!(obj_line("v 0 0\nv 1 0\nv 0 1\nf 1 2 3\n"), 4, "a face");
    assert_eq!(obj_line("v 0 0 0\nv 1 0 0.5\nl 1 2\n"), 2, "not planar");
    assert_eq!(
        obj_line("v 0 0\nv 1 0\nl -3 -1\n"),
        3,
        "relative index too far back"
    );
    assert_eq!(obj_line("v 0 0\nv 1 0\nl 1\n"), 3, "one index");
    assert_eq!(obj_line("v 0\nl 1 1\n"), 1, "v without y");
    assert!(matches!(
        Curve::from_obj(b"v 0 0 0\nv nan 0 0\nv 1 1 0\nl 1 2 3\n"),
        Err(CurveError::NonFinite { index: 1, .. })
    ));
    assert_eq!(
        Curve::from_obj(b"v 0 0\nv 1 0\nv 1 0\nl 1 2 3 1\n"),
        Err(CurveError::ZeroLengthEdge { index: 1 })
    );
}

#[test]
fn json_and_obj_round_trip() {
    // OBJ goes through std's correctly rounded parser: bit for bit. serde_json's default float
    // parser is best effort (its `float_roundtrip` feature is off), so JSON is within an ulp.
    let curve = noisy_closed_curve();
    let back = Curve::from_json(curve.to_json().as_bytes()).expect("valid");
    assert_eq!(back.closed, curve.closed);
    assert_eq!(back.points.len(), curve.points.len());
    for (a, b) in back.points.iter().zip(&curve.points) {
        for c in 0..2 {
            assert!((a[c] - b[c]).abs() <= 2.0 * f64::EPSILON * b[c].abs());
        }
    }
    assert_eq!(
        Curve::from_obj(curve.to_obj().as_bytes()),
        Ok(curve.clone())
    );
    let open = Curve::new(vec![[0.1, 0.2], [1.0 / 3.0, -4.0], [5.0, 6.5]], false).expect("valid");
    assert_eq!(
        Curve::from_json(open.to_json().as_bytes()),
        Ok(open.clone())
    );
    assert_eq!(Curve::from_obj(open.to_obj().as_bytes()), Ok(open.clone()));
    // A bare array is an open polyline; a missing "closed" means open.
    assert_eq!(
        Curve::from_json(b" [[0.1, 0.2], [0.3333333333333333, -4], [5, 6.5]]"),
        Ok(open.clone())
    );
    assert_eq!(
        Curve::from_json(b"{\"points\": [[0.1, 0.2], [0.3333333333333333, -4], [5, 6.5]]}"),
        Ok(open)
    );
}

#[test]
fn fixtures_parse() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/curves");
    let read = |name: &str| std::fs::read(dir.join(name)).expect("fixture exists");
    let square = Curve::from_obj(&read("square.obj")).expect("valid OBJ");
    assert!(square.closed);
    assert_eq!(square.points.len(), 4);
    assert_eq!(square.turning_number(), Some(1));
    let wave = Curve::from_json(&read("wave.json")).expect("valid JSON");
    assert!(!wave.closed);
    assert_eq!(wave.points.len(), 9);
    // Constant discrete curvature (π/2 at every corner, ℓ* = 1) lies in the constraint span:
    // the square is a fixed point of the discrete flow, like the circle.
    let before = square.points.clone();
    let mut f = flow(square, 0.5);
    let m = f.step();
    assert!(m.max_edge_length_distortion < 1e-12, "{m:?}");
    for (a, b) in f.points().iter().zip(&before) {
        assert!((a[0] - b[0]).hypot(a[1] - b[1]) < 1e-12);
    }
}
