//! `willow bench --creases`: issue 40's cost of keeping creases. On a generated CAD part (a
//! cylinder of radius 1 and height 2, both rims chamfered at 45°: four crease rings), the
//! crease detection (on the input and, since it has sharp chains, on its denoised surface)
//! and the median conformal step with its creases held, beside the same flow across them
//! (`feature_angle: none`), at the same τ, in one run. The goal: detection and holding add
//! at most 15% to a step.

use super::{fail, EXIT_FAILURE};
use std::process::ExitCode;
use std::time::Instant;
use willow::flow::creases::held_creases;
use willow::flow::{new_flow, FlowParams, Method};
use willow::mesh::creases::FeatureAngle;
use willow::mesh::generate::chamfered_cylinder;
use willow::mesh::{Mesh, Topology};

const TAU: f64 = 0.05;

/// The chamfered cylinder at about `segments`² / 2 vertices.
fn part(segments: usize) -> Mesh {
    let step = std::f64::consts::TAU / segments as f64;
    chamfered_cylinder(step, segments)
}

/// What one flow measured: setup and median step (ms), the creases it held, and where its
/// last step went.
struct Timed {
    setup: f64,
    step: f64,
    creases: usize,
    phases: Vec<(String, f64)>,
}

/// The flow's setup and median step, milliseconds.
fn time_flow(mesh: &Mesh, angle: FeatureAngle, steps: usize) -> Result<Timed, String> {
    let params = FlowParams {
        method: Method::Conformal,
        tau: TAU,
        feature_angle: angle,
        ..FlowParams::default()
    };
    let start = Instant::now();
    let mut flow = new_flow(mesh, &params).map_err(|e| e.to_string())?;
    let setup = start.elapsed().as_secs_f64() * 1e3;
    let mut times = Vec::with_capacity(steps);
    for _ in 0..steps {
        times.push(flow.step().map_err(|e| e.to_string())?.step_ms);
    }
    times.sort_by(f64::total_cmp);
    Ok(Timed {
        setup,
        step: times[times.len() / 2],
        creases: flow.creases().len(),
        phases: super::bench::profile_of(flow.as_ref()),
    })
}

pub fn run(steps: usize) -> ExitCode {
    let mesh = part(256);
    let steps = steps.max(1);
    let topology = Topology::new(&mesh);
    let start = Instant::now();
    let creases = held_creases(&mesh, &topology, FeatureAngle::Auto);
    let detect_ms = start.elapsed().as_secs_f64() * 1e3;
    let figures = time_flow(&mesh, FeatureAngle::Auto, steps)
        .and_then(|held| Ok((held, time_flow(&mesh, FeatureAngle::None, steps)?)));
    let (held, free) = match figures {
        Ok(f) => f,
        Err(e) => return fail(EXIT_FAILURE, format!("creases benchmark: {e}")),
    };
    println!(
        "creases: chamfered cylinder, {} vertices, {} triangles, {} crease edges ({} held), τ {TAU}, \
         median of {steps} steps",
        mesh.vertex_count(),
        mesh.face_count(),
        creases.edges.len(),
        held.creases
    );
    println!("  detection (input + denoised)  {detect_ms:>10.1} ms");
    println!("  setup, creases held           {:>10.1} ms", held.setup);
    println!("  setup, across them (none)     {:>10.1} ms", free.setup);
    println!("  step, creases held            {:>10.1} ms", held.step);
    println!("  step, across them (none)      {:>10.1} ms", free.step);
    println!(
        "  held / none: step {:.3}, setup incl. detection {:.3} (goal: step ≤ 1.15)",
        held.step / free.step,
        held.setup / free.setup
    );
    for (name, timed) in [("held", &held), ("none", &free)] {
        let phases: Vec<String> = timed
            .phases
            .iter()
            .map(|(n, v)| format!("{n} {v:.1}"))
            .collect();
        println!("    last step, {name}: {}", phases.join(", "));
    }
    ExitCode::SUCCESS
}
