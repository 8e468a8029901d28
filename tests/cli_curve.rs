//! `willow curve`: the isometric curve flow (§5) from the command line, run as the real binary.

use std::path::Path;
use std::process::{Command, Output};
use willow::curve::{curvature_std_over_mean, dual_lengths, Curve};

fn willow() -> Command {
    Command::new(env!("CARGO_BIN_EXE_willow"))
}

/// A closed curve far from round: r = 1 + 0.2 sin 5t plus deterministic radial jitter.
fn noisy_closed_curve(n: usize) -> Vec<[f64; 2]> {
    (0..n)
        .map(|i| {
            let t = i as f64 * std::f64::consts::TAU / n as f64;
            let jitter = 0.01 * ((i as f64 * 12.9898).sin() * 43758.5453).fract();
            let r = 1.0 + 0.2 * (5.0 * t).sin() + jitter;
            [r * t.cos(), r * t.sin()]
        })
        .collect()
}

fn roundness(curve: &Curve) -> f64 {
    let mut dual = vec![0.0; curve.points.len()];
    dual_lengths(&curve.edge_lengths(), curve.closed, &mut dual);
    curvature_std_over_mean(&curve.curvature(), &dual)
}

fn run_curve(input: &Path, output: &Path, extra: &[&str]) -> Output {
    willow()
        .arg("curve")
        .arg(input)
        .arg("-o")
        .arg(output)
        .args(extra)
        .output()
        .expect("run willow")
}

fn stderr(run: &Output) -> String {
    String::from_utf8_lossy(&run.stderr).into_owned()
}

#[test]
fn noisy_closed_json_curve_comes_out_round_with_its_lengths() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("noisy.json");
    let output = dir.path().join("round.json");
    let curve = Curve::new(noisy_closed_curve(256), true).expect("valid curve");
    std::fs::write(&input, curve.to_json()).expect("write input");
    assert!(
        roundness(&curve) > 1.0,
        "the input must be far from round: {}",
        roundness(&curve)
    );

    let run = run_curve(&input, &output, &["--steps", "8", "--tau", "0.5", "--json"]);
    assert!(run.status.success(), "stderr: {}", stderr(&run));
    let stdout = String::from_utf8(run.stdout).expect("utf-8");
    let lines: Vec<serde_json::Value> = stdout
        .lines()
        .map(|l| serde_json::from_str(l).expect("each line is JSON"))
        .collect();
    assert_eq!(lines.len(), 8, "one JSON object per step");
    for (i, line) in lines.iter().enumerate() {
        assert_eq!(line["step"].as_u64(), Some(i as u64 + 1), "{line}");
        for key in [
            "energy",
            "curvature_std_over_mean",
            "max_edge_length_distortion",
            "closure_gap",
            "poisson_residual",
            "total_length",
            "total_curvature",
            "step_ms",
        ] {
            assert!(line[key].as_f64().is_some(), "missing {key} in {line}");
        }
    }

    let out = Curve::from_json(&std::fs::read(&output).expect("output written")).expect("parse");
    assert!(out.closed, "a closed curve stays closed");
    assert_eq!(out.points.len(), curve.points.len());
    let r = roundness(&out);
    assert!(r < 1e-2, "curvature std/mean {r} after 8 steps");
    let reported = lines[7]["curvature_std_over_mean"]
        .as_f64()
        .unwrap_or(f64::NAN);
    assert!(reported < 1e-2, "reported std/mean {reported}");
    // Isometric: every edge keeps its length (Figure 11), hence the total length too.
    let worst = curve
        .edge_lengths()
        .iter()
        .zip(out.edge_lengths())
        .map(|(a, b)| (b / a - 1.0).abs())
        .fold(0.0, f64::max);
    assert!(worst < 1e-2, "edge length distortion {worst}");
    assert!(
        (out.length() / curve.length() - 1.0).abs() < 1e-3,
        "length {} -> {}",
        curve.length(),
        out.length()
    );
}

#[test]
fn obj_polyline_in_obj_out() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = dir.path().join("noisy.obj");
    let output = dir.path().join("round.obj");
    let curve = Curve::new(noisy_closed_curve(128), true).expect("valid curve");
    std::fs::write(&input, curve.to_obj()).expect("write input");
    let run = run_curve(&input, &output, &["--steps", "6"]);
    assert!(run.status.success(), "stderr: {}", stderr(&run));
    assert!(run.stdout.is_empty(), "no JSON without --json");
    let out = Curve::from_obj(&std::fs::read(&output).expect("output written")).expect("parse");
    assert!(out.closed);
    assert!(roundness(&out) < 1e-2, "std/mean {}", roundness(&out));
}

#[test]
fn bad_input_exits_2_with_the_specific_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let output = dir.path().join("out.json");
    let cases: [(&str, &str, &[&str], &str); 6] = [
        // Point 2 repeats point 1: edge 1 has zero length.
        (
            "repeat.json",
            r#"{"points": [[0, 0], [1, 0], [1, 0], [0, 1]], "closed": true}"#,
            &[],
            "edge 1",
        ),
        (
            "two.json",
            r#"{"points": [[0, 0], [1, 0]], "closed": true}"#,
            &[],
            "at least 3 points",
        ),
        ("garbage.json", "not json", &[], "invalid JSON curve"),
        (
            "mesh.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
            &[],
            "invalid OBJ curve",
        ),
        (
            "curve.txt",
            r#"{"points": [[0, 0], [1, 0], [0, 1]], "closed": true}"#,
            &[],
            "unknown extension",
        ),
        (
            "tau.json",
            r#"{"points": [[0, 0], [1, 0], [0, 1]], "closed": true}"#,
            &["--tau", "1.5"],
            "invalid parameter `tau`",
        ),
    ];
    for (name, text, extra, expected) in cases {
        let input = dir.path().join(name);
        std::fs::write(&input, text).expect("write input");
        let run = run_curve(&input, &output, extra);
        assert_eq!(run.status.code(), Some(2), "{name}: {}", stderr(&run));
        assert!(
            stderr(&run).contains(expected),
            "{name}: expected `{expected}` in: {}",
            stderr(&run)
        );
        assert!(!output.exists(), "{name}: no output on error");
    }
    let missing = dir.path().join("missing.json");
    let run = run_curve(&missing, &output, &[]);
    assert_eq!(run.status.code(), Some(2));
    assert!(stderr(&run).contains("cannot read"), "{}", stderr(&run));
}
