//! The `willow` command-line contract: formats by extension, JSON lines, frames, exit codes.

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

#[test]
fn fair_writes_json_lines_frames_and_output() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("spot.glb");
    let frames = dir.path().join("frames");
    let run = willow()
        .args(["fair", &spot(), "-o"])
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
        .args(["fair", &spot(), "-o"])
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
        .args(["fair", &spot(), "-o"])
        .arg(dir.path().join("o.obj"))
        .arg("--tau=-1")
        .output()
        .expect("run willow");
    assert_eq!(run.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&run.stderr).contains("tau"));
}

#[test]
fn bench_prints_figures_and_ratio() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run = willow()
        .current_dir(dir.path()) // no ../shared/meshes here: use a given mesh
        .args(["bench", &spot(), "--steps", "2", "--json"])
        .output()
        .expect("run willow");
    assert!(
        run.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let line: serde_json::Value =
        serde_json::from_str(String::from_utf8_lossy(&run.stdout).trim()).expect("JSON");
    assert_eq!(line["faces"].as_u64(), Some(5856));
    let (c, m, r) = (
        line["conformal_median_step_ms"].as_f64().unwrap_or(0.0),
        line["mcf_median_step_ms"].as_f64().unwrap_or(0.0),
        line["ratio"].as_f64().unwrap_or(0.0),
    );
    assert!(c > 0.0 && m > 0.0 && (r - c / m).abs() < 1e-9 * r.max(1.0));
    // The safeguard's cost, measured against the same flow unguarded in the same run.
    assert!(line["unguarded_median_step_ms"].as_f64().unwrap_or(0.0) > 0.0);
    assert!(line["safeguard_overhead_percent"]
        .as_f64()
        .is_some_and(f64::is_finite));
    assert!(line["rejected_tries"].as_u64().is_some());
    // The distance from the input, timed on the first frame and the last (issue 29).
    for key in [
        "deviation_near_ms",
        "deviation_far_ms",
        "deviation_worst_ms",
    ] {
        assert!(
            line[key].as_f64().is_some_and(|ms| ms > 0.0),
            "{key}: {line}"
        );
    }
    let (far, worst) = (
        line["deviation_far_ms"].as_f64().unwrap_or(0.0),
        line["deviation_worst_ms"].as_f64().unwrap_or(0.0),
    );
    assert!(far <= worst, "{line}");
    assert!(line["deviation_far_max"].as_f64().is_some_and(|d| d > 0.0));
}

/// Meshes are measured in the order given, files before generated ones, each loaded only at
/// its turn; a path that is no file still fails before anything is measured.
#[test]
fn bench_measures_in_order_and_refuses_a_missing_file_first() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bench = |extra: &[&str]| {
        willow()
            .current_dir(dir.path())
            .args(["bench", &spot()])
            .args(extra)
            .args(["--steps", "1", "--no-overhead", "--json"])
            .output()
            .expect("run willow")
    };
    let run = bench(&["--generate", "icosphere:1"]);
    assert!(
        run.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let rows: Vec<serde_json::Value> = String::from_utf8_lossy(&run.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("one JSON object per line"))
        .collect();
    assert_eq!(rows.len(), 2, "{rows:?}");
    assert_eq!(rows[0]["faces"].as_u64(), Some(5856));
    assert_eq!(rows[1]["mesh"].as_str(), Some("bumpy icosphere:1"));
    assert_eq!(rows[1]["faces"].as_u64(), Some(80));
    // Each row also measures a region of 5% of its vertices (spot: 2930 welded vertices).
    assert_eq!(rows[0]["region_vertices"].as_u64(), Some(147));
    for row in &rows {
        let try_ms = row["region_median_try_ms"]
            .as_f64()
            .expect("a region try time");
        assert!(try_ms.is_finite() && try_ms > 0.0, "{row}");
        assert!(
            row["region_try_ratio"].as_f64().is_some_and(|r| r > 0.0),
            "{row}"
        );
    }

    let missing = dir.path().join("missing.obj");
    let run = bench(&[missing.to_str().expect("utf-8 path")]);
    assert_eq!(run.status.code(), Some(2));
    assert!(run.stdout.is_empty(), "a row was measured before the error");
    assert!(String::from_utf8_lossy(&run.stderr).contains("missing.obj: not a file"));
}

