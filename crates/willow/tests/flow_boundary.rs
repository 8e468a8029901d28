//! Surfaces with boundary (§6.2–§6.3): free boundaries and fixed boundaries, issue 4.

mod mesh_support;
use mesh_support::shared_surface;

use willow::flow::{new_flow, Boundary, Flow, FlowParams};
use willow::mesh::generate::{bumpy_cap, torus};
use willow::mesh::{Mesh, Topology};
use willow::metrics::StepMetrics;

fn params(tau: f64, boundary: Boundary) -> FlowParams {
    FlowParams {
        tau,
        boundary,
        ..FlowParams::default()
    }
}

fn run(flow: &mut dyn Flow, steps: usize) -> Vec<StepMetrics> {
    (0..steps).map(|_| flow.step().expect("step")).collect()
}

#[test]
fn a_disk_flows_with_its_boundary_free() {
    let mesh = bumpy_cap(4, 0.06);
    let topology = Topology::new(&mesh);
    assert_eq!(topology.boundary_loops.len(), 1, "the cap is a disk");
    let mut flow = new_flow(&mesh, &params(0.3, Boundary::Free)).expect("flow");
    let w0 = flow.initial_metrics().willmore_energy;
    let metrics = run(flow.as_mut(), 6);
    let last = metrics.last().expect("steps");
    eprintln!(
        "free cap: W {w0:.3} -> {:.3}, Q {:.4}, closure {:.2e}",
        last.willmore_energy, last.q_mean, last.closure_residual
    );
    assert!(metrics.iter().all(|m| m.willmore_energy.is_finite()));
    assert!(
        last.willmore_energy < w0,
        "W {w0} -> {}",
        last.willmore_energy
    );
    assert!(last.q_mean < 1.2, "mean Q {}", last.q_mean);
    // The free boundary moves.
    let moved = boundary_motion(&mesh, &topology, flow.positions());
    assert!(moved > 1e-3, "free boundary did not move: {moved}");
}

fn boundary_motion(mesh: &Mesh, topology: &Topology, positions: &[[f64; 3]]) -> f64 {
    topology
        .boundary_loops
        .iter()
        .flat_map(|l| l.vertices.iter())
        .map(|&v| {
            let (p, q) = (positions[v], mesh.positions[v]);
            (p[0] - q[0])
                .abs()
                .max((p[1] - q[1]).abs())
                .max((p[2] - q[2]).abs())
        })
        .fold(0.0, f64::max)
}

#[test]
fn a_fixed_boundary_does_not_move_and_the_interior_fairs() {
    let mesh = bumpy_cap(4, 0.06);
    let topology = Topology::new(&mesh);
    let mut flow = new_flow(&mesh, &params(0.3, Boundary::Fixed)).expect("flow");
    let w0 = flow.initial_metrics().willmore_energy;
    let metrics = run(flow.as_mut(), 5);
    let last = metrics.last().expect("steps");
    eprintln!(
        "fixed cap: W {w0:.3} -> {:.3}, Q {:.4}, closure {:.2e}, solve residual {:.2e}",
        last.willmore_energy, last.q_mean, last.closure_residual, last.eigen_residual
    );
    // Bit-exact: the Dirichlet rows return the prescribed values untouched.
    for l in &topology.boundary_loops {
        for &v in &l.vertices {
            assert_eq!(
                flow.positions()[v],
                mesh.positions[v],
                "boundary vertex {v} moved"
            );
        }
    }
    assert!(
        last.willmore_energy < w0,
        "W {w0} -> {}",
        last.willmore_energy
    );
    let interior_moved = flow
        .positions()
        .iter()
        .zip(&mesh.positions)
        .map(|(p, q)| (p[0] - q[0]).abs() + (p[1] - q[1]).abs() + (p[2] - q[2]).abs())
        .fold(0.0, f64::max);
    assert!(interior_moved > 1e-3, "the interior did not move");
    assert!(
        last.eigen_residual < 1e-8,
        "boundary-value solve residual {}",
        last.eigen_residual
    );
}

