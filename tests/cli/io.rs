//! Formats by extension, JSON lines and frames, exit codes on bad input, `--repair`.

use super::*;

#[test]
fn fair_writes_json_lines_frames_and_output() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("spot.glb");
    let frames = dir.path().join("frames");
    let run = willow()
        .args(["fair", "--method", "conformal", &spot(), "-o"])
        .arg(&out)
        .args(["--steps", "3", "--tau", "0.5", "--json", "--frames-dir"])
        .arg(&frames)
        .output()
        .expect("run willow");
    assert!(
        run.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let stdout = String::from_utf8(run.stdout).expect("utf-8");
    let mut lines: Vec<serde_json::Value> = stdout
        .lines()
        .map(|l| serde_json::from_str(l).expect("each line is JSON"))
        .collect();
    // The last line says how the run ended.
    let outcome = lines.pop().unwrap_or_default();
    assert_eq!(outcome["outcome"], "completed", "{outcome}");
    assert_eq!(outcome["reason"], "ran its 3 steps", "{outcome}");
    assert_eq!(lines.len(), 3);
    let mut previous = f64::INFINITY;
    for (i, line) in lines.iter().enumerate() {
        assert_eq!(line["step"].as_u64(), Some(i as u64 + 1));
        for key in [
            "willmore_energy",
            "q_mean",
            "q_p95",
            "q_max",
            "closure_residual",
            "step_ms",
        ] {
            assert!(line[key].as_f64().is_some(), "missing {key} in {line}");
        }
        let w = line["willmore_energy"].as_f64().unwrap_or(f64::NAN);
        assert!(w < previous, "W must fall: {w} after {previous}");
        previous = w;
    }
    for step in 1..=3 {
        let frame = frames.join(format!("frame_{step:04}.glb"));
        assert!(frame.exists(), "{} missing", frame.display());
    }
    let bytes = std::fs::read(&out).expect("output written");
    assert_eq!(&bytes[0..4], b"glTF", "GLB magic");
}

#[test]
fn fair_obj_to_obj_keeps_uv_lines() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("spot.obj");
    let run = willow()
        .args(["fair", "--method", "conformal", &spot(), "-o"])
        .arg(&out)
        .args(["--steps", "1", "--method", "mcf", "--tau", "0.01"])
        .output()
        .expect("run willow");
    assert!(
        run.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let text = std::fs::read_to_string(&out).expect("output");
    let input = std::fs::read_to_string(spot()).expect("input");
    let count = |s: &str, p: &str| s.lines().filter(|l| l.starts_with(p)).count();
    assert_eq!(count(&text, "vt "), count(&input, "vt "));
    assert_eq!(count(&text, "f "), count(&input, "f "));
}

#[test]
fn bad_input_exits_nonzero_with_the_reason() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bad = dir.path().join("nan.obj");
    std::fs::write(&bad, "v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n").expect("write");
    let run = willow()
        .args(["fair"])
        .arg(&bad)
        .args(["-o"])
        .arg(dir.path().join("out.obj"))
        .output()
        .expect("run willow");
    assert_eq!(run.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("error:") && stderr.to_lowercase().contains("finite"),
        "{stderr}"
    );

    let run = willow()
        .args(["fair", &spot(), "-o", "out.step"])
        .output()
        .expect("run willow");
    assert_eq!(run.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&run.stderr).contains("unknown extension"));

    let run = willow()
        .args(["fair", "/nonexistent/mesh.obj", "-o", "out.obj"])
        .output()
        .expect("run willow");
    assert_eq!(run.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&run.stderr).contains("cannot read"));

    let run = willow()
        .args(["fair", "--method", "conformal", &spot(), "-o"])
        .arg(dir.path().join("o.obj"))
        .arg("--tau=-1")
        .output()
        .expect("run willow");
    assert_eq!(run.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&run.stderr).contains("tau"));
}

