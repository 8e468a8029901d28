//! `willow bench --holes`: issue 40's hole-filling figures. Three holes (radius 3%, 5%, 8% of
//! the diagonal, `cut_benchmark_holes`) are cut into closed meshes (spot and the genus-2
//! surface from ../shared/meshes, Loop-subdivided once) and the stanford bunny's own five
//! holes are kept; each is closed by Willow (`fill_holes` + `fair_holes`) and, with
//! `--cgal PYTHON`, by CGAL's `triangulate_refine_and_fair_hole` through
//! `scripts/cgal-fill-holes.py`, in the same run on the same holed file. Printed per filler:
//! new vertices, the patch's mean distance to the surface cut away (‰ of the diagonal), the
//! seam's mean dihedral angle beside the uncut surface's, folds, and the filling time (CGAL:
//! its calls only, best of 3; Willow: triangulation, refinement and fairing, best of 3).

use super::{fail, EXIT_BAD_INPUT, EXIT_FAILURE};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Instant;
use willow::flow::holes::fair_holes;
use willow::flow::FlowParams;
use willow::mesh::holes::{
    cut_benchmark_holes, fill_holes, loop_extent, patch_quality, true_seam_dihedral, HoleSize,
    PatchQuality,
};
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::refine::loop_subdivide;
use willow::mesh::{Mesh, Topology};

/// Conformal steps the fairing may take per run (it stops earlier once W settles).
pub const FAIR_STEPS: usize = 20;

struct Case {
    name: String,
    holed: Mesh,
    /// The faces cut away and the uncut seam angle, when the holes were cut here.
    removed: Option<(Vec<[[f64; 3]; 3]>, f64)>,
    diagonal: f64,
}

struct Filling {
    new_vertices: usize,
    quality: PatchQuality,
    seconds: f64,
    closed: bool,
}

fn read_mesh(path: &Path) -> Result<Mesh, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let format = Format::from_path(path).unwrap_or(Format::Obj);
    Asset::read(&bytes, format, &Limits::default())
        .map(|a| a.surface().clone())
        .map_err(|e| format!("{}: {e}", path.display()))
}

fn diagonal(mesh: &Mesh) -> f64 {
    loop_extent(
        &mesh.positions,
        &(0..mesh.vertex_count()).collect::<Vec<_>>(),
    )
}

fn cases(shared: &Path) -> Result<Vec<Case>, String> {
    let mut out = Vec::new();
    for name in ["spot_triangulated.obj", "genus2_24.obj"] {
        let mesh = loop_subdivide(&read_mesh(&shared.join(name))?).0;
        let cut = cut_benchmark_holes(&mesh).ok_or(format!("{name}: a hole ball holds no face"))?;
        let seam = true_seam_dihedral(&mesh, &cut);
        out.push(Case {
            name: format!("{name} ×1, 3 cut holes"),
            diagonal: diagonal(&mesh),
            holed: cut.mesh,
            removed: Some((cut.removed, seam)),
        });
    }
    let bunny = read_mesh(&shared.join("stanford-bunny.obj"))?;
    out.push(Case {
        name: "stanford-bunny.obj, its own holes".into(),
        diagonal: diagonal(&bunny),
        holed: bunny,
        removed: None,
    });
    Ok(out)
}

fn quality(mesh: &Mesh, case: &Case) -> PatchQuality {
    let removed = case
        .removed
        .as_ref()
        .map(|(r, _)| r.as_slice())
        .unwrap_or(&[]);
    patch_quality(
        mesh,
        case.holed.vertex_count(),
        case.holed.face_count(),
        removed,
    )
}

fn willow(case: &Case) -> Result<Filling, String> {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..3 {
        let start = Instant::now();
        let filled = fill_holes(&case.holed, HoleSize::Any, &Limits::default())
            .map_err(|e| e.to_string())?;
        let faired =
            fair_holes(&filled, &FlowParams::default(), FAIR_STEPS).map_err(|e| e.to_string())?;
        best = best.min(start.elapsed().as_secs_f64());
        last = Some(faired.mesh);
    }
    let mesh = last.ok_or("no run")?;
    Ok(Filling {
        new_vertices: mesh.vertex_count() - case.holed.vertex_count(),
        quality: quality(&mesh, case),
        seconds: best,
        closed: Topology::new(&mesh).is_closed(),
    })
}

