//! `willow curve INPUT -o OUTPUT [--steps N] [--tau T] [--json]`: isometric curvature flow of a
//! planar polyline (paper §5). Formats by extension: `.json` (`{"points": [[x, y], ...],
//! "closed": bool}` or a bare point array, which is open) and `.obj` (`v` lines and one `l`
//! line; repeating the first index closes the curve).

use super::{fail, read_input, EXIT_BAD_INPUT, EXIT_FAILURE};
use clap::Args;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use willow::curve::{Curve, CurveFlow, CurveParams};

#[derive(Args, Debug)]
pub struct CurveArgs {
    /// Input curve: .json, `{"points": [[x, y], ...], "closed": true}` (or a bare array of
    /// points: open), or .obj, `v` lines and one `l` line (repeating the first index closes
    /// it).
    pub input: PathBuf,
    /// Output curve; its extension picks the format (.json or .obj).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Number of flow steps.
    #[arg(long, default_value_t = 8)]
    pub steps: usize,
    /// Time step with the paper's meaning (§4): unconstrained curvature becomes (1 − 2τ)κ each
    /// step, stable for 0 < τ < 1; 0.5 removes it in one step.
    #[arg(long, default_value_t = CurveParams::default().tau)]
    pub tau: f64,
    /// One JSON object per step on stdout (the step's metrics).
    #[arg(long)]
    pub json: bool,
}

/// The two curve formats, picked by extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum CurveFormat {
    Json,
    Obj,
}

fn format_of(path: &Path, role: &str) -> Result<CurveFormat, String> {
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    match extension.as_deref() {
        Some("json") => Ok(CurveFormat::Json),
        Some("obj") => Ok(CurveFormat::Obj),
        _ => Err(format!(
            "{role} {}: unknown extension (expected .json or .obj)",
            path.display()
        )),
    }
}

pub fn run(args: CurveArgs) -> ExitCode {
    let input_format = match format_of(&args.input, "input") {
        Ok(f) => f,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    let output_format = match format_of(&args.output, "output") {
        Ok(f) => f,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    let bytes = match read_input(&args.input) {
        Ok(b) => b,
        Err(code) => return code,
    };
    let parsed = match input_format {
        CurveFormat::Json => Curve::from_json(&bytes),
        CurveFormat::Obj => Curve::from_obj(&bytes),
    };
    let curve = match parsed {
        Ok(c) => c,
        Err(e) => return fail(EXIT_BAD_INPUT, format!("{}: {e}", args.input.display())),
    };
    let mut flow = match CurveFlow::new(curve, CurveParams { tau: args.tau }) {
        Ok(f) => f,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    let stdout = std::io::stdout();
    for _ in 0..args.steps {
        let metrics = flow.step();
        if flow
            .points()
            .iter()
            .any(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            return fail(
                EXIT_FAILURE,
                format!(
                    "curve flow produced non-finite points at step {}",
                    metrics.step
                ),
            );
        }
        if args.json {
            let line = match serde_json::to_string(&metrics) {
                Ok(l) => l,
                Err(e) => return fail(EXIT_FAILURE, e),
            };
            let mut out = stdout.lock();
            if writeln!(out, "{line}").and_then(|_| out.flush()).is_err() {
                // stdout closed (e.g. piped into `head`): stop quietly, like `willow fair`.
                return ExitCode::from(EXIT_FAILURE);
            }
        }
    }
    let text = match output_format {
        CurveFormat::Json => flow.curve().to_json(),
        CurveFormat::Obj => flow.curve().to_obj(),
    };
    match std::fs::write(&args.output, text) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => fail(
            EXIT_FAILURE,
            format!("cannot write {}: {e}", args.output.display()),
        ),
    }
}
