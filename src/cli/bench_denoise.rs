//! `willow bench --denoise DIR`: issue 39's figure. For every `<Name>_Noisy.obj` with its
//! `<Name>_Original.obj` in DIR (the field's noisy/clean pairs, same connectivity), the noisy
//! input's θ and Dv, Willow's defaults (a job with no parameters: method `denoise`) and Taubin
//! smoothing (10 iterations, λ 0.5, μ −0.53: MeshLab's default) measured in the same run, each
//! with its time end to end (reading the file included), and the ratios Willow / Taubin.
//! θ: the mean angle between corresponding face normals of a result and the clean mesh,
//! degrees; Dv: the mean distance from the result's vertices to the clean surface, ‰ of its
//! bounding-box diagonal. Figures, not pass/fail (the tests assert the pass/fail side).

use super::{fail, EXIT_BAD_INPUT, EXIT_FAILURE};
use std::path::Path;
use std::process::ExitCode;
use std::time::Instant;
use willow::denoise::score::{score, Score};
use willow::flow::classic::TaubinSmoothing;
use willow::flow::new_flow;
use willow::flow::stopping::{Event, Run};
use willow::mesh::io::{Asset, Format, Limits};
use willow_service::jobs::JobSpec;

struct Row {
    name: String,
    vertices: usize,
    noisy: Score,
    willow: Score,
    willow_ms: f64,
    outcome: String,
    taubin: Score,
    taubin_ms: f64,
}

fn read(path: &Path) -> Result<Asset, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Asset::read(&bytes, Format::Obj, &Limits::default())
        .map_err(|e| format!("{}: {e}", path.display()))
}

fn measure(noisy_path: &Path, clean_path: &Path, name: String) -> Result<Row, String> {
    let clean = read(clean_path)?;
    let start = Instant::now();
    let noisy = read(noisy_path)?;
    let (mesh, reference) = (noisy.surface(), clean.surface());
    if mesh.triangles != reference.triangles {
        return Err(format!(
            "{name}: the noisy and clean meshes do not share their connectivity"
        ));
    }
    let spec = JobSpec::default();
    let params = spec.flow_params();
    let flow = new_flow(mesh, &params).map_err(|e| format!("{name}: {e}"))?;
    let mut run = Run::new(flow, &params, spec.steps).map_err(|e| format!("{name}: {e}"))?;
    let outcome = loop {
        match run.advance().map_err(|e| format!("{name}: {e}"))? {
            Event::Step(_) => {}
            Event::Stopped { outcome, .. } => break outcome,
        }
    };
    let willow_ms = start.elapsed().as_secs_f64() * 1e3;
    let willow = score(
        run.flow().positions(),
        &reference.positions,
        &reference.triangles,
    );

    let start = Instant::now();
    let noisy_again = read(noisy_path)?;
    let taubin = TaubinSmoothing::meshlab_default(noisy_again.surface())
        .map_err(|e| format!("{name}: {e}"))?;
    let taubin_ms = start.elapsed().as_secs_f64() * 1e3;
    Ok(Row {
        vertices: mesh.vertex_count(),
        noisy: score(&mesh.positions, &reference.positions, &reference.triangles),
        willow,
        willow_ms,
        outcome: outcome.name().to_string(),
        taubin: score(&taubin, &reference.positions, &reference.triangles),
        taubin_ms,
        name,
    })
}

/// The pairs in `dir`, by name.
fn pairs(dir: &Path) -> Result<Vec<(String, std::path::PathBuf, std::path::PathBuf)>, String> {
    let entries = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut found: Vec<_> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let file = e.file_name().to_string_lossy().to_string();
            let name = file.strip_suffix("_Noisy.obj")?.to_string();
            let clean = dir.join(format!("{name}_Original.obj"));
            clean.exists().then(|| (name, e.path(), clean))
        })
        .collect();
    found.sort();
    if found.is_empty() {
        return Err(format!(
            "{}: no <Name>_Noisy.obj with its <Name>_Original.obj",
            dir.display()
        ));
    }
    Ok(found)
}

pub fn run(dir: &Path) -> ExitCode {
    let found = match pairs(dir) {
        Ok(f) => f,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    println!(
        "{:<12} {:>7} | {:>14} | {:>14} {:>8} {:>16} | {:>14} {:>8} | {:>13}",
        "pair",
        "V",
        "noisy θ° / Dv‰",
        "Willow θ / Dv",
        "ms",
        "outcome",
        "Taubin θ / Dv",
        "ms",
        "Willow/Taubin"
    );
    for (name, noisy, clean) in found {
        let row = match measure(&noisy, &clean, name) {
            Ok(r) => r,
            Err(e) => return fail(EXIT_FAILURE, e),
        };
        println!(
            "{:<12} {:>7} | {:>6.2} / {:>5.2} | {:>6.2} / {:>5.2} {:>8.0} {:>16} | {:>6.2} / {:>5.2} {:>8.0} | {:>5.2} / {:>5.2}",
            row.name,
            row.vertices,
            row.noisy.theta,
            row.noisy.distance,
            row.willow.theta,
            row.willow.distance,
            row.willow_ms,
            row.outcome,
            row.taubin.theta,
            row.taubin.distance,
            row.taubin_ms,
            row.willow.theta / row.taubin.theta,
            row.willow.distance / row.taubin.distance
        );
    }
    ExitCode::SUCCESS
}