#[test]
fn paper_options_reach_the_flow() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run = |extra: &[&str]| {
        willow()
            .args(["fair", &spot(), "-o"])
            .arg(dir.path().join("o.obj"))
            .args(["--steps", "1", "--json"])
            .args(extra)
            .output()
            .expect("run willow")
    };
    let plain = run(&[]);
    let filtered = run(&["--filter-sigma", "0.01", "--filter-k", "2", "--mobius"]);
    assert!(plain.status.success() && filtered.status.success());
    // The filter changes the step: the reported energies differ.
    let w = |out: &std::process::Output| -> f64 {
        let lines = json_lines(out);
        assert_eq!(lines.len(), 1, "one step");
        lines[0]["willmore_energy"].as_f64().unwrap_or(f64::NAN)
    };
    assert!(
        (w(&plain) - w(&filtered)).abs() > 1e-6 * w(&plain),
        "filter had no effect"
    );
    // A bad filter order is refused with the reason.
    let bad = run(&["--filter-sigma", "0.01", "--filter-k", "7"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("filter"));
    // --filter-sigma alone is a usage error.
    let alone = run(&["--filter-sigma", "0.01"]);
    assert_eq!(alone.status.code(), Some(2));
    // A closed surface ignores --boundary fixed (it has no boundary) and still flows.
    assert!(run(&["--boundary", "fixed", "--no-exactness"])
        .status
        .success());
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

#[test]
fn prescribed_and_cmc_boundaries_from_the_command_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("tube.obj");
    std::fs::write(&input, tube_obj()).expect("write tube");
    let run = |extra: &[&str]| {
        willow()
            .arg("fair")
            .arg(&input)
            .arg("-o")
            .arg(dir.path().join("o.obj"))
            .args(["--steps", "2", "--json"])
            .args(extra)
            .output()
            .expect("run willow")
    };
    for extra in [
        &["--boundary", "cmc"][..],
        &[
            "--boundary",
            "prescribed",
            "--boundary-axis",
            "1,0,0",
            "--boundary-rotation",
            "0.2,-0.2",
            "--frame-angle",
            "-0.3",
        ][..],
    ] {
        let out = run(extra);
        assert!(
            out.status.success(),
            "{extra:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        // Two steps and the outcome line.
        assert_eq!(String::from_utf8_lossy(&out.stdout).lines().count(), 3);
    }
    for (extra, needle) in [
        (
            &["--boundary", "prescribed", "--frame-angle", "1.6"][..],
            "frame_angle",
        ),
        (
            &["--boundary", "prescribed", "--boundary-axis", "up"][..],
            "--boundary-axis",
        ),
        (
            &["--boundary", "prescribed", "--boundary-rotation", "1,2,3"][..],
            "gives 3 angle(s) but the mesh has 2 boundary loop(s)",
        ),
    ] {
        let out = run(extra);
        assert_eq!(out.status.code(), Some(2), "{extra:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{extra:?}: {err}");
    }
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

/// Each JSON line reports the τ its step used and its rejected tries: the requested τ and 0
/// on an easy mesh, with the safeguard on (the default) or off.
#[test]
fn json_lines_report_tau_and_rejected_tries_with_and_without_the_safeguard() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("bumpy.obj");
    std::fs::write(&input, bumpy_obj()).expect("write mesh");
    for extra in [&[][..], &["--no-safeguard"][..]] {
        let out = willow()
            .arg("fair")
            .arg(&input)
            .arg("-o")
            .arg(dir.path().join("o.obj"))
            .args(["--steps", "3", "--tau", "0.5", "--json"])
            .args(extra)
            .output()
            .expect("run willow");
        assert!(
            out.status.success(),
            "{extra:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let lines = json_lines(&out);
        assert_eq!(lines.len(), 3, "{extra:?}");
        for line in &lines {
            assert_eq!(line["tau"].as_f64(), Some(0.5), "{extra:?}: {line}");
            assert_eq!(line["rejected"].as_u64(), Some(0), "{extra:?}: {line}");
        }
    }
}

/// Implicit MCF at τ = 1000 on the bumpy sphere: steps 1 and 2 are kept, and no τ down to
/// 1000/1024 keeps W from rising at step 3 (the library's safeguard gives up with
/// `NoProgress`). The CLI writes the surface after step 2 (the same bytes as frame 2), names
/// the reason on stderr and exits with 3.
#[test]
fn no_progress_writes_the_last_good_mesh_and_exits_3() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("bumpy.obj");
    std::fs::write(&input, bumpy_obj()).expect("write mesh");
    let output = dir.path().join("out.obj");
    let frames = dir.path().join("frames");
    let out = willow()
        .arg("fair")
        .arg(&input)
        .arg("-o")
        .arg(&output)
        .args(["--steps", "6", "--method", "mcf", "--tau", "1000", "--json"])
        .arg("--frames-dir")
        .arg(&frames)
        .output()
        .expect("run willow");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "stderr: {stderr}");
    assert!(
        stderr.contains("no progress at step 3") && stderr.contains("Willmore energy would rise"),
        "the reason is named: {stderr}"
    );
    let lines = json_lines(&out);
    assert_eq!(lines.len(), 2, "steps 1 and 2 were kept");
    assert_eq!(outcome(&out)["outcome"], "no_progress");
    for line in &lines {
        assert_eq!(line["tau"].as_f64(), Some(1000.0), "{line}");
        assert_eq!(line["rejected"].as_u64(), Some(0), "{line}");
    }
    let written = std::fs::read(&output).expect("the output is written");
    let frame2 = std::fs::read(frames.join("frame_0002.obj")).expect("frame 2");
    assert_eq!(written, frame2, "the output is the last accepted surface");
    assert!(!frames.join("frame_0003.obj").exists());
    let text = String::from_utf8_lossy(&written);
    let coords: Vec<f64> = text
        .lines()
        .filter(|l| l.starts_with("v "))
        .flat_map(|l| {
            l.split_whitespace()
                .skip(1)
                .map(|c| c.parse().unwrap_or(f64::NAN))
        })
        .collect();
    assert_eq!(coords.len(), 3 * 162);
    assert!(coords.iter().all(|c| c.is_finite()));
}

