//! The flow's options from the command line: the paper's options, boundary conditions, the
//! step safeguard, the stopping rules.

use super::*;

#[test]
fn paper_options_reach_the_flow() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run = |extra: &[&str]| {
        willow()
            .args(["fair", "--method", "conformal", &spot(), "-o"])
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

#[test]
fn prescribed_and_cmc_boundaries_from_the_command_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("tube.obj");
    std::fs::write(&input, tube_obj()).expect("write tube");
    let run = |extra: &[&str]| {
        willow()
            .args(["fair", "--method", "conformal"])
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

/// Each JSON line reports the τ its step used and its rejected tries: the requested τ and 0
/// on an easy mesh, with the safeguard on (the default) or off.
#[test]
fn json_lines_report_tau_and_rejected_tries_with_and_without_the_safeguard() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("bumpy.obj");
    std::fs::write(&input, bumpy_obj()).expect("write mesh");
    for extra in [&[][..], &["--no-safeguard"][..]] {
        let out = willow()
            .args(["fair", "--method", "conformal"])
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
        .args(["fair", "--method", "conformal"])
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
            .args(["fair", "--method", "conformal"])
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
