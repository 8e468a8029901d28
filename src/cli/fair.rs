//! `willow fair INPUT -o OUTPUT [--steps N] [--tau T] [--iterations K] [--method M]
//! [--frames-dir DIR] [--json] [--no-safeguard] [--preserve area|volume|none]
//! [--max-deviation D] [--measure-deviation] [--until-willmore W] [--all-steps]
//! [--feature-size L] [--falloff F] [--feature-angle auto|none|A]
//! [--region-sphere X,Y,Z,R] [--region-box ..] [--region-vertices FILE] [--region-group NAME]
//! [--seam fixed|smooth]`: the contract other tools rely on.
//!
//! The run stops as `willow::flow::stopping` decides: after `--steps`, or earlier when W
//! stops falling (unless `--all-steps`), reaches `--until-willmore`, the detail below
//! `--feature-size` is gone, or the next step would pass `--max-deviation`.
//! With `--json`, stdout has one JSON object per step, then one last line
//! `{"outcome": "...", "reason": "..."}` (outcomes: `completed`, `converged`,
//! `target_reached`, `max_deviation`, `no_progress`, `feature_scale_reached`, `stalled` (only tiny steps were sound:
//! the result is the last sound surface), `already_fair` (the mesh is too coarse to fair)).
//!
//! Exit codes: 0 done (any outcome but `no_progress`); 2 input refused; 1 failure while
//! running (the output holds the last sound surface, and stderr names its step); 3 the safeguard found no acceptable step
//! (`FlowError::NoProgress`): the output holds the last accepted surface and stderr says why
//! the flow stopped.

use super::{fail, read_input, EXIT_BAD_INPUT, EXIT_FAILURE, EXIT_NO_PROGRESS};
use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use willow::flow::holes::fill_asset_holes;
use willow::flow::region::{resolve_groups, Region, Seam};
use willow::flow::stopping::{Event, Outcome, Run};
use willow::flow::{new_flow, FlowError, FlowParams, Method, Preserve};
use willow::mesh::creases::FeatureAngle;
use willow::mesh::holes::HoleSize;
use willow::mesh::io::{Asset, Format, Limits};
use willow_service::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, FilterSpec, PrescribedSpec};
use willow_service::jobs::JobSpec;