/// Writes `mesh` as a plain OBJ (vertex and face order kept), for the CGAL script.
fn write_obj(mesh: &Mesh, path: &Path) -> Result<(), String> {
    use std::fmt::Write as _;
    let mut text = String::new();
    for p in &mesh.positions {
        let _ = writeln!(text, "v {:?} {:?} {:?}", p[0], p[1], p[2]);
    }
    for t in &mesh.triangles {
        let _ = writeln!(text, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    std::fs::write(path, text).map_err(|e| format!("{}: {e}", path.display()))
}

/// A plain OBJ's `v` and `f` lines in file order (the CGAL script writes nothing else).
fn read_plain_obj(path: &Path) -> Result<Mesh, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    for line in text.lines() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let p: Vec<f64> = it.take(3).filter_map(|x| x.parse().ok()).collect();
                if p.len() != 3 {
                    return Err(format!("{}: bad v line {line:?}", path.display()));
                }
                positions.push([p[0], p[1], p[2]]);
            }
            Some("f") => {
                let f: Vec<usize> = it
                    .filter_map(|x| x.split('/').next()?.parse::<usize>().ok())
                    .collect();
                if f.len() != 3 || f.contains(&0) {
                    return Err(format!("{}: bad f line {line:?}", path.display()));
                }
                triangles.push([f[0] - 1, f[1] - 1, f[2] - 1]);
            }
            _ => {}
        }
    }
    Mesh::new(positions, triangles).map_err(|e| format!("{}: {e}", path.display()))
}

fn cgal(case: &Case, python: &Path, dir: &Path, index: usize) -> Result<Filling, String> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/cgal-fill-holes.py");
    let input = dir.join(format!("holed-{index}.obj"));
    let output = dir.join(format!("cgal-{index}.obj"));
    write_obj(&case.holed, &input)?;
    let run = Command::new(python)
        .arg(&script)
        .arg(&input)
        .arg(&output)
        .args(["--repeat", "3"])
        .output()
        .map_err(|e| format!("{}: {e}", python.display()))?;
    if !run.status.success() {
        return Err(format!(
            "the CGAL script failed: {}",
            String::from_utf8_lossy(&run.stderr)
        ));
    }
    let report: serde_json::Value = serde_json::from_slice(&run.stdout)
        .map_err(|e| format!("the CGAL script's report: {e}"))?;
    let seconds = report["seconds"]
        .as_f64()
        .ok_or("the CGAL script's report has no seconds")?;
    let mesh = read_plain_obj(&output)?;
    Ok(Filling {
        new_vertices: mesh.vertex_count() - case.holed.vertex_count(),
        quality: quality(&mesh, case),
        seconds,
        closed: Topology::new(&mesh).is_closed(),
    })
}

fn print_row(who: &str, r: &Filling, case: &Case) {
    let distance = if case.removed.is_some() {
        format!("{:>8.3}", 1e3 * r.quality.mean_distance / case.diagonal)
    } else {
        format!("{:>8}", "—")
    };
    println!(
        "  {who:<7} new V {:>6}  distance ‰ {distance}  seam {:>6.2}°  folds {:>3}  closed {:<5}  {:>9.1} ms",
        r.new_vertices,
        r.quality.seam_dihedral_deg,
        r.quality.folds,
        r.closed,
        1e3 * r.seconds
    );
}

pub fn run(shared: Option<&Path>, python: Option<&Path>) -> ExitCode {
    let shared = shared
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("../shared/meshes"));
    let cases = match cases(&shared) {
        Ok(c) => c,
        Err(e) => return fail(EXIT_BAD_INPUT, e),
    };
    let dir = std::env::temp_dir().join(format!("willow-bench-holes-{}", std::process::id()));
    if python.is_some() {
        if let Err(e) = std::fs::create_dir_all(&dir) {
            return fail(EXIT_FAILURE, format!("{}: {e}", dir.display()));
        }
    }
    for (i, case) in cases.iter().enumerate() {
        println!(
            "{} ({} vertices, {} loops){}",
            case.name,
            case.holed.vertex_count(),
            Topology::new(&case.holed).boundary_loops.len(),
            case.removed
                .as_ref()
                .map(|(_, s)| format!(", uncut seam {s:.2}°"))
                .unwrap_or_default()
        );
        let ours = match willow(case) {
            Ok(r) => r,
            Err(e) => return fail(EXIT_FAILURE, format!("{}: willow: {e}", case.name)),
        };
        print_row("willow", &ours, case);
        if let Some(py) = python {
            match cgal(case, py, &dir, i) {
                Ok(theirs) => {
                    print_row("cgal", &theirs, case);
                    println!(
                        "  willow / cgal: time {:.2}, seam {:.2}{}",
                        ours.seconds / theirs.seconds,
                        ours.quality.seam_dihedral_deg / theirs.quality.seam_dihedral_deg,
                        if case.removed.is_some() {
                            format!(
                                ", distance {:.2}",
                                ours.quality.mean_distance / theirs.quality.mean_distance
                            )
                        } else {
                            String::new()
                        }
                    );
                }
                Err(e) => return fail(EXIT_FAILURE, format!("{}: cgal: {e}", case.name)),
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    ExitCode::SUCCESS
}