#[test]
fn fair_reads_and_writes_stl_ply_and_off_in_kind() {
    use willow::mesh::io::{Asset, Format, Limits};
    let dir = tempfile::tempdir().expect("tempdir");
    let sphere = willow::mesh::generate::bumpy_sphere(2, 0.1);
    let asset = Asset::from_mesh(sphere, &Limits::default()).expect("valid");
    for (format, output) in [
        (Format::Ply, "out.ply"),
        (Format::Stl, "out.stl"),
        // No extension: the input's format.
        (Format::Off, "out"),
    ] {
        let input = dir.path().join(format!("in.{}", format.extension()));
        let bytes = asset
            .write(&asset.surface().positions, format)
            .expect("write");
        std::fs::write(&input, &bytes).expect("write input");
        let out = dir.path().join(output);
        let run = willow()
            .args(["fair", "--method", "conformal"])
            .arg(&input)
            .arg("-o")
            .arg(&out)
            .args(["--steps", "3", "--json"])
            .output()
            .expect("run willow");
        assert_eq!(
            run.status.code(),
            Some(0),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let written = std::fs::read(&out).expect("output written");
        assert_eq!(Format::sniff(&written), Some(format), "{output}");
        let back = Asset::read(&written, format, &Limits::default()).expect("output parses");
        let before = Asset::read(&bytes, format, &Limits::default()).expect("input parses");
        assert_eq!(back.file_vertex_count(), before.file_vertex_count());
        assert_eq!(back.surface().face_count(), before.surface().face_count());
        assert_ne!(
            back.surface().positions,
            before.surface().positions,
            "faired"
        );
    }
}

#[test]
fn repair_flag_splits_a_bowtie_and_reports_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    // Two tetrahedra sharing the single `v` line 1: a bowtie in the file itself.
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv -1 0 0\nv 0 -1 0\nv 0 0 -1\n\
                f 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\nf 1 6 5\nf 1 5 7\nf 5 6 7\nf 1 7 6\n";
    let input = dir.path().join("bowtie.obj");
    std::fs::write(&input, text).expect("write");
    let out = dir.path().join("out.ply");
    let run = |repair: bool| {
        let mut c = willow();
        c.args(["fair", "--method", "conformal"])
            .arg(&input)
            .arg("-o")
            .arg(&out)
            .args(["--steps", "2"]);
        c.arg(if repair { "--repair" } else { "--no-repair" });
        c.output().expect("run willow")
    };
    let refused = run(false);
    assert_eq!(refused.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("in the file: `v` on line 1"), "{stderr}");
    let fixed = run(true);
    let stderr = String::from_utf8_lossy(&fixed.stderr);
    assert_eq!(fixed.status.code(), Some(0), "{stderr}");
    assert!(
        stderr.contains("split 1 non-manifold vertices into 1 more (first: 0)"),
        "{stderr}"
    );
    let back = willow::mesh::io::Asset::read(
        &std::fs::read(&out).expect("output"),
        willow::mesh::io::Format::Ply,
        &willow::mesh::io::Limits::default(),
    )
    .expect("the repaired PLY reads without repair");
    assert_eq!(back.surface().vertex_count(), 8);
}

/// A CAD cylinder (radius 1, height 2, 32 vertices per rim, fan caps) as OBJ text: too
/// coarse to fair (issue 26 item 5).
fn cylinder_obj() -> String {
    let n = 32;
    let mut s = String::new();
    for z in [-1.0, 1.0] {
        for i in 0..n {
            let a = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
            s += &format!("v {} {} {z}\n", a.cos(), a.sin());
        }
    }
    s += "v 0 0 -1\nv 0 0 1\n";
    let (bottom, top) = (2 * n + 1, 2 * n + 2);
    for i in 0..n {
        let (a, b) = (i + 1, (i + 1) % n + 1);
        s += &format!("f {a} {b} {}\nf {a} {} {}\n", b + n, b + n, a + n);
        s += &format!("f {bottom} {b} {a}\nf {top} {} {}\n", a + n, b + n);
    }
    s
}

#[test]
fn refine_flag_subdivides_a_coarse_cylinder_that_is_otherwise_already_fair() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("cylinder.obj");
    std::fs::write(&input, cylinder_obj()).expect("write");
    let out = dir.path().join("out.obj");
    let run = |extra: &[&str]| {
        willow()
            .args(["fair", "--method", "conformal"])
            .arg(&input)
            .arg("-o")
            .arg(&out)
            .args(["--steps", "3"])
            .args(extra)
            .output()
            .expect("run willow")
    };
    let plain = run(&[]);
    let stderr = String::from_utf8_lossy(&plain.stderr);
    assert_eq!(plain.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("already_fair"), "{stderr}");

    // With a target edge of 0.5 (the rims' edges are 0.2, the sides' 2): 128 · 4^levels
    // faces, still one closed genus-0 surface.
    let refined = run(&["--refine", "--refine-edge", "0.5"]);
    let stderr = String::from_utf8_lossy(&refined.stderr);
    assert_eq!(refined.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("refined"), "{stderr}");
    assert!(!stderr.contains("already_fair"), "{stderr}");
    let text = std::fs::read_to_string(&out).expect("output");
    let faces = text.lines().filter(|l| l.starts_with("f ")).count();
    let verts = text.lines().filter(|l| l.starts_with("v ")).count();
    assert_eq!(faces % 128, 0, "{faces} faces: 128 · 4^levels");
    assert!(faces >= 4 * 128, "{faces}");
    // Euler: a closed genus-0 surface has V − E + F = 2 with E = 3F/2.
    assert_eq!(
        verts + faces - 3 * faces / 2,
        2,
        "{verts} vertices, {faces} faces"
    );

    let bad = run(&["--refine", "--refine-edge", "0"]);
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert_eq!(bad.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("refine"), "{stderr}");
}

