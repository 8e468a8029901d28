//! `willow fair IN -o OUT` with no flags (issue 39): the default denoises a noisy mesh better
//! than Taubin-10 run by the same CLI, leaves a clean one alone, keeps an open scan's border
//! and repairs its bowtie, and a file's vertex numbering survives any output format.

use super::{json_lines, outcome, spot, willow};
use std::path::{Path, PathBuf};
use willow::denoise::score::score;
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::Mesh;

fn shared_denoise(file: &str) -> PathBuf {
    let dir = match std::env::var_os("WILLOW_SHARED_MESHES") {
        Some(d) => PathBuf::from(d).join("denoise"),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/meshes/denoise"),
    };
    let path = dir.join(file);
    assert!(
        path.is_file(),
        "{} is needed by this test; set WILLOW_SHARED_MESHES to the shared meshes' folder",
        path.display()
    );
    path
}

fn read(path: &Path) -> Mesh {
    let bytes = std::fs::read(path).expect("read mesh");
    let format = Format::from_path(path).expect("known extension");
    // Repaired as the CLI reads it by default (a file that needs none reads as it is).
    Asset::read_repaired(&bytes, format, &Limits::default())
        .expect("mesh reads")
        .surface()
        .clone()
}

fn fair(input: &Path, output: &Path, extra: &[&str]) -> std::process::Output {
    let out = willow()
        .arg("fair")
        .arg(input)
        .arg("-o")
        .arg(output)
        .arg("--json")
        .args(extra)
        .output()
        .expect("run willow");
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

#[test]
fn the_default_denoises_fandisk_better_than_taubin_from_the_same_cli() {
    let dir = tempfile::tempdir().expect("tempdir");
    let noisy = shared_denoise("Fandisk0.3_Noisy.obj");
    let clean = read(&shared_denoise("Fandisk0.3_Original.obj"));
    let ours = dir.path().join("ours.obj");
    let run = fair(&noisy, &ours, &[]);
    assert_eq!(outcome(&run)["outcome"], "completed");
    let theirs = dir.path().join("taubin.obj");
    fair(
        &noisy,
        &theirs,
        &[
            "--method",
            "taubin",
            "--tau",
            "0.5",
            "--steps",
            "10",
            "--all-steps",
            "--no-safeguard",
            "--preserve",
            "none",
        ],
    );
    let s = |m: Mesh| score(&m.positions, &clean.positions, &clean.triangles);
    let (before, ours, theirs) = (s(read(&noisy)), s(read(&ours)), s(read(&theirs)));
    assert!(
        ours.theta < 0.5 * theirs.theta && ours.theta < before.theta,
        "{ours:?} / {theirs:?}"
    );
    assert!(
        ours.distance < theirs.distance && ours.distance < before.distance,
        "{ours:?} / {theirs:?}"
    );
}

#[test]
fn a_clean_mesh_comes_out_as_it_went_in() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("spot.obj");
    let run = fair(Path::new(&spot()), &out, &[]);
    assert_eq!(
        outcome(&run)["outcome"],
        "already_fair",
        "{:?}",
        outcome(&run)
    );
    assert!(json_lines(&run).is_empty(), "no step taken");
    let (a, b) = (read(Path::new(&spot())), read(&out));
    let theta = willow::denoise::score::mean_normal_angle(&a.positions, &b.positions, &a.triangles);
    assert!(theta < 1e-3, "θ to the input {theta}°");
}

