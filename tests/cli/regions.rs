//! Local fairing from the command line: regions, the feature size, OBJ groups and falloff.

use super::*;

/// The `v` lines of an OBJ text, in order: the file's vertex numbering.
fn v_lines(text: &str) -> Vec<[f64; 3]> {
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
}

/// `--region-sphere` and `--region-vertices` fair spot's ear alone: every `v` line outside is
/// written back to the bit, and the outcome line closes the run; bad region flags exit 2
/// naming the flag or the region.
#[test]
fn fair_moves_only_the_named_region() {
    let dir = tempfile::tempdir().expect("tempdir");
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
            .args(["fair", "--method", "conformal", &spot(), "-o"])
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
            .args(["fair", "--method", "conformal", &spot(), "-o"])
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
            .args(["fair", "--method", "conformal"])
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
    let written = v_lines(&std::fs::read_to_string(&output).expect("output"));
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
            .args(["fair", "--method", "conformal"])
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

/// `--feature-angle`: a chamfered cylinder's four crease rings are held by the conformal flow
/// (every crease vertex written back to the bit, `crease_edges` on every JSON line); `none`
/// fairs across them; an angle out of range or a word is refused, exit 2, naming the flag.
#[test]
fn fair_keeps_the_creases_of_a_part() {
    let dir = tempfile::tempdir().expect("tempdir");
    let part = willow::mesh::generate::chamfered_cylinder(0.1, 64);
    let mut text = String::new();
    for p in &part.positions {
        text += &format!("v {:?} {:?} {:?}\n", p[0], p[1], p[2]);
    }
    for t in &part.triangles {
        text += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    let input = dir.path().join("part.obj");
    std::fs::write(&input, text).expect("write part");
    let out = dir.path().join("out.obj");
    let run = |angle: &str| {
        willow()
            .args(["fair", input.to_str().expect("utf-8"), "-o"])
            .arg(&out)
            .args(["--method", "conformal", "--tau", "0.05", "--steps", "3"])
            .args(["--all-steps", "--json", "--feature-angle", angle])
            .output()
            .expect("run willow")
    };
    let held = run("auto");
    assert!(
        held.status.success(),
        "{}",
        String::from_utf8_lossy(&held.stderr)
    );
    let lines = json_lines(&held);
    assert!(!lines.is_empty(), "{:?}", outcome(&held));
    assert!(
        lines.iter().all(|l| l["crease_edges"] == 4 * 64),
        "{lines:?}"
    );
    // The output's `v` lines, in the file's numbering (the input's: the generator's).
    let now = v_lines(&std::fs::read_to_string(&out).expect("output"));
    assert_eq!(now.len(), part.vertex_count());
    let topology = willow::mesh::topology::Topology::new(&part);
    let creases = willow::mesh::creases::detect_creases(
        &part.positions,
        &part.triangles,
        &topology,
        willow::mesh::creases::FeatureAngle::Auto,
    );
    let kept = (0..part.vertex_count())
        .filter(|&v| creases.vertices[v])
        .all(|v| now[v] == part.positions[v]);
    assert!(kept, "every crease vertex is written back as it was");

    let across = run("none");
    assert!(across.status.success());
    assert!(json_lines(&across)
        .iter()
        .all(|l| l.get("crease_edges").is_none()));
    for bad in ["180", "sharp"] {
        let refused = run(bad);
        assert_eq!(refused.status.code(), Some(2), "--feature-angle {bad}");
        let stderr = String::from_utf8_lossy(&refused.stderr);
        assert!(
            stderr.contains("feature-angle") || stderr.contains("feature_angle"),
            "{bad}: {stderr}"
        );
    }
}
