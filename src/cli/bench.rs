//! `willow bench [MESH...]`: per mesh, the median per-step time of the conformal flow (and per
//! try: a step the safeguard retried counts its time over its tries) and of implicit MCF
//! measured in the same run (their steps interleaved), their ratio (per try), the cost of
//! the safeguard (the same conformal flow with `safeguard` off, interleaved too: where no try
//! is rejected both take identical steps, so the time ratio is the safeguard's overhead), and
//! the conformal flow's peak memory. Figures, not
//! pass/fail: performance targets are checked by reading these, never by timed tests. The
//! table ends with a line giving the median step of the closed curve flow (§5) at 2,000
//! vertices.

use super::{fail, EXIT_BAD_INPUT, EXIT_FAILURE};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;
use willow::curve::{Curve, CurveFlow, CurveParams};
use willow::flow::region::Region;
use willow::flow::{new_flow, FlowParams, Method, Precision};
use willow::geometry::operators::face_areas_into;
use willow::mesh::generate::bumpy_sphere;
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::Mesh;

/// The part of `willow bench --help` that is no one flag's: what it measures and prints.
const BENCH_AFTER_HELP: &str = "\
Per mesh: the median per-step time of the conformal flow (and per try: a step the safeguard
retried counts its time over its tries) and of implicit MCF (unguarded: the yardstick's cost,
not its quality) measured in the same run, their ratio (per try), the safeguard's overhead
(guarded steps taken at their first try against the same conformal flow unguarded, interleaved
too; the rejected tries are counted beside it), the conformal flow's peak RSS, and where its
last step and its setup went, phase by phase. The flows take turns step by step, so a change
in the machine's speed during the run moves both medians alike instead of the ratio.

--denoise DIR: θ and Dv of the noisy input, of the defaults and of Taubin-10, in the same run,
their times and ratios (docs/denoise.md). --genus [MESH]: the conformal step on a surface of
higher genus (default botijo_genus5_irregular) with and without its exactness constraints,
against a generated genus-0 irregular sphere of the same size, at the same τ, in one run.
--creases: crease detection and the conformal step with a generated CAD part's creases held,
beside the same flow across them (feature_angle none), in one run. --holes [DIR] [--cgal PY]:
three holes cut into spot and the genus-2 surface (DIR: the shared meshes) and the stanford
bunny's five, filled by Willow and by CGAL in one run: patch distance to the cut surface,
seam angle, folds and time.
Current figures: docs/measurements.md.";