/// A noisy open scan: the bumpy cap (a sphere cut below z = −0.3) with Gaussian noise of 0.2
/// of an edge, and a stray pair of triangles touching its border at one vertex (a bowtie).
fn scan_obj() -> (String, usize, usize) {
    let mesh =
        willow::mesh::generate::with_noise(willow::mesh::generate::bumpy_cap(4, 0.05), 0.2, 11);
    let topology = willow::mesh::topology::Topology::new(&mesh);
    let border = topology.boundary_loops[0].vertices[0];
    let p = mesh.positions[border];
    let mut s = String::new();
    for q in &mesh.positions {
        s += &format!("v {} {} {}\n", q[0], q[1], q[2]);
    }
    let n = mesh.positions.len();
    for d in [[0.05, 0.0, -0.05], [0.05, 0.05, -0.05], [0.0, 0.05, -0.05]] {
        s += &format!("v {} {} {}\n", p[0] + d[0], p[1] + d[1], p[2] + d[2]);
    }
    for t in &mesh.triangles {
        s += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s += &format!("f {} {} {}\n", border + 1, n + 1, n + 2);
    s += &format!("f {} {} {}\n", border + 1, n + 2, n + 3);
    (s, n, border)
}

#[test]
fn an_open_noisy_scan_with_a_bowtie_is_repaired_and_keeps_its_border() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (text, n, _) = scan_obj();
    let input = dir.path().join("scan.obj");
    std::fs::write(&input, text).expect("write");
    let output = dir.path().join("out.obj");
    let run = fair(&input, &output, &[]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains("split 1 non-manifold vertices"), "{stderr}");
    let end = outcome(&run);
    assert_eq!(end["outcome"], "completed", "{end}");
    let (before, after) = (read(&input), read(&output));
    // The cap's own vertices, in file order (the OBJ keeps its `v` lines).
    let topology = willow::mesh::topology::Topology::new(&before);
    let edge = willow::mesh::generate::mean_edge_length(&before);
    let border = topology.boundary_vertex_mask(before.vertex_count());
    let moved = |i: usize| {
        let (a, b) = (before.positions[i], after.positions[i]);
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let worst_border = (0..n).filter(|&i| border[i]).map(moved).fold(0.0, f64::max);
    assert!(
        worst_border < 0.5 * edge,
        "a border vertex moved {worst_border} (edge {edge})"
    );
    // No crowding: the share of faces that shrank below 1e-3 of their area share.
    let crowded = willow::denoise::score::crowded_share(
        &before.positions,
        &after.positions,
        &before.triangles,
    );
    assert!(crowded < 0.005, "{crowded} of the faces crowded");
    // And it is smoother: the median dihedral angle fell.
    let median = |m: &Mesh| {
        willow::denoise::noise::median_dihedral(&m.positions, &m.triangles, &topology.edge_faces)
    };
    assert!(
        median(&after) < 0.5 * median(&before),
        "{} → {}",
        median(&before),
        median(&after)
    );
}

/// Issue 39: the conformal flow on an open scan keeps its border where it is unless asked
/// for `free` (where the border shrinks inward: what made a raw rabbit scan a crumpled fan).
#[test]
fn the_conformal_flow_holds_an_open_scans_border_unless_asked_free() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (text, n, _) = scan_obj();
    let input = dir.path().join("scan.obj");
    std::fs::write(&input, text).expect("write");
    let before = read(&input);
    let topology = willow::mesh::topology::Topology::new(&before);
    let border = topology.boundary_vertex_mask(before.vertex_count());
    let worst_border_move = |extra: &[&str]| {
        let output = dir.path().join("out.obj");
        let mut args = vec!["--method", "conformal", "--steps", "3"];
        args.extend_from_slice(extra);
        let run = fair(&input, &output, &args);
        let end = outcome(&run);
        assert_eq!(end["outcome"], "completed", "{extra:?}: {end}");
        let after = read(&output);
        (0..n)
            .filter(|&i| border[i])
            .map(|i| {
                let (a, b) = (before.positions[i], after.positions[i]);
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            })
            .fold(0.0, f64::max)
    };
    assert_eq!(worst_border_move(&[]), 0.0, "the default holds the border");
    assert_eq!(worst_border_move(&["--boundary", "auto"]), 0.0);
    let edge = willow::mesh::generate::mean_edge_length(&before);
    let free = worst_border_move(&["--boundary", "free"]);
    assert!(free > edge, "free: the border moved {free} (edge {edge})");
}

#[test]
fn a_ply_keeps_its_vertex_numbering_in_every_output_format() {
    let dir = tempfile::tempdir().expect("tempdir");
    // An octahedron whose faces use the records in an order unlike the file's.
    let v = [
        [0.0, 0.0, 1.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.0, 0.0, -1.0],
    ];
    let f = [
        [5, 2, 1],
        [5, 3, 2],
        [5, 4, 3],
        [5, 1, 4],
        [0, 1, 2],
        [0, 2, 3],
        [0, 3, 4],
        [0, 4, 1],
    ];
    let mut ply = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        v.len(),
        f.len()
    );
    for p in v {
        ply += &format!("{} {} {}\n", p[0], p[1], p[2]);
    }
    for t in f {
        ply += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    let input = dir.path().join("octa.ply");
    std::fs::write(&input, ply).expect("write");
    for ext in ["obj", "off", "ply", "glb"] {
        let output = dir.path().join(format!("out.{ext}"));
        fair(&input, &output, &[]);
        let back = std::fs::read(&output).expect("output");
        let asset = Asset::read(
            &back,
            Format::from_path(&output).expect("format"),
            &Limits::default(),
        )
        .expect("reads back");
        let positions = asset.file_positions(asset.surface().positions.as_slice());
        assert_eq!(positions.len(), v.len(), "{ext}");
        for (i, (p, q)) in positions.iter().zip(v).enumerate() {
            let same = (0..3).all(|k| (p[k] as f64 - q[k]).abs() < 1e-6);
            assert!(same, "{ext}: vertex {i} is {p:?}, the file's is {q:?}");
        }
    }
}