#[test]
fn a_numerical_failure_still_writes_the_last_sound_surface() {
    // The implicit bi-Laplacian flow at an absurd step, unguarded: its system stops being
    // numerically positive definite at step 3 on spot.
    let dir = tempfile::tempdir().expect("tempdir");
    let run = |steps: &str, out: &std::path::Path| {
        willow()
            .args(["fair", "--method", "conformal"])
            .arg(spot())
            .arg("-o")
            .arg(out)
            .args([
                "--method",
                "bilaplacian",
                "--tau",
                "1e6",
                "--no-safeguard",
                "--all-steps",
            ])
            .args(["--steps", steps])
            .output()
            .expect("run willow")
    };
    let failed_out = dir.path().join("failed.obj");
    let failed = run("20", &failed_out);
    let stderr = String::from_utf8_lossy(&failed.stderr);
    assert_eq!(failed.status.code(), Some(1), "{stderr}");
    let step = stderr
        .split("holds the last sound surface (step ")
        .nth(1)
        .and_then(|rest| rest.split(')').next())
        .unwrap_or_else(|| panic!("stderr names the surface written: {stderr}"));
    // The same surface as a run that stops there by itself.
    let kept_out = dir.path().join("kept.obj");
    let kept = run(step, &kept_out);
    assert_eq!(
        kept.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&kept.stderr)
    );
    assert_eq!(
        std::fs::read(&failed_out).expect("written on failure"),
        std::fs::read(&kept_out).expect("written")
    );
}

#[test]
fn fill_holes_closes_the_stanford_bunnys_five_holes_and_a_size_keeps_the_large_ones() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bunny = match std::env::var_os("WILLOW_SHARED_MESHES") {
        Some(d) => std::path::PathBuf::from(d).join("stanford-bunny.obj"),
        None => std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/meshes/stanford-bunny.obj"),
    };
    assert!(
        bunny.exists(),
        "the shared bunny is missing: {}",
        bunny.display()
    );
    let input_v = std::fs::read_to_string(&bunny)
        .expect("bunny")
        .lines()
        .filter(|l| l.starts_with("v "))
        .count();
    let out = dir.path().join("out.obj");
    let run = |extra: &[&str]| {
        willow()
            .args(["fair", "--method", "mcf", "--steps", "1"])
            .arg(&bunny)
            .arg("-o")
            .arg(&out)
            .args(extra)
            .output()
            .expect("run willow")
    };
    let boundary_edges = |text: &str| {
        let mut count = std::collections::HashMap::new();
        for l in text.lines().filter(|l| l.starts_with("f ")) {
            let v: Vec<usize> = l
                .split_whitespace()
                .skip(1)
                .map(|c| c.split('/').next().and_then(|x| x.parse().ok()).expect("f"))
                .collect();
            for k in 0..v.len() {
                let (a, b) = (v[k], v[(k + 1) % v.len()]);
                *count.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        count.values().filter(|&&c| c == 1).count()
    };

    let all = run(&["--fill-holes"]);
    let stderr = String::from_utf8_lossy(&all.stderr);
    assert_eq!(all.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("5 holes closed"), "{stderr}");
    let text = std::fs::read_to_string(&out).expect("output");
    assert_eq!(boundary_edges(&text), 0, "every hole closed");
    assert!(text.lines().filter(|l| l.starts_with("v ")).count() > input_v);

    // The bunny's loops have 22–80 boundary vertices: 40 keeps the two largest open.
    let some = run(&["--fill-holes", "40"]);
    let stderr = String::from_utf8_lossy(&some.stderr);
    assert_eq!(some.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("3 holes closed"), "{stderr}");
    assert!(stderr.contains("2 left open"), "{stderr}");
    let text = std::fs::read_to_string(&out).expect("output");
    assert_eq!(boundary_edges(&text), 42 + 80);

    let bad = run(&["--fill-holes", "big"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("hole size"));
}
