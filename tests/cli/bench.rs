//! `willow bench`: its figures, its order, its refusals.

use super::*;

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
