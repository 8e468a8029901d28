//! The `willow` command-line contract: formats by extension, JSON lines, frames, exit codes.
//! One file a theme: `io` (formats, JSON lines, exit codes, repair), `bench`, `denoise` (the
//! default method on the shared noisy/clean pairs, scans, clean meshes), `options` (the
//! paper's options, boundaries, the safeguard, stopping rules), `regions` (regions, feature
//! size, groups and falloff). The shared meshes and JSON-line readers live here.

mod bench;
mod denoise;
mod io;
mod options;
mod regions;

use std::process::Command;

fn willow() -> Command {
    Command::new(env!("CARGO_BIN_EXE_willow"))
}

fn spot() -> String {
    concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/crates/willow/tests/data/spot_triangulated.obj"
    )
    .to_string()
}

/// An open tube (two boundary loops) as OBJ text.
fn tube_obj() -> String {
    let (m, rings) = (16, 6);
    let mut s = String::new();
    for j in 0..=rings {
        for i in 0..m {
            let t = 2.0 * std::f64::consts::PI * i as f64 / m as f64;
            s += &format!("v {} {} {}\n", t.cos(), t.sin(), j as f64 / 3.0);
        }
    }
    for j in 0..rings {
        for i in 0..m {
            let a = j * m + i + 1;
            let b = j * m + (i + 1) % m + 1;
            let (c, d) = (b + m, a + m);
            s += &format!("f {a} {b} {c}\nf {a} {c} {d}\n");
        }
    }
    s
}

/// `generate::bumpy_sphere(2, 0.4)` (162 vertices) as OBJ text: an easy mesh for the conformal
/// flow at τ = 0.5, and one where implicit MCF at τ = 1000 can make no acceptable step 3.
fn bumpy_obj() -> String {
    let mesh = willow::mesh::generate::bumpy_sphere(2, 0.4);
    let mut s = String::new();
    for p in &mesh.positions {
        s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    for t in &mesh.triangles {
        s += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

/// The per-step JSON lines of a `fair --json` run (every line but the outcome line).
fn json_lines(out: &std::process::Output) -> Vec<serde_json::Value> {
    let mut lines = all_json_lines(out);
    let last = lines.pop().unwrap_or_default();
    assert!(
        last["outcome"].is_string(),
        "the last line is the outcome: {last}"
    );
    assert!(lines.iter().all(|l| l["step"].is_u64()));
    lines
}

fn all_json_lines(out: &std::process::Output) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("each line is JSON"))
        .collect()
}

/// The outcome line of a `fair --json` run.
fn outcome(out: &std::process::Output) -> serde_json::Value {
    all_json_lines(out).pop().unwrap_or_default()
}