/// The part of `willow fair --help` that is no one flag's: what it prints, how a run ends,
/// the exit codes. (The README points here: the CLI's flags are documented in this file only.)
const FAIR_AFTER_HELP: &str = "\
Output:
  On a terminal, a progress bar: W in both forms, Q mean and p95, the spread of log area
  ratios against the input and the collapsed triangles, the distance from the input, the τ
  used and the rejected tries.
  With --json, one JSON object per step on stdout with step, willmore_energy, q_mean,
  q_area_mean, q_p95, q_max, closure_residual, eigen_residual, area, step_ms, tau, rejected,
  volume, deviation_max, deviation_mean, willmore_energy_vector (Σ|Lf|²/4A, the |Δf| form;
  willmore_energy is the signed, normal-projected one), log_area_ratio_p1, log_area_ratio_p99,
  collapsed_triangles (scale distortion against the input), crease_edges (the creases held or
  found, with --feature-angle), then a last line
  {\"outcome\": ..., \"reason\": ...}.
  Input and output formats may differ; a PLY or OFF keeps its vertex numbering in every output
  format. A file with bowties or degenerate faces is repaired (stderr says what changed, in
  the file's numbering) unless --no-repair.

Outcomes (the --json last line):
  completed              ran its steps
  converged              W changed less than 1e-4 relative, at the requested τ, over 3 steps,
                         or no step could lower it (--all-steps: run them all)
  target_reached         W reached --until-willmore
  max_deviation          the next step would have moved the surface further than
                         --max-deviation from the input: the output is the last surface within it
  feature_scale_reached  --feature-size: the detail below it is gone
  stalled                the safeguard let only steps of τ/16 or less through for 5 steps: the
                         output is the last sound surface
  already_fair           the mesh is too coarse to be faired (denoise: no noise found)
  no_progress            the safeguard found no acceptable step (exit code 3)

Exit codes:
  0  success (any outcome but no_progress)
  2  input refused, with the reason on stderr
  1  a failure while running: the output holds the last sound surface, and stderr names its step
  3  the safeguard found no acceptable step: the output holds the last accepted surface (the
     same as the last --frames-dir frame) and stderr says why

The default method and its --denoise-* knobs: docs/denoise.md. Regions, feature scale,
boundaries and the rest of the conformal flow's options: docs/library.md.";

#[derive(Args, Debug)]
#[command(after_long_help = FAIR_AFTER_HELP)]
pub struct FairArgs {
    /// Input mesh (.obj, .gltf, .glb, .stl, .ply, .off; without one of these extensions the
    /// content decides).
    pub input: PathBuf,
    /// Output mesh; its extension picks the format (none: the input's format).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Number of flow steps, at most: the run stops earlier when W stops falling (relative
    /// change below 1e-4 for 3 steps) or another stopping rule below applies.
    #[arg(long, default_value_t = 10)]
    pub steps: usize,
    /// Time step. Conformal flow: the paper's τ, stable below 1 (0.5 removes the unconstrained
    /// curvature in one step). MCF and cMCF: unitless, the step is τ·area/4π; bi-Laplacian:
    /// τ·(area/4π)² (0.01 is stable, 0.5 is not); Taubin: λ = τ (below 0.7).
    #[arg(long, default_value_t = 0.5)]
    pub tau: f64,
    /// Inverse power iterations per step.
    #[arg(long, default_value_t = 1)]
    pub iterations: usize,
    /// `denoise` (the default: feature-preserving denoising by guided normal filtering; a mesh
    /// without noise is left as it is, outcome `already_fair`), `conformal` (the paper's
    /// Willmore flow, toward the round sphere: `--method conformal` is the flow all the way),
    /// `mcf`, `cmcf` (conformalized MCF, genus 0 only), `bilaplacian` or `taubin` (λ|μ
    /// smoothing, λ = τ).
    /// Given twice, the last one counts (a script's own choice after a wrapper's).
    #[arg(long, default_value = "denoise", value_parser = Method::parse, overrides_with = "method")]
    pub method: Method,
    /// `--method denoise`: outer filtering iterations (1–200); default: read off the mesh
    /// (none without noise, else until the share of flat edges settles, 4–20). Two
    /// iterations make one step.
    #[arg(long)]
    pub denoise_iterations: Option<usize>,
    /// `--method denoise`: vertex updates per outer iteration (1–200).
    #[arg(long, default_value_t = 10)]
    pub denoise_vertex_iterations: usize,
    /// `--method denoise`: width of the range kernel in unit-normal difference, (0, 2]
    /// (0.35 ≈ 20°: guidance normals further apart do not mix, so creases stay).
    #[arg(long, default_value_t = 0.35)]
    pub denoise_sigma_r: f64,
    /// `--method denoise`: the filtering disc's radius in mean centroid distances, 0.5–4.
    #[arg(long, default_value_t = 2.0)]
    pub denoise_radius: f64,
    /// `--method denoise`: plain bilateral range weights (Zheng et al. 2011) instead of guided
    /// ones (Zhang et al. 2015).
    #[arg(long)]
    pub denoise_bilateral: bool,
    /// Repair the input first: drop degenerate faces and split non-manifold vertices and
    /// edges (one vertex per fan); what changed is printed on stderr, in file numbering. The
    /// default (a file that needs no repair reads as it is); kept for scripts that pass it.
    #[arg(long, conflicts_with = "no_repair")]
    pub repair: bool,
    /// Refuse a file that needs repair instead, naming its vertex and face numbers.
    #[arg(long)]
    pub no_repair: bool,
    /// Loop-subdivide the input toward a target edge length before the flow (UVs
    /// interpolated per corner): for coarse tessellations (a CAD part) that end
    /// `already_fair`. The output has the refined connectivity: the file's vertices first,
    /// then the new ones.
    #[arg(long)]
    pub refine: bool,
    /// The target edge length for --refine (model units, > 0); default: the edge that gives
    /// about 16k triangles.
    #[arg(long, requires = "refine")]
    pub refine_edge: Option<f64>,
    /// Close holes before the flow (after --refine): every boundary loop up to MAX, which is
    /// `all` (the default when MAX is left out), an integer (the loop's boundary vertices) or
    /// a decimal (its extent in model units, e.g. 0.25). Each patch is triangulated, refined
    /// to the surrounding edge length and faired G1 against the surface; the output has the
    /// file's vertices and faces first, then the patches'.
    #[arg(
        long,
        value_name = "MAX",
        num_args = 0..=1,
        default_missing_value = "all",
        value_parser = HoleSize::parse
    )]
    pub fill_holes: Option<HoleSize>,
    /// Write every intermediate mesh here, as `frame_NNNN.<ext>` (the output's format).
    #[arg(long)]
    pub frames_dir: Option<PathBuf>,
    /// One JSON object per step on stdout instead of a progress bar.
    #[arg(long)]
    pub json: bool,
    /// Leave out the exactness constraints on surfaces of genus > 0 (App. C): only to see
    /// what they prevent (the paper's Figure 12).
    #[arg(long)]
    pub no_exactness: bool,
    /// Möbius balancing toward the input's area distribution (App. E).
    #[arg(long)]
    pub mobius: bool,
    /// Take every step at --tau whatever it does. By default a step that raises the Willmore
    /// energy or damages the mesh is retried at a smaller τ (willow::flow::safeguard).
    #[arg(long)]
    pub no_safeguard: bool,
    /// Threads for the factorizations (0: every core). One CLI run is one flow, so it may
    /// use the machine; the result is bitwise the same for any count.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// The conformal flow's Dirac factor: auto (single precision kept across steps, with
    /// conjugate gradients, from 100k vertices), double (refactored exactly every step) or mixed.
    #[arg(long, value_enum, default_value_t = super::bench::PrecisionArg::Auto)]
    pub precision: super::bench::PrecisionArg,
    /// Spectral filter strength σ (§4, unitless: σ = (l(l+1))^−k puts the crossover at
    /// spherical degree l); needs --filter-k.
    #[arg(long, requires = "filter_k")]
    pub filter_sigma: Option<f64>,
    /// Spectral filter shape k (0..=3); k = 2 approximates position-based Willmore flow.
    #[arg(long, requires = "filter_sigma")]
    pub filter_k: Option<u32>,
    /// Boundary condition for surfaces with boundary (§6.3).
    #[arg(long, value_enum, default_value_t = BoundaryArg::Auto)]
    pub boundary: BoundaryArg,
    /// With --boundary prescribed: V = cos φ·B + sin φ·N, φ in radians, |φ| ≤ 1.5 (§6.3.1).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub frame_angle: f64,
    /// With --boundary prescribed: the target Ṽ is the input's V turned by this angle
    /// (radians); one value for every loop, or one per boundary loop, comma-separated.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    pub boundary_rotation: Vec<f64>,
    /// With --boundary prescribed: the rotation axis, `tangent` (the boundary tangent at each
    /// vertex) or a fixed direction `x,y,z`.
    #[arg(long, default_value = "tangent", allow_negative_numbers = true)]
    pub boundary_axis: String,
    /// What each connected component keeps after every step: `area` (the input's area and
    /// centroid), `volume` (closed components keep their enclosed volume, to 1e-6, open ones
    /// their area) or `none` (only the centroid).
    #[arg(long, default_value = "area", value_parser = Preserve::parse)]
    pub preserve: Preserve,
    /// Stop before the first step that would move the surface further than D (model units)
    /// from the input, in either direction; the output is the last surface within D.
    #[arg(long, value_name = "D", allow_negative_numbers = true)]
    pub max_deviation: Option<f64>,
    /// Stop once the Willmore energy is at most W (4π for a round sphere).
    #[arg(long, value_name = "W", allow_negative_numbers = true)]
    pub until_willmore: Option<f64>,
    /// Run every step: do not stop when W has stopped falling (outcome `converged`).
    #[arg(long)]
    pub all_steps: bool,
    /// Report each step's distance from the input (`deviation_max`, `deviation_mean`; on with
    /// `--max-deviation`). At 100k triangles it costs up to 7.3% of a step at τ 0.5 and 9.7%
    /// at τ 0.01 on one thread, 6–8.5% with `--threads 2`; off by default, since on a mesh of
    /// a few thousand triangles it costs as much as the step (`willow bench` prints the
    /// figure; docs/performance.md).
    #[arg(long)]
    pub measure_deviation: bool,
    /// Fair only a sphere of the surface, `x,y,z,r` (model units); everything outside the
    /// regions stays bit-identical. Repeatable; all `--region-*` flags name their union.
    #[arg(long, value_name = "X,Y,Z,R", allow_negative_numbers = true, value_parser = Region::parse_sphere)]
    pub region_sphere: Vec<Region>,
    /// Fair only a box, `xmin,ymin,zmin,xmax,ymax,zmax`. Repeatable.
    #[arg(long, value_name = "MIN,MAX", allow_negative_numbers = true, value_parser = Region::parse_box)]
    pub region_box: Vec<Region>,
    /// Fair only the file vertices listed in FILE (numbers separated by commas, spaces or
    /// lines: OBJ `v` lines from 0, glTF accessor vertices).
    #[arg(long, value_name = "FILE")]
    pub region_vertices: Option<PathBuf>,
    /// Fair only the faces of a named group of the file: an OBJ `g` or `o` name, a glTF node
    /// or mesh name. Repeatable.
    #[arg(long, value_name = "NAME")]
    pub region_group: Vec<String>,
    /// How a region meets the surface around it: `smooth` (tangent-continuous) or `fixed`.
    #[arg(long, default_value = "smooth", value_parser = Seam::parse)]
    pub seam: Seam,
    /// Remove the detail smaller than L (model units) and keep the shape above it; the run
    /// ends `feature_scale_reached` once that detail is gone (conformal flow only; with
    /// --filter-sigma/--filter-k those replace the σ and k derived from L).
    #[arg(long, value_name = "L", allow_negative_numbers = true)]
    pub feature_size: Option<f64>,
    /// Blend a region's motion to zero over this width (model units) toward its border.
    #[arg(long, value_name = "F", allow_negative_numbers = true)]
    pub falloff: Option<f64>,
    /// Keep sharp edges sharp: edges whose faces meet at more than this many degrees, in
    /// chains of 8 or more, read off the denoised surface, are creases; the conformal flow
    /// holds them and fairs the patches between. `auto` (30°, only on parts that have such
    /// chains), `none`, or an angle (0 < A < 180).
    #[arg(long, value_name = "A", default_value = "auto", allow_negative_numbers = true,
          value_parser = FeatureAngle::parse)]
    pub feature_angle: FeatureAngle,
}