/// The stopping rules from the command line: `--until-willmore` ends `target_reached` at the
/// first step at or below the target, `--max-deviation` keeps every reported step (and the
/// output) within the bound, `--preserve volume` keeps the volume; bad values are refused
/// naming the flag.
#[test]
fn fair_stops_on_its_rules_and_names_a_bad_flag() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("bumpy.obj");
    std::fs::write(&input, bumpy_obj()).expect("write mesh");
    let run = |extra: &[&str]| {
        willow()
            .arg("fair")
            .arg(&input)
            .arg("-o")
            .arg(dir.path().join("o.obj"))
            .arg("--json")
            .args(extra)
            .output()
            .expect("run willow")
    };
    let target = 20.0;
    let out = run(&[
        "--steps",
        "40",
        "--until-willmore",
        "20",
        "--preserve",
        "volume",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let end = outcome(&out);
    assert_eq!(end["outcome"], "target_reached", "{end}");
    assert!(end["reason"]
        .as_str()
        .is_some_and(|r| r.contains("until_willmore")));
    let lines = json_lines(&out);
    assert!(lines.len() >= 2, "{} steps", lines.len());
    let w = |l: &serde_json::Value| l["willmore_energy"].as_f64().unwrap_or(f64::NAN);
    assert!(w(&lines[lines.len() - 1]) <= target);
    assert!(lines[..lines.len() - 1].iter().all(|l| w(l) > target));
    let v0 = lines[0]["volume"].as_f64().unwrap_or(f64::NAN);
    for l in &lines {
        let v = l["volume"].as_f64().unwrap_or(f64::NAN);
        assert!((v / v0 - 1.0).abs() < 1e-6, "volume {v} vs {v0}");
    }

    // A bound between the distances after steps 1 and 2 of the free run: step 1 only.
    let free = json_lines(&run(&["--steps", "2", "--measure-deviation"]));
    let d = |l: &serde_json::Value| l["deviation_max"].as_f64().unwrap_or(f64::NAN);
    let bound = 0.5 * (d(&free[0]) + d(&free[1]));
    let out = run(&["--steps", "40", "--max-deviation", &bound.to_string()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(outcome(&out)["outcome"], "max_deviation");
    let lines = json_lines(&out);
    assert_eq!(lines.len(), 1);
    assert!(d(&lines[0]) <= bound);

    for (extra, flag) in [
        (&["--max-deviation", "-1"][..], "--max-deviation"),
        (&["--until-willmore", "nan"][..], "--until-willmore"),
        (&["--preserve", "mass"][..], "--preserve"),
    ] {
        let out = run(extra);
        assert_eq!(out.status.code(), Some(2), "{extra:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(flag), "{extra:?}: {err}");
        assert!(out.stdout.is_empty(), "{extra:?}: nothing ran");
    }
}

/// `--region-sphere` and `--region-vertices` fair spot's ear alone: every `v` line outside is
/// written back to the bit, and the outcome line closes the run; bad region flags exit 2
/// naming the flag or the region.
#[test]
fn fair_moves_only_the_named_region() {
    let dir = tempfile::tempdir().expect("tempdir");
    let v_lines = |text: &str| -> Vec<[f64; 3]> {
        text.lines()
            .filter_map(|l| l.strip_prefix("v "))
            .map(|l| {
                let c: Vec<f64> = l
                    .split_whitespace()
                    .map(|t| t.parse().expect("a number"))
                    .collect();
                [c[0], c[1], c[2]]
            })
            .collect()
    };
    let input = v_lines(&std::fs::read_to_string(spot()).expect("spot"));
    let (c, r) = ([0.40, 0.72, -0.20], 0.15);
    let in_ear = |p: &[f64; 3]| (0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f64>() <= r * r;
    let ear: Vec<String> = (0..input.len())
        .filter(|&k| in_ear(&input[k]))
        .map(|k| k.to_string())
        .collect();
    let list = dir.path().join("ear.txt");
    std::fs::write(&list, ear.join("\n")).expect("write list");
    let out = dir.path().join("out.obj");
    let sphere = format!("{},{},{},{r}", c[0], c[1], c[2]);
    for region in [
        vec!["--region-sphere", sphere.as_str()],
        vec![
            "--region-vertices",
            list.to_str().expect("utf-8"),
            "--seam",
            "fixed",
        ],
    ] {
        let run = willow()
            .args(["fair", &spot(), "-o"])
            .arg(&out)
            .args(["--steps", "3", "--json"])
            .args(&region)
            .output()
            .expect("run willow");
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let stdout = String::from_utf8_lossy(&run.stdout);
        let last: serde_json::Value =
            serde_json::from_str(stdout.lines().last().expect("lines")).expect("json");
        assert!(last["outcome"].is_string(), "{last}");
        let output = v_lines(&std::fs::read_to_string(&out).expect("out"));
        let mut moved = 0;
        for (p, q) in input.iter().zip(&output) {
            if in_ear(p) {
                moved += usize::from(p != q);
            } else {
                assert_eq!(p.map(f64::to_bits), q.map(f64::to_bits), "{region:?}");
            }
        }
        assert!(moved > 10, "{region:?}: {moved} moved");
    }
    for (flags, needle) in [
        (vec!["--region-sphere", "1,2,3"], "--region-sphere"),
        (vec!["--seam", "wavy"], "--seam"),
        (vec!["--region-sphere", "100,0,0,0.1"], "region"),
    ] {
        let run = willow()
            .args(["fair", &spot(), "-o"])
            .arg(&out)
            .args(&flags)
            .output()
            .expect("run willow");
        assert_eq!(run.status.code(), Some(2), "{flags:?}");
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(err.contains(needle), "{flags:?}: {err}");
    }
}

/// `--feature-size` on a 2:1:1 ellipsoid (icosphere level 5) carrying bumps 0.13 across: the
/// run ends by itself `feature_scale_reached`, the extents keep 2:1:1 within 5%, and a bad
/// length is refused naming the flag.
#[test]
fn fair_removes_detail_below_the_feature_size() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("ellipsoid.obj");
    let mut mesh = willow::mesh::generate::icosphere(5);
    for p in &mut mesh.positions {
        let e = [2.0 * p[0], p[1], p[2]];
        let r = 1.0 + 0.02 * (24.0 * e[0]).sin() * (24.0 * e[1]).sin() * (24.0 * e[2]).sin();
        *p = [e[0] * r, e[1] * r, e[2] * r];
    }
    let mut text = String::new();
    for p in &mesh.positions {
        text += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    for t in &mesh.triangles {
        text += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    std::fs::write(&input, text).expect("write mesh");
    let output = dir.path().join("out.obj");
    let run = |extra: &[&str]| {
        willow()
            .arg("fair")
            .arg(&input)
            .arg("-o")
            .arg(&output)
            .args(["--json", "--steps", "40"])
            .args(extra)
            .output()
            .expect("run willow")
    };
    let out = run(&["--feature-size", "0.2"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let end = outcome(&out);
    assert_eq!(end["outcome"], "feature_scale_reached", "{end}");
    assert!(json_lines(&out).len() < 40);
    let written: Vec<[f64; 3]> = std::fs::read_to_string(&output)
        .expect("output")
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let c: Vec<f64> = l
                .split_whitespace()
                .filter_map(|t| t.parse().ok())
                .collect();
            [c[0], c[1], c[2]]
        })
        .collect();
    let extent = |axis: usize| {
        let (lo, hi) = written.iter().fold((f64::MAX, f64::MIN), |(lo, hi), q| {
            (lo.min(q[axis]), hi.max(q[axis]))
        });
        hi - lo
    };
    let ratio = extent(0) / (0.5 * (extent(1) + extent(2)));
    assert!((ratio / 2.0 - 1.0).abs() < 0.05, "elongation {ratio}");
    for bad in ["0", "-1", "nan"] {
        let out = run(&["--feature-size", bad]);
        assert_eq!(out.status.code(), Some(2), "{bad}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("--feature-size"), "{bad}: {err}");
    }
    let out = run(&["--feature-size", "0.2", "--method", "mcf"]);
    assert_eq!(out.status.code(), Some(2));
}

/// `--region-group` fairs the faces under an OBJ `g` name (here spot's ear, grouped in the
/// test) and keeps every other `v` line to the bit; `--falloff` blends a region's motion;
/// an unknown group and a falloff without a region exit 2 naming the flag.
#[test]
fn fair_a_named_group_with_a_falloff() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = std::fs::read_to_string(spot()).expect("spot");
    let (c, r) = ([0.40, 0.72, -0.20], 0.15);
    let in_ear = |p: &[f64; 3]| (0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f64>() <= r * r;
    let mut v: Vec<[f64; 3]> = Vec::new();
    let (mut head, mut ear, mut body) = (String::new(), String::new(), String::new());
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("v ") {
            let p: Vec<f64> = rest
                .split_whitespace()
                .filter_map(|t| t.parse().ok())
                .collect();
            v.push([p[0], p[1], p[2]]);
            head += &format!("{line}\n");
        } else if let Some(rest) = line.strip_prefix("f ") {
            let inside = rest.split_whitespace().all(|w| {
                let k: usize = w
                    .split('/')
                    .next()
                    .and_then(|i| i.parse().ok())
                    .unwrap_or(0);
                in_ear(&v[k - 1])
            });
            *(if inside { &mut ear } else { &mut body }) += &format!("{line}\n");
        } else {
            head += &format!("{line}\n");
        }
    }
    let input = dir.path().join("grouped.obj");
    std::fs::write(&input, format!("{head}g ear\n{ear}g body\n{body}")).expect("write");
    let output = dir.path().join("out.obj");
    let run = |extra: &[&str]| {
        willow()
            .arg("fair")
            .arg(&input)
            .arg("-o")
            .arg(&output)
            .args(["--json", "--steps", "3"])
            .args(extra)
            .output()
            .expect("run willow")
    };
    for extra in [
        vec!["--region-group", "ear"],
        vec!["--region-group", "ear", "--falloff", "0.05"],
    ] {
        let out = run(&extra);
        assert!(
            out.status.success(),
            "{extra:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(outcome(&out)["outcome"].is_string());
        let written: Vec<[f64; 3]> = std::fs::read_to_string(&output)
            .expect("output")
            .lines()
            .filter_map(|l| l.strip_prefix("v "))
            .map(|l| {
                let c: Vec<f64> = l
                    .split_whitespace()
                    .filter_map(|t| t.parse().ok())
                    .collect();
                [c[0], c[1], c[2]]
            })
            .collect();
        assert_eq!(written.len(), v.len());
        let mut moved = 0;
        for (p, q) in v.iter().zip(&written) {
            if in_ear(p) {
                moved += usize::from(p != q);
            } else {
                assert_eq!(p.map(f64::to_bits), q.map(f64::to_bits), "{extra:?}");
            }
        }
        assert!(moved > 10, "{extra:?}: {moved} moved");
    }
    for (extra, needles) in [
        (
            vec!["--region-group", "tail"],
            vec!["--region-group", "`tail`", "`ear`"],
        ),
        (vec!["--falloff", "0.05"], vec!["--falloff", "region"]),
        (
            vec!["--region-group", "ear", "--falloff", "-1"],
            vec!["--falloff"],
        ),
    ] {
        let out = run(&extra);
        assert_eq!(out.status.code(), Some(2), "{extra:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        for n in needles {
            assert!(err.contains(n), "{extra:?}: {err} lacks {n}");
        }
    }
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
            .arg("fair")
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
        c.arg("fair")
            .arg(&input)
            .arg("-o")
            .arg(&out)
            .args(["--steps", "2"]);
        if repair {
            c.arg("--repair");
        }
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
