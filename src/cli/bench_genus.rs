//! `willow bench --genus [MESH]`: issue 4's figure for surfaces of higher genus. The median
//! conformal step on a genus-g mesh with its exactness constraints (App. C: one extra
//! factorization of X at ρ = 0 per step and 2g solves), the same mesh without them, and a
//! generated genus-0 irregular sphere of about the same vertex count, all at the same τ in
//! one run; the ratio genus-g / genus-0 is the figure (goal ≤ 2).

use super::{fail, EXIT_BAD_INPUT, EXIT_FAILURE};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use willow::flow::{new_flow, FlowParams};
use willow::mesh::generate::irregular_sphere;
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::{Mesh, Topology};

/// botijo (genus 5, W/4π = 44) runs away from τ ≈ 0.025; every run here uses this τ.
const TAU: f64 = 0.0125;

/// Median per-step time of the conformal flow on `mesh` over `steps` steps.
fn median_step_ms(mesh: &Mesh, exactness: bool, steps: usize) -> Result<f64, String> {
    let params = FlowParams {
        tau: TAU,
        exactness,
        ..FlowParams::default()
    };
    let mut flow = new_flow(mesh, &params).map_err(|e| e.to_string())?;
    let mut times = Vec::with_capacity(steps);
    for _ in 0..steps {
        times.push(flow.step().map_err(|e| e.to_string())?.step_ms);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[times.len() / 2])
}

/// The genus-0 mesh to compare with: the irregular sphere whose vertex count (10·4ˢ + 2) is
/// nearest to `vertices`.
fn comparable_sphere(vertices: usize) -> Mesh {
    let s = (0..8)
        .min_by_key(|&s| (10 * 4usize.pow(s) + 2).abs_diff(vertices))
        .unwrap_or(0);
    irregular_sphere(s as usize, 7)
}

pub fn run(mesh: Option<&Path>, steps: usize) -> ExitCode {
    let path = mesh
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("../shared/meshes").join("botijo_genus5_irregular.obj"));
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) => return fail(EXIT_BAD_INPUT, format!("{}: {e}", path.display())),
    };
    let format = Format::from_path(&path).unwrap_or(Format::Obj);
    let asset = match Asset::read(&bytes, format, &Limits::default()) {
        Ok(a) => a,
        Err(e) => return fail(EXIT_BAD_INPUT, format!("{}: {e}", path.display())),
    };
    let surface = asset.surface();
    let genus: usize = Topology::new(surface)
        .components
        .iter()
        .map(|c| c.genus)
        .sum();
    let sphere = comparable_sphere(surface.vertex_count());
    let steps = steps.max(1);
    let figures = median_step_ms(surface, true, steps).and_then(|with| {
        let without = median_step_ms(surface, false, steps)?;
        let zero = median_step_ms(&sphere, true, steps)?;
        Ok((with, without, zero))
    });
    match figures {
        Ok((with, without, zero)) => {
            println!(
                "genus {genus} ({}, {} vertices), τ = {TAU}, median of {steps} steps:",
                path.display(),
                surface.vertex_count()
            );
            println!("  with exactness     {with:>10.1} ms");
            println!("  without exactness  {without:>10.1} ms");
            println!(
                "  genus 0 ({} vertices) {zero:>7.1} ms",
                sphere.vertex_count()
            );
            println!(
                "  ratio genus {genus} / genus 0: {:.2} (goal ≤ 2); exactness costs {:.2}×",
                with / zero,
                with / without
            );
            ExitCode::SUCCESS
        }
        Err(e) => fail(EXIT_FAILURE, format!("{}: {e}", path.display())),
    }
}