#[derive(Args, Debug)]
#[command(after_long_help = BENCH_AFTER_HELP)]
pub struct BenchArgs {
    /// Meshes to measure. Default: cheburashka and nefertiti from ../shared/meshes when
    /// present, else generated bumpy spheres of 20k and 82k triangles.
    pub meshes: Vec<PathBuf>,
    /// Steps per flow (the first step is included: it pays for nothing extra, the symbolic
    /// analysis happens when the flow is built and is reported separately). Nine steps give a
    /// median that a few steps slowed by other processes on a shared machine cannot move.
    #[arg(long, default_value_t = 9)]
    pub steps: usize,
    /// Conformal time step.
    #[arg(long, default_value_t = 0.5)]
    pub tau: f64,
    /// One JSON object per mesh instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Instead: the genus-g step with exactness constraints against a genus-0 mesh of the same
    /// size (issue 4); MESH defaults to botijo_genus5_irregular from ../shared/meshes.
    #[arg(long, conflicts_with = "json")]
    pub genus: bool,
    /// Instead: the cost of keeping creases (issue 40): detection, and the conformal step
    /// with a generated CAD part's creases held beside the same flow across them.
    #[arg(long, conflicts_with_all = ["json", "genus"])]
    pub creases: bool,
    /// Instead: hole filling (issue 40): three holes cut into spot and the genus-2 surface
    /// and the stanford bunny's own five, closed by Willow and, with `--cgal PYTHON`, by
    /// CGAL's `triangulate_refine_and_fair_hole` in the same run.
    #[arg(long, conflicts_with_all = ["json", "genus", "creases"])]
    pub holes: bool,
    /// With --holes: a Python with CGAL's bindings (scripts/cgal-fill-holes-setup.sh prints
    /// one), to measure CGAL on the same holed files.
    #[arg(long, value_name = "PYTHON", requires = "holes")]
    pub cgal: Option<PathBuf>,
    /// Instead: the denoising benchmark (issue 39) on every `<Name>_Noisy.obj` /
    /// `<Name>_Original.obj` pair in DIR (e.g. ../shared/meshes/denoise): θ and Dv of the
    /// noisy input, of Willow's defaults and of Taubin-10 measured in the same run, with
    /// their times and ratios.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["json", "genus"])]
    pub denoise: Option<PathBuf>,
    /// Generated meshes to measure as well, built in code so anyone can reproduce a figure
    /// without a file: `icosphere:N` is the bumpy sphere on an N-times subdivided icosahedron
    /// (20·4^N triangles: 8 gives 1.3M).
    #[arg(long, value_name = "icosphere:N")]
    pub generate: Vec<String>,
    /// Skip the safeguard-overhead column (the unguarded flow run beside the guarded one):
    /// at a million triangles it doubles the run time.
    #[arg(long)]
    pub no_overhead: bool,
    /// Threads for the factorizations of every flow measured (the conformal flow and the MCF
    /// yardstick alike, so the ratio compares equals), and for the distance measure, as a job
    /// given that many threads measures it.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// The conformal flow's Dirac factor: auto (single precision with conjugate gradients
    /// from 100k vertices), double or mixed.
    #[arg(long, value_enum, default_value_t = PrecisionArg::Auto)]
    pub precision: PrecisionArg,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum PrecisionArg {
    Auto,
    Double,
    Mixed,
}

impl From<PrecisionArg> for Precision {
    fn from(p: PrecisionArg) -> Self {
        match p {
            PrecisionArg::Auto => Precision::Auto,
            PrecisionArg::Double => Precision::Double,
            PrecisionArg::Mixed => Precision::Mixed,
        }
    }
}

/// The most subdivisions `--generate` builds: 9 is 5.2M triangles, beyond this machine.
const MAX_SUBDIVISIONS: usize = 8;

/// The subdivisions `icosphere:N` asks for.
fn parse_generate(spec: &str) -> Result<usize, String> {
    let n = spec
        .strip_prefix("icosphere:")
        .and_then(|n| n.parse::<usize>().ok())
        .ok_or_else(|| format!("--generate {spec}: expected icosphere:N"))?;
    if n > MAX_SUBDIVISIONS {
        return Err(format!(
            "--generate {spec}: at most {MAX_SUBDIVISIONS} subdivisions"
        ));
    }
    Ok(n)
}

#[derive(serde::Serialize)]
struct Figures {
    mesh: String,
    vertices: usize,
    faces: usize,
    setup_ms: f64,
    conformal_median_step_ms: f64,
    /// Median time of one try of a conformal step (a step's time over its tries): the cost
    /// of the computation, whatever the safeguard rejected. The ratio uses it.
    conformal_median_try_ms: f64,
    mcf_median_step_ms: f64,
    ratio: f64,
    /// Median conformal step with the safeguard off, and the overhead in %: the median of the
    /// guarded steps taken at their first try over it, minus 1.
    unguarded_median_step_ms: f64,
    safeguard_overhead_percent: f64,
    /// Tries the safeguard rejected over the guarded run (the overhead is meaningful at 0).
    rejected_tries: u32,
    conformal_peak_rss_mb: Option<f64>,
    final_willmore_energy: f64,
    final_q_mean: f64,
    /// Where the conformal flow's last step went: (phase, ms), in the order they ran.
    profile: Vec<(String, f64)>,
    /// Where its setup went (the safeguard's own setup is the rest of `setup_ms`).
    setup_profile: Vec<(String, f64)>,
    /// The same flow on a region of [`REGION_SHARE`] of the vertices (a sphere about the
    /// vertex farthest along +x): its vertex count, setup, median try, and that try over the
    /// whole mesh's (issue 29: the system solved is the region's).
    region_vertices: usize,
    region_setup_ms: f64,
    region_median_try_ms: f64,
    region_try_ratio: f64,
    /// Where the region flow's last step went, as `profile` for the whole mesh.
    region_profile: Vec<(String, f64)>,
    /// The distance from the input (`deviation_max`, `deviation_mean`) measured on every frame
    /// of the conformal flow, as a job measures it (one `Deviation`, frame after frame, on the
    /// flow's threads), in ms
    /// and over the median try (issue 29: at most 10% at 100k triangles, in every phase): after
    /// the first step (the surface near the input), after the last (moved far from it), and
    /// the slowest frame.
    deviation_near_ms: f64,
    deviation_near_ratio: f64,
    deviation_far_ms: f64,
    deviation_far_ratio: f64,
    deviation_worst_ms: f64,
    deviation_worst_ratio: f64,
    /// The last frame's `deviation_max` (model units): how far "far" was.
    deviation_far_max: f64,
    /// Where the slowest frame's measure went: (phase, ms), as
    /// `Deviation::profile` names them.
    deviation_worst_profile: Vec<(String, f64)>,
}

/// The share of a mesh's vertices the region benchmark fairs.
const REGION_SHARE: f64 = 0.05;

pub fn run(args: BenchArgs) -> ExitCode {
    if let Some(dir) = &args.denoise {
        return super::bench_denoise::run(dir);
    }
    if args.creases {
        return super::bench_creases::run(args.steps);
    }
    if args.holes {
        return super::bench_holes::run(
            args.meshes.first().map(PathBuf::as_path),
            args.cgal.as_deref(),
        );
    }
    if args.genus {
        return super::bench_genus::run(args.meshes.first().map(PathBuf::as_path), args.steps);
    }
    let inputs = match list_inputs(&args.meshes, &args.generate) {
        Ok(i) => i,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    if !args.json {
        println!(
            "{:<28} {:>8} {:>8} {:>10} {:>14} {:>10} {:>12} {:>7} {:>14} {:>9} {:>12}",
            "mesh",
            "V",
            "F",
            "setup ms",
            "conformal ms",
            "(per try)",
            "MCF ms",
            "ratio",
            "guard % (rej)",
            "",
            "peak RSS MB"
        );
    }
    for input in inputs {
        // Built here and dropped after its row, so that no other input's mesh counts in a
        // mesh's peak RSS (a generated million-triangle mesh is 60 MB).
        let (name, mesh) = match input.load() {
            Ok(loaded) => loaded,
            Err(e) => return fail(EXIT_BAD_INPUT, e),
        };
        match measure(&name, &mesh, &args) {
            Ok(f) => {
                if args.json {
                    match serde_json::to_string(&f) {
                        Ok(s) => println!("{s}"),
                        Err(e) => return fail(EXIT_FAILURE, e),
                    }
                } else {
                    println!(
                        "{:<28} {:>8} {:>8} {:>10.1} {:>14.1} {:>10.1} {:>12.2} {:>7.2} {:>14.1} {:>9} {:>12}",
                        f.mesh,
                        f.vertices,
                        f.faces,
                        f.setup_ms,
                        f.conformal_median_step_ms,
                        f.conformal_median_try_ms,
                        f.mcf_median_step_ms,
                        f.ratio,
                        f.safeguard_overhead_percent,
                        format!("({})", f.rejected_tries),
                        f.conformal_peak_rss_mb
                            .map(|m| format!("{m:.0}"))
                            .unwrap_or_else(|| "n/a".into())
                    );
                    let phases: Vec<String> = f
                        .profile
                        .iter()
                        .map(|(name, value)| format!("{name} {value:.1}"))
                        .collect();
                    println!("    last conformal step: {}", phases.join(", "));
                    let setup: Vec<String> = f
                        .setup_profile
                        .iter()
                        .map(|(name, value)| format!("{name} {value:.1}"))
                        .collect();
                    println!("    conformal setup: {}", setup.join(", "));
                    println!(
                        "    region of {} vertices ({:.0}%): setup {:.1} ms, per try {:.2} ms, \
                         {:.1}% of the whole mesh's try",
                        f.region_vertices,
                        REGION_SHARE * 100.0,
                        f.region_setup_ms,
                        f.region_median_try_ms,
                        f.region_try_ratio * 100.0
                    );
                    let phases: Vec<String> = f
                        .region_profile
                        .iter()
                        .map(|(name, value)| format!("{name} {value:.2}"))
                        .collect();
                    println!("    last region step: {}", phases.join(", "));
                    println!(
                        "    distance from the input (deviation_*) a frame: near (step 1) {:.2} ms, \
                         {:.1}% of a try; far (step {}, max {:.3e}) {:.2} ms, {:.1}%; slowest \
                         frame {:.2} ms, {:.1}%",
                        f.deviation_near_ms,
                        f.deviation_near_ratio * 100.0,
                        args.steps,
                        f.deviation_far_max,
                        f.deviation_far_ms,
                        f.deviation_far_ratio * 100.0,
                        f.deviation_worst_ms,
                        f.deviation_worst_ratio * 100.0
                    );
                    let phases: Vec<String> = f
                        .deviation_worst_profile
                        .iter()
                        .map(|(name, value)| format!("{name} {value:.1}"))
                        .collect();
                    println!("    slowest distance frame: {}", phases.join(", "));
                }
            }
            Err(e) => return fail(EXIT_FAILURE, format!("{name}: {e}")),
        }
    }
    // Table only: `--json` keeps its contract of exactly one object per mesh.
    if args.json {
        return ExitCode::SUCCESS;
    }
    match measure_curve() {
        Ok(c) => println!(
            "curve flow (closed, {} vertices): median {:.4} ms per step over {} steps, \
             curvature std/mean {:.1e}",
            c.curve_vertices,
            c.curve_median_step_ms,
            c.curve_steps,
            c.final_curvature_std_over_mean
        ),
        Err(e) => return fail(EXIT_FAILURE, format!("curve flow: {e}")),
    }
    ExitCode::SUCCESS
}

/// Vertices of the benchmark curve: the size issue 4 states its target for (≤ 0.1 ms/step).
const CURVE_VERTICES: usize = 2000;
/// Curve steps take a fraction of a millisecond, so a stable median needs many of them; 200
/// cost well under a second.
const CURVE_STEPS: usize = 200;

struct CurveFigures {
    curve_vertices: usize,
    curve_steps: usize,
    curve_median_step_ms: f64,
    final_curvature_std_over_mean: f64,
}

/// Median per-step time of the closed isometric curve flow (§5) on a generated noisy curve,
/// `r = 1 + 0.2 sin 5t` plus deterministic radial jitter of 0.2% (smaller than the edge
/// length, so no cusps), at τ = 0.5.
fn measure_curve() -> Result<CurveFigures, String> {
    let n = CURVE_VERTICES;
    let points = (0..n)
        .map(|i| {
            let t = i as f64 * std::f64::consts::TAU / n as f64;
            // A hash in [-1, 1): reproducible noise without a random-number dependency.
            let jitter = ((i as f64 * 12.9898).sin() * 43758.5453).fract();
            let r = 1.0 + 0.2 * (5.0 * t).sin() + 0.002 * jitter;
            [r * t.cos(), r * t.sin()]
        })
        .collect();
    let curve = Curve::new(points, true).map_err(|e| e.to_string())?;
    let mut flow = CurveFlow::new(curve, CurveParams::default()).map_err(|e| e.to_string())?;
    let mut times = Vec::with_capacity(CURVE_STEPS);
    let mut last = flow.initial_metrics();
    for _ in 0..CURVE_STEPS {
        last = flow.step();
        times.push(last.step_ms);
    }
    Ok(CurveFigures {
        curve_vertices: n,
        curve_steps: CURVE_STEPS,
        curve_median_step_ms: median(&mut times),
        final_curvature_std_over_mean: last.curvature_std_over_mean,
    })
}

/// A mesh to measure, loaded only when its turn comes ([`Input::load`]).
enum Input {
    File(PathBuf),
    /// The bumpy sphere on an icosahedron subdivided this many times.
    Icosphere {
        name: String,
        subdivisions: usize,
    },
}

impl Input {
    fn load(&self) -> Result<(String, Mesh), String> {
        match self {
            Input::File(path) => {
                let name = path
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_else(|| path.display().to_string());
                Ok((name, read(path)?))
            }
            Input::Icosphere { name, subdivisions } => {
                Ok((name.clone(), bumpy_sphere(*subdivisions, 0.15)))
            }
        }
    }
}

/// The inputs in the order they are measured. A bad `--generate` spec or a path that is no
/// file fails here, before any measurement; a file that does not parse fails at its turn.
fn list_inputs(paths: &[PathBuf], generated: &[String]) -> Result<Vec<Input>, String> {
    let mut inputs = Vec::new();
    if paths.is_empty() && generated.is_empty() {
        let shared = PathBuf::from("../shared/meshes");
        for name in ["cheburashka.obj", "nefertiti.obj"] {
            let path = shared.join(name);
            if path.exists() {
                inputs.push(Input::File(path));
            }
        }
        if inputs.is_empty() {
            for subdivisions in [5, 6] {
                inputs.push(Input::Icosphere {
                    name: format!("bumpy_sphere({subdivisions})"),
                    subdivisions,
                });
            }
        }
    }
    for path in paths {
        if !path.is_file() {
            return Err(format!("cannot read {}: not a file", path.display()));
        }
        inputs.push(Input::File(path.clone()));
    }
    for spec in generated {
        let subdivisions = parse_generate(spec)?;
        inputs.push(Input::Icosphere {
            name: format!("bumpy icosphere:{subdivisions}"),
            subdivisions,
        });
    }
    Ok(inputs)
}

fn read(path: &PathBuf) -> Result<Mesh, String> {
    let format =
        Format::from_path(path).ok_or_else(|| format!("{}: unknown extension", path.display()))?;
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let asset = Asset::read(&bytes, format, &Limits::default())
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(asset.surface().clone())
}

fn measure(name: &str, mesh: &Mesh, args: &BenchArgs) -> Result<Figures, String> {
    reset_peak_rss();
    let setup = std::time::Instant::now();
    let conformal = FlowParams {
        method: Method::Conformal,
        tau: args.tau,
        iterations: 1,
        threads: args.threads,
        precision: args.precision.into(),
        ..FlowParams::default()
    };
    let mut flow = new_flow(mesh, &conformal).map_err(|e| e.to_string())?;
    let setup_ms = setup.elapsed().as_secs_f64() * 1e3;
    let mut times = Vec::with_capacity(args.steps);
    let mut try_times = Vec::with_capacity(args.steps);
    let mut last = flow.initial_metrics();
    // The first step alone: the steps allocate nothing, so the peak RSS after it is the
    // conformal flow's own, before the MCF flow is built beside it.
    if args.steps > 0 {
        last = flow.step().map_err(|e| e.to_string())?;
        times.push(last.step_ms);
        try_times.push(last.step_ms / f64::from(1 + last.rejected));
    }
    let peak = peak_rss_mb();
    // Built after the peak is read, so the flow's own memory stays comparable with earlier runs.
    let mut deviation = FrameDeviation::new(mesh, args.threads);
    if args.steps > 0 {
        deviation.time(flow.positions());
    }

    // A small MCF step: its cost does not depend on τ, and mean curvature flow pinches thin
    // features (cheburashka's ears) within a few larger steps, after which M + hL stops being
    // positive definite. If it still breaks down, the steps it did take are timed.
    // The yardstick runs unguarded: implicit MCF folds a face of cheburashka even at τ/1024
    // (cotan weights go negative on obtuse triangles), so the safeguard would stop it at step
    // 1, and the ratio is about the cost of one step, not about its quality.
    let mcf = FlowParams {
        method: Method::Mcf,
        tau: 0.01,
        iterations: 1,
        safeguard: false,
        threads: args.threads,
        ..FlowParams::default()
    };
    let mut mcf_flow = new_flow(mesh, &mcf).map_err(|e| e.to_string())?;
    let unguarded = FlowParams {
        safeguard: false,
        ..conformal.clone()
    };
    let mut unguarded_flow = if args.no_overhead {
        None
    } else {
        Some(new_flow(mesh, &unguarded).map_err(|e| e.to_string())?)
    };
    let mut unguarded_times = Vec::with_capacity(args.steps);
    let mut unguarded_running = unguarded_flow.is_some();
    let mut rejected = last.rejected;
    // Guarded steps taken at their first try: the overhead is measured on those alone (a
    // rejected try costs a whole step, which is the point, not overhead).
    let mut clean_times: Vec<f64> = times
        .iter()
        .copied()
        .filter(|_| last.rejected == 0)
        .collect();
    let mut mcf_times = Vec::with_capacity(args.steps);
    let mut mcf_running = true;
    // The two flows take turns, step by step: this VM's speed drifts by up to 1.5x over
    // seconds (the setup time of identical work moves 51 -> 86 ms), and timing one flow after
    // the other let that drift into the ratio (nefertiti: 9.5 one run, 6.5 the next).
    for k in 0..args.steps {
        if mcf_running {
            match mcf_flow.step() {
                Ok(m) => mcf_times.push(m.step_ms),
                Err(e) if mcf_times.is_empty() => return Err(format!("implicit MCF: {e}")),
                Err(_) => mcf_running = false,
            }
        }
        if k + 1 < args.steps {
            last = flow.step().map_err(|e| e.to_string())?;
            times.push(last.step_ms);
            try_times.push(last.step_ms / f64::from(1 + last.rejected));
            rejected += last.rejected;
            if last.rejected == 0 {
                clean_times.push(last.step_ms);
            }
            deviation.time(flow.positions());
        }
        if let (true, Some(unguarded_flow)) = (unguarded_running, unguarded_flow.as_mut()) {
            // Timed from outside, like the guarded step's step_ms (which spans its tries).
            let t = std::time::Instant::now();
            match unguarded_flow.step() {
                Ok(_) => unguarded_times.push(t.elapsed().as_secs_f64() * 1e3),
                Err(_) => unguarded_running = false,
            }
        }
    }
    let profile = profile_of(flow.as_ref());
    let setup_profile = flow
        .setup_profile()
        .map(|p| {
            p.phases()
                .iter()
                .map(|&(n, ms)| (format!("{n} ms"), ms))
                .collect()
        })
        .unwrap_or_default();
    drop((flow, mcf_flow, unguarded_flow));
    let region = measure_region(mesh, &conformal, args.steps)?;
    let u = median(&mut unguarded_times);
    let clean = median(&mut clean_times);
    let (c, m) = (median(&mut times), median(&mut mcf_times));
    let t = median(&mut try_times);
    let share = |ms: f64| if t > 0.0 { ms / t } else { f64::NAN };
    Ok(Figures {
        mesh: name.to_string(),
        vertices: mesh.vertex_count(),
        faces: mesh.face_count(),
        setup_ms,
        conformal_median_step_ms: c,
        mcf_median_step_ms: m,
        conformal_median_try_ms: t,
        ratio: if m > 0.0 { t / m } else { f64::NAN },
        unguarded_median_step_ms: u,
        safeguard_overhead_percent: if u > 0.0 {
            (clean / u - 1.0) * 100.0
        } else {
            f64::NAN
        },
        rejected_tries: rejected,
        conformal_peak_rss_mb: peak,
        final_willmore_energy: last.willmore_energy,
        final_q_mean: last.q_mean,
        profile,
        setup_profile,
        region_vertices: region.vertices,
        region_setup_ms: region.setup_ms,
        region_median_try_ms: region.median_try_ms,
        region_try_ratio: if t > 0.0 {
            region.median_try_ms / t
        } else {
            f64::NAN
        },
        region_profile: region.profile,
        deviation_near_ms: deviation.near_ms(),
        deviation_near_ratio: share(deviation.near_ms()),
        deviation_far_ms: deviation.far_ms(),
        deviation_far_ratio: share(deviation.far_ms()),
        deviation_worst_ms: deviation.worst_ms(),
        deviation_worst_ratio: share(deviation.worst_ms()),
        deviation_far_max: deviation.far_max,
        deviation_worst_profile: deviation.worst_profile,
    })
}

/// The flow's per-frame distance measurement (`geometry::distance::Deviation`, built once
/// from the input as the flow builds it), timed on each frame in turn: a job measures every
/// frame with one `Deviation`, which keeps what it learnt from the previous frame.
struct FrameDeviation {
    triangles: Vec<[usize; 3]>,
    areas: Vec<f64>,
    deviation: willow::geometry::distance::Deviation,
    frame_ms: Vec<f64>,
    far_max: f64,
    /// The slowest frame's `Deviation::profile`.
    worst_profile: Vec<(String, f64)>,
}

impl FrameDeviation {
    /// `threads`: the flow's, as a job passes its own ([`FlowParams::deviation_threads`]).
    fn new(mesh: &Mesh, threads: usize) -> Self {
        let topology = willow::mesh::topology::Topology::new(mesh);
        let mut areas = vec![0.0; mesh.face_count()];
        face_areas_into(&mesh.positions, &mesh.triangles, &mut areas);
        let deviation = willow::geometry::distance::Deviation::new(
            &mesh.positions,
            &mesh.triangles,
            &topology,
            &areas,
        )
        .with_threads(threads);
        FrameDeviation {
            triangles: mesh.triangles.clone(),
            areas,
            deviation,
            frame_ms: Vec::new(),
            far_max: f64::NAN,
            worst_profile: Vec::new(),
        }
    }

    fn time(&mut self, positions: &[[f64; 3]]) {
        // The face areas come with the frame (the flow has them already): not timed.
        face_areas_into(positions, &self.triangles, &mut self.areas);
        let t = std::time::Instant::now();
        let (max, _) = std::hint::black_box(self.deviation.measure(
            positions,
            &self.triangles,
            &self.areas,
        ));
        let ms = t.elapsed().as_secs_f64() * 1e3;
        if self.frame_ms.iter().all(|&slower| slower < ms) {
            self.worst_profile = self
                .deviation
                .profile()
                .iter()
                .map(|&(name, v)| (format!("{name} ms"), v))
                .chain([(
                    "mean's queries".to_string(),
                    self.deviation.mean_queries() as f64,
                )])
                .collect();
        }
        self.frame_ms.push(ms);
        self.far_max = max;
    }

    fn near_ms(&self) -> f64 {
        self.frame_ms.first().copied().unwrap_or(f64::NAN)
    }

    fn far_ms(&self) -> f64 {
        self.frame_ms.last().copied().unwrap_or(f64::NAN)
    }

    fn worst_ms(&self) -> f64 {
        self.frame_ms.iter().copied().fold(f64::NAN, f64::max)
    }
}

/// Where a flow's last step went: its phases in ms, then its counts.
pub(super) fn profile_of(flow: &dyn willow::flow::Flow) -> Vec<(String, f64)> {
    flow.profile()
        .map(|p| {
            let phases = p.phases().iter().map(|&(n, ms)| (format!("{n} ms"), ms));
            let counts = p.counts().iter().map(|&(n, c)| (n.to_string(), c));
            phases.chain(counts).collect()
        })
        .unwrap_or_default()
}

struct RegionFigures {
    vertices: usize,
    setup_ms: f64,
    median_try_ms: f64,
    profile: Vec<(String, f64)>,
}

/// `steps` steps of `params`' flow on a sphere about the vertex farthest along +x holding
/// [`REGION_SHARE`] of the vertices (a converged region ends early; its steps so far count).
fn measure_region(mesh: &Mesh, params: &FlowParams, steps: usize) -> Result<RegionFigures, String> {
    let tip = (0..mesh.vertex_count())
        .max_by(|&a, &b| mesh.positions[a][0].total_cmp(&mesh.positions[b][0]))
        .ok_or("an empty mesh")?;
    let center = mesh.positions[tip];
    let mut distances: Vec<f64> = mesh
        .positions
        .iter()
        .map(|p| {
            (0..3)
                .map(|a| (p[a] - center[a]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    let k = ((mesh.vertex_count() as f64 * REGION_SHARE).ceil() as usize).max(1);
    distances.sort_unstable_by(f64::total_cmp);
    let radius = distances[k - 1];
    let params = FlowParams {
        regions: vec![Region::Sphere { center, radius }],
        ..params.clone()
    };
    let start = std::time::Instant::now();
    let mut flow = new_flow(mesh, &params).map_err(|e| format!("region: {e}"))?;
    let setup_ms = start.elapsed().as_secs_f64() * 1e3;
    let mut tries = Vec::with_capacity(steps);
    for _ in 0..steps {
        match flow.step() {
            Ok(m) => tries.push(m.step_ms / f64::from(1 + m.rejected)),
            Err(_) if !tries.is_empty() => break,
            Err(e) => return Err(format!("region: {e}")),
        }
    }
    Ok(RegionFigures {
        vertices: k,
        setup_ms,
        median_try_ms: median(&mut tries),
        profile: profile_of(flow.as_ref()),
    })
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Linux resets the peak RSS (VmHWM) when "5" is written to /proc/self/clear_refs, so each
/// mesh's peak is its own.
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}
