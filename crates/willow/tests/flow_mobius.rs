//! Paper §6.2 and Figure 13 / Appendix E.1: Möbius balancing moves the flow's area
//! distribution toward the input's (issue 4).

use willow::flow::mobius::{area_distortion, log_area_spread};
use willow::flow::{new_flow, FlowParams};
use willow::geometry::barycentric_vertex_areas;
use willow::mesh::generate::icosphere;
use willow::mesh::Mesh;

/// An asymmetric dumbbell (genus 0): a big lobe and a smaller one (radii 1 and 0.6 at the
/// ends) joined by a neck. Rounding it off compresses the small lobe much more than the big
/// one, an area imbalance with a large dipole part, which is what an inversion can undo.
fn dumbbell(subdivisions: usize) -> Mesh {
    let mut mesh = icosphere(subdivisions);
    for p in &mut mesh.positions {
        let z = p[2];
        let neck = 1.0 - 0.4 * (-((z - 0.25) / 0.22).powi(2)).exp();
        let taper = 1.0 - 0.4 * (1.0 + z) / 2.0;
        *p = [p[0] * neck * taper, p[1] * neck * taper, 1.6 * z];
    }
    mesh
}

/// `|Σ A_i (f_i − c) u⁰_i| / Σ A_i`: the vector `v` of App. E.1 step III (per unit area), the
/// part of the log-area distortion `u⁰` an inversion can change; balancing drives it to 0.
fn dipole(positions: &[[f64; 3]], areas: &[f64], input_areas: &[f64]) -> f64 {
    let total: f64 = areas.iter().sum();
    let u: Vec<f64> = areas
        .iter()
        .zip(input_areas)
        .map(|(a, t)| 0.5 * (a / t).ln())
        .collect();
    let mean = u.iter().zip(areas).map(|(u, a)| u * a).sum::<f64>() / total;
    let mut c = [0.0; 3];
    for (p, a) in positions.iter().zip(areas) {
        for k in 0..3 {
            c[k] += a * p[k] / total;
        }
    }
    let mut v = [0.0; 3];
    for ((p, a), u) in positions.iter().zip(areas).zip(&u) {
        for k in 0..3 {
            v[k] += a * (p[k] - c[k]) * (u - mean);
        }
    }
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() / total
}

struct Outcome {
    ratio: f64,
    spread: f64,
    dipole: f64,
    energy: Vec<f64>,
    q_mean: f64,
}

fn run(mesh: &Mesh, balancing: bool, steps: usize) -> Outcome {
    let params = FlowParams {
        tau: 0.5,
        mobius_balancing: balancing,
        ..FlowParams::default()
    };
    let input_areas = barycentric_vertex_areas(mesh);
    let mut flow = new_flow(mesh, &params).expect("flow");
    let mut energy = vec![flow.initial_metrics().willmore_energy];
    let mut q_mean = 1.0;
    for _ in 0..steps {
        let m = flow.step().expect("step");
        energy.push(m.willmore_energy);
        q_mean = m.q_mean;
    }
    let now = Mesh {
        positions: flow.positions().to_vec(),
        triangles: mesh.triangles.clone(),
    };
    let areas = barycentric_vertex_areas(&now);
    Outcome {
        ratio: area_distortion(&areas, &input_areas),
        spread: log_area_spread(&areas, &input_areas),
        dipole: dipole(&now.positions, &areas, &input_areas),
        energy,
        q_mean,
    }
}

/// Figure 13: with the inversion constraint alone the flow keeps whatever Möbius normal form
/// it drifts into; balancing flows toward the input's area distribution. Asymmetric dumbbell
/// (642 vertices), 8 steps at τ = 0.5. Measured: largest over smallest `A_i / A*_i` 229.5
/// without balancing, 127.9 with (−44%); App. E.1's `v` (per unit area) 5.7e-2 without, 6.8e-3
/// with (it shrinks ~25% a step once W has settled); W 21.91 → 12.51 and 12.52, mean Q 1.114
/// and 1.112. The area-weighted L² spread of
/// `u⁰` is *not* lower (0.216 without, 0.220 with): App. E.1 weights `v = Σ V_i f_i u⁰_i` by
/// the current areas, so its fixed point `v = 0` is not the minimum of that spread (moving
/// area into the compressed lobe also raises the lobe's weight). It is the max/min ratio and
/// the dipole that Figure 13 shows improving. The same shape at 2562 vertices gives 153 and
/// 140: the extreme ratio is a mesh-sensitive statistic, the dipole is not.
#[test]
fn balancing_lowers_the_area_ratio_of_an_asymmetric_dumbbell() {
    let mesh = dumbbell(3);
    let steps = 8;
    let without = run(&mesh, false, steps);
    let with = run(&mesh, true, steps);
    for (name, o) in [("without", &without), ("with", &with)] {
        eprintln!(
            "{name} balancing: max/min area ratio {:.1}, log spread {:.3}, dipole {:.2e}, W {:.2} → {:.2}, mean Q {:.3}",
            o.ratio,
            o.spread,
            o.dipole,
            o.energy[0],
            o.energy[steps],
            o.q_mean
        );
        for pair in o.energy.windows(2) {
            assert!(
                pair[1] <= pair[0] * (1.0 + 1e-6),
                "{name} balancing: W rose, {:?}",
                o.energy
            );
        }
        assert!(o.q_mean < 1.15, "{name} balancing: mean Q {}", o.q_mean);
    }
    assert!(
        with.ratio < 0.7 * without.ratio,
        "max/min area ratio with balancing {} vs without {}",
        with.ratio,
        without.ratio
    );
    assert!(
        with.dipole < 0.25 * without.dipole,
        "dipole with balancing {} vs without {}",
        with.dipole,
        without.dipole
    );
    // Balancing is a Möbius motion, which costs no Willmore energy: both runs reach the same W.
    let (a, b) = (with.energy[steps], without.energy[steps]);
    assert!((a - b).abs() < 0.01 * b, "W with {a} vs without {b}");
}