/// The vertex numbers of a `--region-vertices` file.
fn read_vertex_list(path: &Path) -> Result<Region, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("--region-vertices {}: {e}", path.display()))?;
    Region::parse_vertices(&text).map_err(|e| format!("--region-vertices {}: {e}", path.display()))
}

/// `--boundary-axis`: `tangent` or `x,y,z`.
fn parse_axis(text: &str) -> Result<AxisSpec, String> {
    if text.eq_ignore_ascii_case("tangent") {
        return Ok(AxisSpec::Tangent);
    }
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let values: Result<Vec<f64>, _> = parts.iter().map(|p| p.parse::<f64>()).collect();
    match values {
        Ok(v) if v.len() == 3 => Ok(AxisSpec::Fixed([v[0], v[1], v[2]])),
        _ => Err(format!(
            "--boundary-axis must be `tangent` or three numbers `x,y,z`, got {text:?}"
        )),
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum BoundaryArg {
    /// The border stays where it is: held under the conformal flow (`fixed`), free under the
    /// other methods and with regions, which keep it themselves.
    Auto,
    /// The boundary moves freely (§6.2): an open scan may shrink away from its border.
    Free,
    /// Boundary vertices stay exactly where they are.
    Fixed,
    /// V = B kept at the input's binormals: flows to constant mean curvature.
    Cmc,
    /// Prescribed boundary vectors: see --frame-angle, --boundary-rotation, --boundary-axis.
    Prescribed,
}

/// The input's format: its extension, else what its content shows (magic bytes, keywords).
fn input_format_of(path: &Path, bytes: &[u8]) -> Result<Format, String> {
    Format::from_path(path)
        .or_else(|| Format::sniff(bytes))
        .ok_or_else(|| {
            format!(
                "input {}: unknown extension and unrecognized content (expected .obj, .gltf, \
                 .glb, .stl, .ply or .off)",
                path.display()
            )
        })
}

/// The output's format: its extension, else the input's (what you read is what you get).
fn output_format_of(path: &Path, input: Format) -> Result<Format, String> {
    match path.extension() {
        None => Ok(input),
        Some(_) => Format::from_path(path).ok_or_else(|| {
            format!(
                "output {}: unknown extension (expected .obj, .gltf, .glb, .stl, .ply or .off, \
                 or none for the input's format)",
                path.display()
            )
        }),
    }
}

pub fn run(args: FairArgs) -> ExitCode {
    let bytes = match read_input(&args.input) {
        Ok(b) => b,
        Err(code) => return code,
    };
    let input_format = match input_format_of(&args.input, &bytes) {
        Ok(f) => f,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    let output_format = match output_format_of(&args.output, input_format) {
        Ok(f) => f,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    let read = if args.no_repair {
        Asset::read
    } else {
        Asset::read_repaired
    };
    let asset = match read(&bytes, input_format, &Limits::default()) {
        Ok(a) => a,
        Err(e) => return fail(EXIT_BAD_INPUT, format!("{}: {e}", args.input.display())),
    };
    if !asset.repairs().is_empty() {
        // On stderr, so --json's stdout stays one object per step.
        eprintln!("repaired {}: {}", args.input.display(), asset.repairs());
    }
    for note in asset.notes() {
        eprintln!("note: {}: {note}", args.input.display());
    }
    let asset = if args.refine {
        match asset.refined(args.refine_edge, &Limits::default()) {
            Ok((refined, how)) => {
                eprintln!(
                    "refined {}: {} levels, {} → {} faces, {} → {} vertices",
                    args.input.display(),
                    how.levels,
                    how.faces_before,
                    refined.surface().face_count(),
                    how.vertices_before,
                    refined.file_vertex_count()
                );
                refined
            }
            Err(e) => return fail(EXIT_BAD_INPUT, format!("--refine: {e}")),
        }
    } else {
        asset
    };
    let asset = match args.fill_holes {
        Some(size) => {
            match fill_asset_holes(&asset, size, &FlowParams::default(), &Limits::default()) {
                Ok(r) => {
                    eprintln!(
                        "filled {}: {} holes closed ({} vertices, {} triangles appended), {} \
                         left open{}",
                        args.input.display(),
                        r.filled,
                        r.new_vertices,
                        r.new_triangles,
                        r.left_open.len(),
                        if r.left_open.is_empty() {
                            String::new()
                        } else {
                            format!(" (loops of {:?} vertices, larger than {size})", r.left_open)
                        }
                    );
                    for note in r.asset.notes().iter().filter(|n| n.contains("no UVs")) {
                        eprintln!("note: {}: {note}", args.input.display());
                    }
                    r.asset
                }
                Err(e) => return fail(EXIT_BAD_INPUT, format!("--fill-holes: {e}")),
            }
        }
        None => asset,
    };
    // The CLI maps onto the same job spec as HTTP and gRPC, and is checked by the same rules.
    let boundary = match args.boundary {
        BoundaryArg::Auto => BoundarySpec::Auto,
        BoundaryArg::Free => BoundarySpec::Free,
        BoundaryArg::Fixed => BoundarySpec::Fixed,
        BoundaryArg::Cmc => BoundarySpec::Cmc,
        BoundaryArg::Prescribed => {
            let axis = match parse_axis(&args.boundary_axis) {
                Ok(a) => a,
                Err(e) => return fail(EXIT_BAD_INPUT, e),
            };
            let angles = match args.boundary_rotation.as_slice() {
                [] => AnglesSpec::Uniform(0.0),
                [a] => AnglesSpec::Uniform(*a),
                many => AnglesSpec::PerLoop(many.to_vec()),
            };
            BoundarySpec::Prescribed(PrescribedSpec {
                frame_angle: args.frame_angle,
                axis,
                angles,
            })
        }
    };
    let mut region: Vec<Region> = args
        .region_sphere
        .iter()
        .chain(&args.region_box)
        .cloned()
        .collect();
    if let Some(path) = &args.region_vertices {
        match read_vertex_list(path) {
            Ok(list) => region.push(list),
            Err(e) => return fail(EXIT_BAD_INPUT, e),
        }
    }
    let spec = JobSpec {
        method: args.method,
        steps: args.steps,
        tau: args.tau,
        iterations: args.iterations,
        exactness: !args.no_exactness,
        mobius_balancing: args.mobius,
        filter: match (args.filter_sigma, args.filter_k) {
            (Some(sigma), Some(k)) => Some(FilterSpec { sigma, k }),
            _ => None,
        },
        boundary,
        safeguard: !args.no_safeguard,
        region,
        seam: args.seam,
        repair: !args.no_repair,
        refine: args.refine,
        fill_holes: args.fill_holes,
        feature_angle: args.feature_angle,
        denoise: willow_service::jobs::spec::DenoiseSpec {
            iterations: args.denoise_iterations,
            vertex_iterations: args.denoise_vertex_iterations,
            sigma_r: args.denoise_sigma_r,
            radius: args.denoise_radius,
            guided: !args.denoise_bilateral,
        },
        ..JobSpec::default()
    };
    if let Err(e) = spec
        .validate_with(usize::MAX, f64::INFINITY)
        .and_then(|()| spec.validate_for_asset(&asset))
    {
        return fail(EXIT_BAD_INPUT, e);
    }
    // Vertex regions are renumbered from the file's numbering to the welded surface's.
    let base = match spec.flow_params_for(&asset) {
        Ok(p) => p,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    // Groups are the file's own names: looked up here, on the welded surface (the job spec
    // holds file-numbered regions only).
    let groups: Vec<Region> = args
        .region_group
        .iter()
        .cloned()
        .map(Region::Group)
        .collect();
    let groups = match resolve_groups(&groups, &asset) {
        Ok(g) => g,
        Err(e) => return fail(EXIT_BAD_INPUT, format!("--region-group: {e}")),
    };
    let regions: Vec<Region> = base.regions.iter().cloned().chain(groups).collect();
    let params = willow::flow::FlowParams {
        // `auto` resolved again: a group is a region too, and a region holds its own border.
        boundary: spec.boundary.to_flow(spec.method, !regions.is_empty()),
        regions,
        threads: match args.threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        },
        precision: args.precision.into(),
        preserve: args.preserve,
        max_deviation: args.max_deviation,
        until_willmore: args.until_willmore,
        until_converged: !args.all_steps,
        feature_size: args.feature_size,
        falloff: args.falloff,
        measure_deviation: args.measure_deviation,
        ..base
    };
    // The job spec checked everything else; these the library checks, named as flags.
    if let Err(FlowError::InvalidParameter { name, reason }) = params.validate() {
        return fail(
            EXIT_BAD_INPUT,
            format!("--{}: {reason}", name.replace('_', "-")),
        );
    }
    let flow = match new_flow(asset.surface(), &params) {
        Ok(f) => f,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    let mut run = match Run::new(flow, &params, args.steps) {
        Ok(r) => r,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    if let Some(dir) = &args.frames_dir {
        if let Err(e) = std::fs::create_dir_all(dir) {
            return fail(
                EXIT_FAILURE,
                format!("cannot create {}: {e}", dir.display()),
            );
        }
    }

    let progress = if !args.json && std::io::stderr().is_terminal() {
        let bar =
            ProgressBar::with_draw_target(Some(args.steps as u64), ProgressDrawTarget::stderr());
        if let Ok(style) = ProgressStyle::with_template("{bar:40} {pos}/{len} {msg}") {
            bar.set_style(style);
        }
        Some(bar)
    } else {
        None
    };
    let stdout = std::io::stdout();
    let print_line = |line: String| -> Result<(), ExitCode> {
        let mut out = stdout.lock();
        // stdout closed (e.g. piped into `head`): stop quietly, like other tools.
        writeln!(out, "{line}")
            .and_then(|_| out.flush())
            .map_err(|_| ExitCode::from(EXIT_FAILURE))
    };
    // The last surface a step ended on: a numerical failure part-way through a step leaves
    // the flow's own positions undefined, and the output gets this one instead (issue 39).
    let mut sound = run.flow().positions().to_vec();
    let mut sound_step = 0;
    let (outcome, reason) = loop {
        let metrics = match run.advance() {
            Ok(Event::Step(m)) => m,
            // The flow is on its result (for `no_progress`, the last accepted surface):
            // write it below, then say why it stopped.
            Ok(Event::Stopped { outcome, reason }) => break (outcome, reason),
            Err(e) => {
                if let Some(bar) = &progress {
                    bar.abandon();
                }
                return match write_mesh(&asset, &sound, output_format, &args.output) {
                    Ok(()) => fail(
                        EXIT_FAILURE,
                        format!(
                            "{e}; {} holds the last sound surface (step {sound_step})",
                            args.output.display()
                        ),
                    ),
                    Err(w) => fail(
                        EXIT_FAILURE,
                        format!("{e}; writing the last sound surface: {w}"),
                    ),
                };
            }
        };
        sound.copy_from_slice(run.flow().positions());
        sound_step = metrics.step;
        if args.json {
            let line = match serde_json::to_string(&metrics) {
                Ok(l) => l,
                Err(e) => return fail(EXIT_FAILURE, e),
            };
            if let Err(code) = print_line(line) {
                return code;
            }
        }
        if let Some(bar) = &progress {
            bar.set_message(format!(
                "W {:.4} (|Δf| form {:.4})  Q mean {:.4} p95 {:.3}  ln area ratio [{:.2}, {:.2}], \
                 {} collapsed{}  τ {}{}  {:.0} ms",
                metrics.willmore_energy,
                metrics.willmore_energy_vector.unwrap_or(f64::NAN),
                metrics.q_mean,
                metrics.q_p95,
                metrics.log_area_ratio_p1.unwrap_or(f64::NAN),
                metrics.log_area_ratio_p99.unwrap_or(f64::NAN),
                metrics.collapsed_triangles.unwrap_or(0),
                metrics
                    .deviation_max
                    .map(|d| format!("  dev {d:.3e}"))
                    .unwrap_or_default(),
                metrics.tau,
                match metrics.rejected {
                    0 => String::new(),
                    n => format!(" ({n} rejected)"),
                },
                metrics.step_ms
            ));
            bar.inc(1);
        }
        if let Some(dir) = &args.frames_dir {
            let path = dir.join(format!(
                "frame_{:04}.{}",
                metrics.step,
                output_format.extension()
            ));
            if let Err(e) = write_mesh(&asset, run.flow().positions(), output_format, &path) {
                return fail(EXIT_FAILURE, e);
            }
        }
    };
    if let Some(bar) = progress {
        bar.finish();
    }
    if let Err(e) = write_mesh(&asset, run.flow().positions(), output_format, &args.output) {
        return fail(EXIT_FAILURE, e);
    }
    if args.json {
        let line = serde_json::json!({"outcome": outcome, "reason": reason}).to_string();
        if let Err(code) = print_line(line) {
            return code;
        }
    }
    match outcome {
        Outcome::NoProgress => fail(
            EXIT_NO_PROGRESS,
            format!(
                "{reason}; {} holds the last accepted surface",
                args.output.display()
            ),
        ),
        _ => {
            if !args.json {
                eprintln!("{}: {reason}", outcome.name());
            }
            ExitCode::SUCCESS
        }
    }
}

fn write_mesh(
    asset: &Asset,
    positions: &[[f64; 3]],
    format: Format,
    path: &Path,
) -> Result<(), String> {
    let bytes = asset
        .write(positions, format)
        .map_err(|e| format!("cannot encode {}: {e}", path.display()))?;
    std::fs::write(path, bytes).map_err(|e| format!("cannot write {}: {e}", path.display()))
}