#[test]
fn an_annulus_flows_with_the_exactness_constraint() {
    // Half a torus is an annulus (two boundary loops, b1 = 1).
    let full = torus(2.0, 0.7, 48, 24);
    let mut mesh = full.clone();
    mesh.triangles
        .retain(|t| t.iter().all(|&v| full.positions[v][1] >= -1e-9));
    let mut used = vec![usize::MAX; mesh.positions.len()];
    let mut positions = Vec::new();
    for t in &mesh.triangles {
        for &v in t {
            if used[v] == usize::MAX {
                used[v] = positions.len();
                positions.push(full.positions[v]);
            }
        }
    }
    mesh.triangles = mesh
        .triangles
        .iter()
        .map(|t| [used[t[0]], used[t[1]], used[t[2]]])
        .collect();
    mesh.positions = positions;
    let topology = Topology::new(&mesh);
    assert_eq!(topology.boundary_loops.len(), 2);
    let mut flow = new_flow(&mesh, &params(0.3, Boundary::Free)).expect("flow");
    let w0 = flow.initial_metrics().willmore_energy;
    let metrics = run(flow.as_mut(), 5);
    let last = metrics.last().expect("steps");
    eprintln!(
        "annulus: W {w0:.3} -> {:.3}, Q {:.4}, closure {:.2e}",
        last.willmore_energy, last.q_mean, last.closure_residual
    );
    assert!(metrics.iter().all(|m| m.willmore_energy.is_finite()));
    assert!(
        last.willmore_energy < 0.5 * w0,
        "W {w0} -> {}",
        last.willmore_energy
    );
    // The safeguard no longer refuses a step for its closure residual as such (issue 26):
    // these steps are sound (W falls, nothing folds), and their residual grows to 0.18 at
    // step 5 (measured; 0.05 with the constraint off, which does not keep the loop's period
    // closed). Bounded, not small.
    assert!(
        metrics.iter().all(|m| m.closure_residual < 0.25),
        "closure {:?}",
        metrics
            .iter()
            .map(|m| m.closure_residual)
            .collect::<Vec<_>>()
    );
}

#[test]
fn real_disks_flow_free_and_fixed() {
    // Free boundaries here have no boundary condition for λ at all, which is not elliptic
    // (§6.3.1, after Bohle and Pinkall): on cat_head the free flow is smooth at τ = 0.05 but
    // oscillates and blows up from τ ≈ 0.3 once the disk is nearly flat. Until the N–B-plane
    // condition exists, free boundaries are tested at the small step they tolerate.
    for name in ["cat_head.obj", "alligator.obj"] {
        let mesh = shared_surface(name);
        for (boundary, tau) in [(Boundary::Free, 0.05), (Boundary::Fixed, 0.3)] {
            let mut flow = new_flow(&mesh, &params(tau, boundary.clone())).expect("flow");
            let w0 = flow.initial_metrics().willmore_energy;
            let metrics = run(flow.as_mut(), 4);
            let last = metrics.last().expect("steps");
            eprintln!(
                "{name} {boundary:?}: W {w0:.3} -> {:.3}, Q {:.4}, closure {:.2e}",
                last.willmore_energy, last.q_mean, last.closure_residual
            );
            assert!(metrics
                .iter()
                .all(|m| m.willmore_energy.is_finite() && m.q_mean.is_finite()));
            if w0 > 1e-9 {
                assert!(
                    last.willmore_energy < w0,
                    "{name} {boundary:?}: W {w0} -> {}",
                    last.willmore_energy
                );
            } else {
                // alligator is planar: W = 0 already, and a flat disk must stay flat.
                assert!(
                    last.willmore_energy < 1e-9,
                    "{name}: W {}",
                    last.willmore_energy
                );
            }
        }
    }
}
