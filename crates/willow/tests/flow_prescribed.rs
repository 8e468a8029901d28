//! Prescribed boundary vectors and CMC surfaces (§6.3.1, Figure 14), issue 4.

mod mesh_support;
use mesh_support::shared_surface;

use std::f64::consts::PI;
use willow::flow::prescribed::{boundary_frame, frame_vector, BoundaryVertices};
use willow::flow::{
    new_flow, Boundary, BoundaryAngles, FlowError, FlowParams, PrescribedVectors, RotationAxis,
};
use willow::geometry::cache::GeometryCache;
use willow::geometry::vec3::{cross, dot, norm};
use willow::mesh::{Mesh, Topology};

fn params(tau: f64, boundary: Boundary) -> FlowParams {
    FlowParams {
        tau,
        boundary,
        ..FlowParams::default()
    }
}

/// An open cylinder of radius 1 around the z axis, `rings + 1` rings of `m` vertices from
/// z = −h to z = h, outward normals.
fn cylinder(m: usize, rings: usize, h: f64) -> Mesh {
    let mut positions = Vec::new();
    for j in 0..=rings {
        let z = -h + 2.0 * h * j as f64 / rings as f64;
        for i in 0..m {
            let t = 2.0 * PI * (i as f64 + 0.5 * (j % 2) as f64) / m as f64;
            positions.push([t.cos(), t.sin(), z]);
        }
    }
    let mut triangles = Vec::new();
    for j in 0..rings {
        for i in 0..m {
            let a = j * m + i;
            let b = j * m + (i + 1) % m;
            let c = (j + 1) * m + (i + 1) % m;
            let d = (j + 1) * m + i;
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    Mesh::new(positions, triangles).expect("valid cylinder")
}

/// A unit hemisphere z ≥ 0 (boundary on the equator) in latitude rings, with a radial bump
/// `1 + amplitude·sin(3θ)·cos(5φ)`-style perturbation, outward normals.
fn bumpy_hemisphere(m: usize, rings: usize, amplitude: f64) -> Mesh {
    let radius = |theta: f64, phi: f64| 1.0 + amplitude * (3.0 * phi).sin() * (5.0 * theta).cos();
    let mut positions = Vec::new();
    // Ring j at polar angle θ_j = (π/2)(1 − j/rings), j = 0 on the equator.
    for j in 0..rings {
        let theta = 0.5 * PI * (1.0 - j as f64 / rings as f64);
        for i in 0..m {
            let phi = 2.0 * PI * (i as f64 + 0.5 * (j % 2) as f64) / m as f64;
            let r = if j == 0 { 1.0 } else { radius(theta, phi) };
            positions.push([
                r * theta.sin() * phi.cos(),
                r * theta.sin() * phi.sin(),
                r * theta.cos(),
            ]);
        }
    }
    let pole = positions.len();
    positions.push([0.0, 0.0, 1.0]);
    let mut triangles = Vec::new();
    for j in 0..rings - 1 {
        for i in 0..m {
            let a = j * m + i;
            let b = j * m + (i + 1) % m;
            let c = (j + 1) * m + (i + 1) % m;
            let d = (j + 1) * m + i;
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    let top = (rings - 1) * m;
    for i in 0..m {
        triangles.push([top + i, top + (i + 1) % m, pole]);
    }
    Mesh::new(positions, triangles).expect("valid hemisphere")
}

/// Area-weighted std(H)/mean(H) over interior vertices (the cotan H at a boundary vertex
/// measures the boundary curve, not the surface).
fn mean_curvature_spread(positions: &[[f64; 3]], mesh: &Mesh, boundary: &[bool]) -> f64 {
    let g = GeometryCache::new(positions, &mesh.triangles);
    let (mut s0, mut s1, mut s2) = (0.0, 0.0, 0.0);
    for ((&h, &a), &b) in g.mean_curvature.iter().zip(&g.vertex_areas).zip(boundary) {
        if !b {
            s0 += a;
            s1 += a * h;
            s2 += a * h * h;
        }
    }
    let mean = s1 / s0;
    ((s2 / s0 - mean * mean).max(0.0)).sqrt() / mean.abs()
}

/// Largest angle (radians) between the flowed surface's `V` and the targets `Ṽ` computed on
/// the input the same way the flow does.
fn boundary_vector_error(
    mesh: &Mesh,
    positions: &[[f64; 3]],
    spec: &PrescribedVectors,
    targets: &[[f64; 3]],
) -> f64 {
    let topology = Topology::new(mesh);
    let boundary = BoundaryVertices::new(&topology, mesh.vertex_count());
    let g = GeometryCache::new(positions, &mesh.triangles);
    boundary
        .triples
        .iter()
        .zip(targets)
        .map(|(&[p, v, n], t)| {
            let frame = boundary_frame(positions, &g.normals, p, v, n).expect("frame");
            let now = frame_vector(&frame, spec.frame_angle);
            (dot(now, *t) / (norm(now) * norm(*t)))
                .clamp(-1.0, 1.0)
                .acos()
        })
        .fold(0.0, f64::max)
}

/// `Ṽ` per boundary vertex of `mesh` for `spec`, through the library's own function.
fn targets(mesh: &Mesh, spec: &PrescribedVectors) -> Vec<[f64; 3]> {
    let topology = Topology::new(mesh);
    let boundary = BoundaryVertices::new(&topology, mesh.vertex_count());
    let g = GeometryCache::new(&mesh.positions, &mesh.triangles);
    willow::flow::prescribed::boundary_targets(
        spec,
        &boundary,
        topology.boundary_loops.len(),
        &mesh.positions,
        &g.normals,
    )
    .expect("targets")
}

#[test]
fn cmc_boundary_fairs_a_bumpy_hemisphere_to_constant_mean_curvature() {
    let mesh = bumpy_hemisphere(48, 16, 0.08);
    let boundary = Topology::new(&mesh).boundary_vertex_mask(mesh.vertex_count());
    let spread0 = mean_curvature_spread(&mesh.positions, &mesh, &boundary);
    let mut flow = new_flow(&mesh, &params(0.5, Boundary::Cmc)).expect("flow");
    let w0 = flow.initial_metrics().willmore_energy;
    // 40 steps: the safeguard takes some early steps below τ = 0.5, so 30 steps cover less
    // flow time than they did unguarded (spread 0.052 after 30).
    for _ in 0..40 {
        let m = flow.step().expect("step");
        eprintln!(
            "step {}: W {:.4} Q {:.4} closure {:.2e} eig {:.2e} spread {:.4}",
            m.step,
            m.willmore_energy,
            m.q_mean,
            m.closure_residual,
            m.eigen_residual,
            mean_curvature_spread(flow.positions(), &mesh, &boundary)
        );
    }
    let spread = mean_curvature_spread(flow.positions(), &mesh, &boundary);
    let spec = PrescribedVectors::default();
    let err = boundary_vector_error(&mesh, flow.positions(), &spec, &targets(&mesh, &spec));
    eprintln!("W0 {w0:.4}, spread {spread0:.4} -> {spread:.4}, boundary B error {err:.4} rad");
    assert!(spread < 0.05, "std(H)/mean(H) {spread0} -> {spread}");
    assert!(err < 0.01, "boundary binormal off by {err} rad");
}

#[test]
fn rotated_binormals_bend_a_cylinder() {
    let mesh = cylinder(40, 20, 1.0);
    let topology = Topology::new(&mesh);
    assert_eq!(topology.boundary_loops.len(), 2);
    // Tilt one end's binormals by 0.3 rad about the x axis, keep the other.
    let top = if mesh.positions[topology.boundary_loops[0].vertices[0]][2] > 0.0 {
        0
    } else {
        1
    };
    let mut angles = vec![0.0; 2];
    angles[top] = 0.3;
    let spec = PrescribedVectors {
        frame_angle: 0.0,
        axis: RotationAxis::Fixed([1.0, 0.0, 0.0]),
        angles: BoundaryAngles::PerLoop(angles),
    };
    let goal = targets(&mesh, &spec);
    let mut flow = new_flow(&mesh, &params(0.5, Boundary::Prescribed(spec.clone()))).expect("flow");
    for _ in 0..8 {
        let m = flow.step().expect("step");
        eprintln!(
            "step {}: W {:.4} Q {:.4} closure {:.2e} eig {:.2e} err {:.4}",
            m.step,
            m.willmore_energy,
            m.q_mean,
            m.closure_residual,
            m.eigen_residual,
            boundary_vector_error(&mesh, flow.positions(), &spec, &goal)
        );
    }
    let err = boundary_vector_error(&mesh, flow.positions(), &spec, &goal);
    // The bend: the top ring's plane turns by the prescribed angle about x, the bottom's not.
    let tilt = |l: usize| {
        let n = loop_normal(flow.positions(), &topology.boundary_loops[l].vertices);
        (n[2].abs() / norm(n)).acos()
    };
    let (top_tilt, bottom_tilt) = (tilt(top), tilt(1 - top));
    eprintln!("err {err:.4} rad, ring tilts: top {top_tilt:.4}, bottom {bottom_tilt:.4}");
    assert!(err < 0.01, "boundary binormals off by {err} rad");
    assert!(
        (top_tilt - 0.3).abs() < 0.02,
        "top ring tilted {top_tilt} rad, not 0.3"
    );
    assert!(bottom_tilt < 0.02, "bottom ring tilted {bottom_tilt} rad");
}

/// The area vector `½ Σ p_i × p_{i+1}` of a closed polygon: normal to its best plane.
fn loop_normal(p: &[[f64; 3]], ring: &[usize]) -> [f64; 3] {
    let mut n = [0.0; 3];
    for (i, &a) in ring.iter().enumerate() {
        let b = ring[(i + 1) % ring.len()];
        let c = cross(p[a], p[b]);
        n = [n[0] + c[0], n[1] + c[1], n[2] + c[2]];
    }
    n
}

#[test]
fn bad_prescriptions_are_refused_with_the_reason() {
    let mesh = cylinder(12, 4, 1.0);
    let cases = [
        (
            PrescribedVectors {
                frame_angle: 1.6,
                ..Default::default()
            },
            "frame_angle",
        ),
        (
            PrescribedVectors {
                axis: RotationAxis::Fixed([0.0, 0.0, 0.0]),
                ..Default::default()
            },
            "axis",
        ),
        (
            PrescribedVectors {
                angles: BoundaryAngles::PerLoop(vec![0.1]),
                ..Default::default()
            },
            "1 per-loop angles given for a mesh with 2 boundary loops",
        ),
        (
            PrescribedVectors {
                angles: BoundaryAngles::PerVertex(vec![(10_000, 0.1)]),
                ..Default::default()
            },
            "vertex 10000 is not a boundary vertex",
        ),
        (
            PrescribedVectors {
                angles: BoundaryAngles::Uniform(f64::NAN),
                ..Default::default()
            },
            "finite",
        ),
    ];
    for (spec, needle) in cases {
        match new_flow(&mesh, &params(0.5, Boundary::Prescribed(spec))) {
            Err(FlowError::InvalidParameter { name, reason }) => {
                assert_eq!(name, "boundary");
                assert!(reason.contains(needle), "{reason:?} lacks {needle:?}");
            }
            Err(other) => panic!("wrong error {other:?}"),
            Ok(_) => panic!("accepted a bad prescription ({needle})"),
        }
    }
}

/// Figure 14, bottom: binormals that oscillate around the equator of a round hemisphere,
/// `Ṽ = B` turned about `T` by `0.5·sin 3φ`, give a CMC surface with those binormals.
#[test]
fn oscillating_binormals_on_a_hemisphere_give_a_cmc_surface() {
    let mesh = bumpy_hemisphere(48, 16, 0.0);
    let topology = Topology::new(&mesh);
    let boundary = BoundaryVertices::new(&topology, mesh.vertex_count());
    let per_vertex = boundary
        .triples
        .iter()
        .map(|&[_, v, _]| {
            let p = mesh.positions[v];
            (v, 0.5 * (3.0 * p[1].atan2(p[0])).sin())
        })
        .collect();
    let spec = PrescribedVectors {
        frame_angle: 0.0,
        axis: RotationAxis::Tangent,
        angles: BoundaryAngles::PerVertex(per_vertex),
    };
    let goal = targets(&mesh, &spec);
    let mask = topology.boundary_vertex_mask(mesh.vertex_count());
    let mut flow = new_flow(&mesh, &params(0.5, Boundary::Prescribed(spec.clone()))).expect("flow");
    let round = mean_curvature_spread(&mesh.positions, &mesh, &mask);
    let mut spreads = Vec::new();
    for _ in 0..20 {
        let m = flow.step().expect("step");
        assert!(m.willmore_energy.is_finite() && m.q_mean.is_finite());
        spreads.push(mean_curvature_spread(flow.positions(), &mesh, &mask));
    }
    let err = boundary_vector_error(&mesh, flow.positions(), &spec, &goal);
    eprintln!("spread {round:.4} then per step {spreads:.4?}, boundary error {err:.4} rad");
    // The first step turns the boundary and bends the surface away from constant H; the flow
    // then removes the non-constant part.
    let worst = spreads.iter().cloned().fold(0.0, f64::max);
    let last = spreads[spreads.len() - 1];
    assert!(
        worst > 2.0 * round,
        "the prescription should bend the surface first: {round} -> {worst}"
    );
    assert!(
        last < 0.05 && last < 0.5 * worst,
        "std(H)/mean(H) {worst} -> {last}"
    );
    assert!(err < 0.01, "boundary binormals off by {err} rad");
}

/// `V` off the binormal (φ = 0.6 toward N) turned about the tangent: elliptic but not
/// self-adjoint (§6.3.1); the boundary still takes the prescribed vectors and the flow is
/// stable at the paper's step size.
#[test]
fn a_tilted_frame_vector_is_prescribed_too() {
    let mesh = cylinder(40, 20, 1.0);
    let spec = PrescribedVectors {
        frame_angle: 0.6,
        axis: RotationAxis::Tangent,
        angles: BoundaryAngles::Uniform(0.2),
    };
    let goal = targets(&mesh, &spec);
    let mut flow = new_flow(&mesh, &params(0.5, Boundary::Prescribed(spec.clone()))).expect("flow");
    for _ in 0..8 {
        let m = flow.step().expect("step");
        assert!(m.willmore_energy.is_finite() && m.q_mean < 2.0, "{m:?}");
    }
    let err = boundary_vector_error(&mesh, flow.positions(), &spec, &goal);
    eprintln!("tilted frame: boundary error {err:.4} rad");
    assert!(err < 0.01, "boundary vectors off by {err} rad");
}

/// The real disks of issue 4 with `V = B`: the boundary problem is elliptic, so the paper's
/// τ = 0.5 is stable where the free boundary needs τ ≈ 0.05 (tests/flow_boundary.rs).
#[test]
fn real_disks_flow_with_the_cmc_boundary_at_the_papers_step() {
    for name in ["cat_head.obj", "alligator.obj"] {
        let mesh = shared_surface(name);
        let mut flow = new_flow(&mesh, &params(0.5, Boundary::Cmc)).expect("flow");
        let w0 = flow.initial_metrics().willmore_energy;
        let mut w = Vec::new();
        for _ in 0..6 {
            let m = flow.step().expect("step");
            assert!(
                m.willmore_energy.is_finite() && m.q_mean.is_finite(),
                "{name}: {m:?}"
            );
            w.push(m.willmore_energy);
        }
        eprintln!("{name}: W {w0:.3} -> {w:.3?}");
        let last = w[w.len() - 1];
        if w0 > 1e-9 {
            assert!(last < 0.8 * w0, "{name}: W {w0} -> {last}");
        } else {
            // alligator is flat: a plane is already CMC (H = 0) and must stay one.
            assert!(last < 1e-9, "{name}: a flat disk left its plane, W {last}");
        }
    }
}
