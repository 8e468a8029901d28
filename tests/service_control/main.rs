//! The shape controls and stopping rules over HTTP and gRPC: `preserve`, `measure_deviation`,
//! `max_deviation`, `until_willmore`, `until_converged`, and the outcome every succeeded job
//! reports. Volumes and distances are checked against computations in this file, not the
//! server's own.

#[path = "../service_http_support/mod.rs"]
mod service_http_support;

use service_http_support::*;
use std::time::Duration;
use willow::mesh::{generate, Mesh};

const JOB_TIMEOUT: Duration = Duration::from_secs(120);

fn bumpy() -> Mesh {
    generate::bumpy_sphere(3, 0.15)
}

/// Submits `obj` with `params` as the multipart JSON part.
async fn submit_json(srv: &TestServer, obj: &str, params: &serde_json::Value) -> reqwest::Response {
    // These tests drive the conformal flow: a params object that names no method asks for it
    // (the default method, `denoise`, has tests of its own).
    let mut params = params.clone();
    if let Some(map) = params.as_object_mut() {
        map.entry("method").or_insert_with(|| "conformal".into());
    }
    let form = reqwest::multipart::Form::new()
        .part(
            "mesh",
            reqwest::multipart::Part::text(obj.to_string()).file_name("m.obj"),
        )
        .text("params", params.to_string());
    srv.client
        .post(srv.url("/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .expect("send")
}

/// Submits `obj` with `params` as the multipart JSON part and waits for it to end.
async fn run_json(srv: &TestServer, obj: &str, params: serde_json::Value) -> serde_json::Value {
    let res = submit_json(srv, obj, &params).await;
    assert_eq!(
        res.status(),
        202,
        "{}",
        res.text().await.unwrap_or_default()
    );
    let job: serde_json::Value = res.json().await.expect("json");
    let id = job["id"].as_str().expect("id").to_string();
    srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await
}

async fn frames(srv: &TestServer, id: &str) -> Vec<serde_json::Value> {
    let (st, v) = srv.get_json(&format!("/v1/jobs/{id}/frames")).await;
    assert_eq!(st, 200, "{v}");
    v["frames"].as_array().expect("frames").clone()
}

async fn result_positions(srv: &TestServer, id: &str) -> Vec<[f64; 3]> {
    let text = srv
        .client
        .get(srv.url(&format!("/v1/jobs/{id}/result?format=obj")))
        .send()
        .await
        .expect("GET result")
        .text()
        .await
        .expect("body");
    obj_vertices(&text)
}

fn num(v: &serde_json::Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("a number, got {v}"))
}

/// Enclosed volume by the divergence theorem: Σ p0 · (p1 × p2) / 6.
fn volume(p: &[[f64; 3]], triangles: &[[usize; 3]]) -> f64 {
    triangles
        .iter()
        .map(|t| {
            let (a, b, c) = (p[t[0]], p[t[1]], p[t[2]]);
            let cross = [
                b[1] * c[2] - b[2] * c[1],
                b[2] * c[0] - b[0] * c[2],
                b[0] * c[1] - b[1] * c[0],
            ];
            (a[0] * cross[0] + a[1] * cross[1] + a[2] * cross[2]) / 6.0
        })
        .sum()
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Distance from `p` to triangle `abc`, by the Voronoi regions of its vertices, edges and face
/// (Ericson, Real-Time Collision Detection §5.1.5).
fn point_triangle(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    let at = |s: f64, t: f64| {
        let q = [
            a[0] + s * ab[0] + t * ac[0],
            a[1] + s * ab[1] + t * ac[1],
            a[2] + s * ab[2] + t * ac[2],
        ];
        dot(sub(p, q), sub(p, q)).sqrt()
    };
    if d1 <= 0.0 && d2 <= 0.0 {
        return at(0.0, 0.0);
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return at(1.0, 0.0);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return at(d1 / (d1 - d3), 0.0);
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return at(0.0, 1.0);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return at(0.0, d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return at(1.0 - w, w);
    }
    let denom = 1.0 / (va + vb + vc);
    at(vb * denom, vc * denom)
}

/// The largest distance from a vertex of one surface to the other surface, both ways (brute
/// force): a lower bound of the two-sided distance the server samples more densely.
fn vertex_hausdorff(a: &[[f64; 3]], b: &[[f64; 3]], triangles: &[[usize; 3]]) -> f64 {
    let one_way = |from: &[[f64; 3]], to: &[[f64; 3]]| {
        from.iter()
            .map(|&p| {
                triangles
                    .iter()
                    .map(|t| point_triangle(p, to[t[0]], to[t[1]], to[t[2]]))
                    .fold(f64::INFINITY, f64::min)
            })
            .fold(0.0, f64::max)
    };
    one_way(a, b).max(one_way(b, a))
}

/// `preserve: volume` keeps the enclosed volume at every frame and in the result; a flow
/// that settles ends `converged` before its steps, with a reason; frames carry the distance.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn volume_is_kept_and_a_settling_flow_ends_converged() {
    let srv = start(|_| {}).await;
    let mesh = bumpy();
    let v0 = volume(&mesh.positions, &mesh.triangles);
    let done = run_json(
        &srv,
        &obj_text(&mesh),
        serde_json::json!({"steps": 60, "preserve": "volume", "measure_deviation": true}),
    )
    .await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["outcome"], "converged", "{done}");
    assert!(done["outcome_reason"]
        .as_str()
        .is_some_and(|r| r.contains("changed by less than")));
    assert_eq!(done["params"]["preserve"], "volume");
    let id = done["id"].as_str().expect("id");
    let steps = num(&done["progress"]["step"]) as usize;
    assert!(steps < 60, "converged at step {steps}");
    let frames = frames(&srv, id).await;
    assert_eq!(frames.len(), steps + 1);
    for f in &frames {
        let v = num(&f["volume"]);
        assert!(
            (v / v0 - 1.0).abs() < 1e-6,
            "step {}: volume {v} vs {v0}",
            f["step"]
        );
        let (max, mean) = (num(&f["deviation_max"]), num(&f["deviation_mean"]));
        assert!(0.0 <= mean && mean <= max, "{f}");
    }
    assert_eq!(num(&frames[0]["deviation_max"]), 0.0);
    // The SSE stream replays the frames, then `done` with the same outcome.
    let res = srv
        .client
        .get(srv.url(&format!("/v1/jobs/{id}/events")))
        .send()
        .await
        .expect("events");
    let events = read_sse(res, JOB_TIMEOUT).await;
    let last = events.last().expect("events");
    assert_eq!(last.event, "done");
    assert_eq!(last.data["outcome"], "converged", "{:?}", last.data);
    assert!(events
        .iter()
        .filter(|e| e.event == "frame")
        .all(|e| e.data["metrics"]["volume"].is_number() || e.data["volume"].is_number()));
    let out = result_positions(&srv, id).await;
    let v1 = volume(&out, &mesh.triangles);
    assert!((v1 / v0 - 1.0).abs() < 1e-6, "result volume {v1} vs {v0}");
    srv.stop().await;
}

/// `max_deviation` between the distances after steps 2 and 3 of the free flow: the job ends
/// `max_deviation` after step 2, no frame passes the bound, and the result's distance from the
/// input, measured here, is within the bound too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn max_deviation_ends_on_the_last_surface_within_the_bound() {
    let srv = start(|_| {}).await;
    let mesh = bumpy();
    let obj = obj_text(&mesh);
    let free = run_json(
        &srv,
        &obj,
        serde_json::json!({"steps": 5, "until_converged": false, "measure_deviation": true}),
    )
    .await;
    assert_eq!(free["outcome"], "completed", "{free}");
    let free_frames = frames(&srv, free["id"].as_str().expect("id")).await;
    let d: Vec<f64> = free_frames
        .iter()
        .map(|f| num(&f["deviation_max"]))
        .collect();
    assert!(d[2] < d[3], "the surface keeps moving away: {d:?}");
    let bound = 0.5 * (d[2] + d[3]);

    // The query string form this time.
    let (st, _, job) = srv
        .submit_obj(
            &obj,
            &format!("steps=5&until_converged=false&max_deviation={bound}"),
        )
        .await;
    assert_eq!(st, 202);
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["outcome"], "max_deviation", "{done}");
    assert_eq!(done["error_code"], "max_deviation");
    assert_eq!(num(&done["progress"]["step"]), 2.0);
    let bounded = frames(&srv, &id).await;
    assert_eq!(bounded.len(), 3);
    for f in &bounded {
        assert!(num(&f["deviation_max"]) <= bound, "{f}");
    }
    let out = result_positions(&srv, &id).await;
    let measured = vertex_hausdorff(&mesh.positions, &out, &mesh.triangles);
    let reported = num(&bounded[2]["deviation_max"]);
    assert!(measured <= bound, "measured {measured} > bound {bound}");
    assert!(
        measured <= reported * 1.02 && measured >= reported * 0.5,
        "measured {measured} vs reported {reported}"
    );
    srv.stop().await;
}

/// `until_willmore` stops at the first step at or below the target; `until_converged: false`
/// runs every step and ends `completed`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn until_willmore_ends_target_reached() {
    let srv = start(|_| {}).await;
    let obj = obj_text(&bumpy());
    let target = 4.0 * std::f64::consts::PI * 1.05;
    let done = run_json(
        &srv,
        &obj,
        serde_json::json!({"steps": 40, "until_willmore": target}),
    )
    .await;
    assert_eq!(done["outcome"], "target_reached", "{done}");
    let frames = frames(&srv, done["id"].as_str().expect("id")).await;
    let n = frames.len();
    assert!(num(&frames[n - 1]["willmore_energy"]) <= target);
    assert!(num(&frames[n - 2]["willmore_energy"]) > target);

    let done = run_json(
        &srv,
        &obj,
        serde_json::json!({"steps": 12, "until_converged": false}),
    )
    .await;
    assert_eq!(done["outcome"], "completed", "{done}");
    assert_eq!(done["outcome_reason"], "ran its 12 steps");
    assert_eq!(num(&done["progress"]["step"]), 12.0);
    assert!(done.get("error_code").is_none(), "{done}");
    srv.stop().await;
}

/// An OBJ of `mesh` with its faces in two groups, `top` (centroid above z = 0.3) and `rest`.
fn grouped_obj(mesh: &Mesh) -> String {
    let mut out = String::new();
    for p in &mesh.positions {
        out.push_str(&format!("v {} {} {}\n", p[0], p[1], p[2]));
    }
    let top = |t: &[usize; 3]| t.iter().map(|&v| mesh.positions[v][2]).sum::<f64>() / 3.0 > 0.3;
    for (name, want) in [("top", true), ("rest", false)] {
        out.push_str(&format!("g {name}\n"));
        for t in mesh.triangles.iter().filter(|t| top(t) == want) {
            out.push_str(&format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1));
        }
    }
    out
}

/// `region.group` names a group of the file's faces: only vertices of its faces move; an
/// unknown group is refused naming the file's groups. `feature_size` reaches the flow and the
/// job ends by itself with `feature_scale_reached`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_group_region_and_a_feature_size_reach_the_flow() {
    let srv = start(|_| {}).await;
    let mesh = bumpy();
    let obj = grouped_obj(&mesh);
    let (st, _, job) = srv
        .submit_obj(&obj, "steps=3&region.group=top&seam=fixed&falloff=0.1")
        .await;
    assert_eq!(st, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    assert_eq!(
        job["params"]["region"],
        serde_json::json!([{"group": "top"}])
    );
    assert_eq!(num(&job["params"]["falloff"]), 0.1);
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let out = result_positions(&srv, &id).await;
    let mut in_top = vec![false; mesh.positions.len()];
    for t in &mesh.triangles {
        if t.iter().map(|&v| mesh.positions[v][2]).sum::<f64>() / 3.0 > 0.3 {
            t.iter().for_each(|&v| in_top[v] = true);
        }
    }
    let mut moved = 0;
    for (k, (p, q)) in mesh.positions.iter().zip(&out).enumerate() {
        if in_top[k] {
            moved += usize::from(p != q);
        } else {
            assert_eq!(p.map(f64::to_bits), q.map(f64::to_bits), "vertex {k} moved");
        }
    }
    assert!(moved > 10, "{moved} vertices of the group moved");
    let (st, _, p) = srv.submit_obj(&obj, "region.group=ears").await;
    assert_eq!(st, 400, "{p}");
    assert_eq!(p["field"], "region");
    assert!(p["detail"]
        .as_str()
        .is_some_and(|d| d.contains("`top`") && d.contains("`rest`")));

    let done = run_json(
        &srv,
        &obj_text(&mesh),
        serde_json::json!({"steps": 60, "feature_size": 0.5}),
    )
    .await;
    assert_eq!(done["outcome"], "feature_scale_reached", "{done}");
    assert!(num(&done["progress"]["step"]) < 60.0);
    srv.stop().await;
}

/// A non-manifold upload with `repair=false` is refused naming the file's own vertex; by
/// default (and with `repair`) it is split, the answer says what changed, and the job runs. What changed is stored with the job: a
/// poll, and a poll after a restart, report it too; so are a glTF's notes (dropped morph
/// targets).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn repair_splits_a_bowtie_and_says_so() {
    let srv = start(|_| {}).await;
    let obj = bowtie_obj();
    let (st, _, p) = srv.submit_obj(&obj, "steps=2&repair=false").await;
    assert_eq!(st, 422, "{p}");
    assert!(
        p["detail"].as_str().is_some_and(|d| d.contains("line 1")),
        "names the file's line: {p}"
    );
    let (st, _, job) = srv.submit_obj(&obj, "steps=2&repair=true").await;
    assert_eq!(st, 202, "{job}");
    assert_eq!(job["params"]["repair"], true);
    let repairs = &job["repairs"];
    assert_eq!(repairs["split_vertices"]["count"], 1, "{repairs}");
    assert_eq!(num(&repairs["added_vertices"]), 1.0, "{repairs}");
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["repairs"], *repairs, "{done}");
    assert!(done.get("notes").is_none(), "{done}");
    // Repair is the default (issue 39: a scan with a few bowties is repaired with a note).
    let (st, _, by_default) = srv.submit_obj(&obj, "steps=2").await;
    assert_eq!(st, 202, "{by_default}");
    assert_eq!(by_default["repairs"], *repairs, "{by_default}");
    // A job whose file needs no repair reports none.
    let (_, _, plain) = srv.submit_obj(&small_obj(), "steps=1").await;
    assert!(plain.get("repairs").is_none(), "{plain}");
    let plain_id = plain["id"].as_str().expect("id").to_string();
    // A glTF with morph targets: the job notes that its result drops them.
    let res = reqwest::Client::new()
        .post(srv.url("/v1/jobs?steps=1"))
        .header("content-type", "model/gltf-binary")
        .body(morph_glb())
        .send()
        .await
        .expect("POST");
    assert_eq!(res.status(), 202);
    let morph: serde_json::Value = res.json().await.expect("job");
    let morph_id = morph["id"].as_str().expect("id").to_string();
    let noted = |v: &serde_json::Value| {
        v["notes"].as_array().is_some_and(|n| {
            n.iter().any(|n| {
                n.as_str()
                    .is_some_and(|n| n.starts_with("morph targets dropped"))
            })
        })
    };
    assert!(noted(&morph), "{morph}");
    srv.poll_until(&morph_id, JOB_TIMEOUT, is_terminal).await;
    srv.poll_until(&plain_id, JOB_TIMEOUT, is_terminal).await;

    let srv = start_in(srv.stop().await, |_| {}).await;
    let (st, after) = srv.get_json(&format!("/v1/jobs/{id}")).await;
    assert_eq!(st, 200);
    assert_eq!(after["repairs"], *repairs, "after a restart: {after}");
    let (_, after) = srv.get_json(&format!("/v1/jobs/{morph_id}")).await;
    assert!(noted(&after), "after a restart: {after}");
    let (_, after) = srv.get_json(&format!("/v1/jobs/{plain_id}")).await;
    assert!(
        after.get("repairs").is_none() && after.get("notes").is_none(),
        "{after}"
    );
    srv.stop().await;
}

/// Bad values are 400s naming the parameter, in JSON and in the query.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_controls_are_refused_naming_their_field() {
    let srv = start(|_| {}).await;
    let obj = small_obj();
    for (query, field) in [
        ("max_deviation=-1", "max_deviation"),
        ("until_willmore=nan", "until_willmore"),
        ("preserve=mass", "preserve"),
        ("method=taubin&preserve=volume", "preserve"),
        ("until_converged=maybe", "until_converged"),
        ("feature_size=0", "feature_size"),
        ("falloff=0.1", "falloff"),
        ("method=mcf&feature_size=1", "feature_size"),
    ] {
        let (st, _, p) = srv.submit_obj(&obj, query).await;
        assert_eq!(st, 400, "{query}: {p}");
        assert_eq!(p["field"], field, "{query}: {p}");
    }
    for (params, field) in [
        (serde_json::json!({"preserve": "mass"}), "preserve"),
        (serde_json::json!({"max_deviation": "far"}), "max_deviation"),
        (serde_json::json!({"until_wilmore": 3}), "until_wilmore"),
        (
            serde_json::json!({"filter": {"sigma": 1e-3, "k": 2, "x": 1}}),
            "filter.x",
        ),
    ] {
        let res = submit_json(&srv, &obj, &params).await;
        let st = res.status();
        let p: serde_json::Value = res.json().await.expect("problem json");
        assert_eq!(
            (st.as_u16(), p["field"].as_str()),
            (400, Some(field)),
            "{params}: {p}"
        );
    }
    srv.stop().await;
}

// ---------------------------------------------------------------------------------------------
// gRPC: the same parameters as JobParams fields 13-19, the outcome on the Job.

mod grpc;

/// A CAD cylinder with fan caps and UVs (the side unrolled, with a seam at angle 0; each cap
/// its own disc): too coarse to fair.
fn uv_cylinder_obj(n: usize) -> String {
    let mut s = String::new();
    for z in [-1.0, 1.0] {
        for i in 0..n {
            let a = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
            s += &format!("v {} {} {z}\n", a.cos(), a.sin());
        }
    }
    s += "v 0 0 -1\nv 0 0 1\n";
    // vt 1..=2(n+1): the side (column n repeats column 0: the seam); then the cap rim, then
    // the cap centre.
    for v in [0.0, 1.0] {
        for i in 0..=n {
            s += &format!("vt {} {v}\n", i as f64 / n as f64);
        }
    }
    for i in 0..n {
        let a = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
        s += &format!("vt {} {}\n", 0.5 + 0.5 * a.cos(), 0.5 + 0.5 * a.sin());
    }
    s += "vt 0.5 0.5\n";
    let side =
        |ring: usize, i: usize| format!("{}/{}", ring * n + i % n + 1, ring * (n + 1) + i + 1);
    let cap =
        |ring: usize, i: usize| format!("{}/{}", ring * n + i % n + 1, 2 * (n + 1) + i % n + 1);
    let centre = 2 * (n + 1) + n + 1;
    for i in 0..n {
        s += &format!("f {} {} {}\n", side(0, i), side(0, i + 1), side(1, i + 1));
        s += &format!("f {} {} {}\n", side(0, i), side(1, i + 1), side(1, i));
        s += &format!("f {}/{centre} {} {}\n", 2 * n + 1, cap(0, i + 1), cap(0, i));
        s += &format!("f {}/{centre} {} {}\n", 2 * n + 2, cap(1, i), cap(1, i + 1));
    }
    s
}

/// Issue 42 item 2: `refine`'s size is known from the upload and the target edge, so a plan
/// past the limits is refused at submission, before any level is built (413, `field:
/// refine`), and `refine_edge` is a real parameter: the levels it asks for are the ones made.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refine_edge_sets_the_levels_and_a_plan_past_the_limits_is_refused_before_work() {
    let srv = start(|_| {}).await;
    // A needle ellipsoid (the campaign's 12 KB stretched one): 80 · 4 = 320 triangles whose
    // long edges stay long.
    let mut needle = generate::icosphere(2);
    for p in &mut needle.positions {
        p[0] *= 40.0;
    }
    let obj = obj_text(&needle);
    let mean_edge = generate::mean_edge_length(&needle);
    // ⌈log₂(mean edge / target)⌉ = 20 levels: 320 · 4²⁰ triangles, were it built.
    let query = format!(
        "steps=1&refine=true&refine_edge={}",
        mean_edge / 1_000_000.0
    );
    let mut fastest = Duration::MAX;
    for _ in 0..3 {
        let t = std::time::Instant::now();
        let (st, _, body) = srv.submit_obj(&obj, &query).await;
        fastest = fastest.min(t.elapsed());
        assert_eq!(st, 413, "{body}");
        assert_eq!(body["field"], "refine", "{body}");
        assert_eq!(body["what"], "triangles", "{body}");
        assert_eq!(body["planned"].as_u64(), Some(320 * 4u64.pow(20)), "{body}");
        let detail = body["detail"].as_str().expect("detail");
        assert!(detail.contains("refine_edge"), "{detail}");
    }
    // Refused from the plan: no level was built (building one of 1.3M triangles and checking
    // it took over a second before).
    println!("refine refusal: {:.1} ms", fastest.as_secs_f64() * 1e3);
    assert!(fastest < Duration::from_millis(100), "{fastest:?}");

    // A target a third of the mean edge: ⌈log₂ 3⌉ = 2 levels, 16 children per triangle.
    let (st, _, job) = srv
        .submit_obj(
            &obj,
            &format!("steps=1&refine=true&refine_edge={}", mean_edge / 3.0),
        )
        .await;
    assert_eq!(st, 202, "{job}");
    assert_eq!(job["face_count"], 320 * 16, "{job}");
    assert_eq!(job["params"]["refine_edge"], mean_edge / 3.0, "{job}");

    for (query, words) in [
        ("steps=1&refine_edge=0.1", "refine: true"),
        ("steps=1&refine=true&refine_edge=-1", "> 0"),
        ("steps=1&refine=true&refine_edge=0", "> 0"),
    ] {
        let (st, _, body) = srv.submit_obj(&obj, query).await;
        assert_eq!(st, 400, "{query}: {body}");
        assert_eq!(body["field"], "refine_edge", "{query}: {body}");
        let detail = body["detail"].as_str().expect("detail");
        assert!(detail.contains(words), "{query}: {detail}");
    }
}

/// `refine` (issue 26 item 5): the job runs on the Loop-subdivided mesh, frame 0 says the
/// connectivity changed and carries the refined vertices (the file's own first), and the
/// result has the refined faces with the UVs interpolated.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refine_subdivides_a_coarse_cylinder_and_frame_zero_says_so() {
    let srv = start(|_| {}).await;
    let n = 16;
    // A material library, group and material: the refined result keeps them (obj/refined.rs).
    let kept = ["mtllib cylinder.mtl", "g body", "usemtl paint"];
    let obj = format!("{}\n{}", kept.join("\n"), uv_cylinder_obj(n));
    let upload_faces = 4 * n;
    let (st, _, job) = srv
        .submit_obj(&obj, "steps=2&refine=true&until_converged=false")
        .await;
    assert_eq!(st, 202, "{job}");
    assert_eq!(job["params"]["refine"], true);
    let vertex_count = job["vertex_count"].as_u64().expect("vertex_count") as usize;
    let face_count = job["face_count"].as_u64().expect("face_count") as usize;
    assert!(face_count >= 16 * upload_faces, "{job}");
    assert_eq!(
        face_count % upload_faces,
        0,
        "4^levels children per face: {job}"
    );
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");

    let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
    let events = read_sse(res, JOB_TIMEOUT).await;
    let frames: Vec<&Sse> = events.iter().filter(|e| e.event == "frame").collect();
    assert_eq!(frames[0].data["step"], 0);
    assert_eq!(
        frames[0].data["connectivity_changed"], true,
        "{:?}",
        frames[0]
    );
    assert!(frames[1..]
        .iter()
        .all(|f| f.data.get("connectivity_changed").is_none()));
    let b64 = frames[0].data["positions_b64"].as_str().expect("positions");
    let bytes =
        base64::Engine::decode(&base64::engine::general_purpose::STANDARD, b64).expect("base64");
    let frame0 = f32_triples(&bytes);
    assert_eq!(frame0.len(), vertex_count);

    // Frame 0's mesh and the result: the refined connectivity, UVs kept; the file's own
    // vertices first (the `v` lines hold frame 0's positions in order).
    for path in [
        format!("/v1/jobs/{id}/frames/0?format=obj"),
        format!("/v1/jobs/{id}/result?format=obj"),
    ] {
        let res = srv.get(&path).await;
        assert_eq!(res.status(), 200, "{path}");
        let text = res.text().await.expect("body");
        let faces: Vec<&str> = text.lines().filter(|l| l.starts_with("f ")).collect();
        assert_eq!(faces.len(), face_count, "{path}");
        assert!(faces
            .iter()
            .all(|f| f.split_whitespace().skip(1).all(|c| c.contains('/'))));
        let vts = text.lines().filter(|l| l.starts_with("vt ")).count();
        assert!(vts > 2 * (n + 1) + n + 1, "{path}: {vts} UVs");
        let head: Vec<&str> = text.lines().take_while(|l| !l.starts_with("f ")).collect();
        let statements: Vec<&str> = head.iter().copied().filter(|l| kept.contains(l)).collect();
        assert_eq!(statements, kept, "{path}");
        if path.contains("frames/0") {
            let v = obj_vertices(&text);
            assert_eq!(v.len(), vertex_count);
            for (a, b) in v.iter().zip(&frame0) {
                for k in 0..3 {
                    assert!((a[k] - b[k] as f64).abs() < 1e-5, "{a:?} vs {b:?}");
                }
            }
        }
    }
    srv.stop().await;
}

/// A UV-mapped latitude–longitude sphere (`n` around, `n / 2` down) with its north cap's fan
/// left out: one hole of `n` boundary vertices, every corner in one chart.
fn holed_uv_sphere_obj(n: usize) -> (String, usize, usize) {
    let rows = n / 2;
    let mut s = String::new();
    // Ring r (1..rows) at polar angle π r / rows; the south pole last. Seam column n repeats
    // column 0 in UV only.
    for r in 1..rows {
        let theta = std::f64::consts::PI * r as f64 / rows as f64;
        for i in 0..n {
            let phi = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
            s += &format!(
                "v {} {} {}\n",
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos()
            );
        }
    }
    s += "v 0 0 -1\n";
    let vertices = (rows - 1) * n + 1;
    for r in 1..rows {
        for i in 0..=n {
            s += &format!(
                "vt {} {}\n",
                i as f64 / n as f64,
                1.0 - r as f64 / rows as f64
            );
        }
    }
    s += "vt 0.5 0\n";
    let v = |r: usize, i: usize| (r - 1) * n + i % n + 1;
    let t = |r: usize, i: usize| (r - 1) * (n + 1) + i + 1;
    let mut faces = 0;
    for r in 1..rows - 1 {
        for i in 0..n {
            let (a, b, c, d) = ((r, i), (r, i + 1), (r + 1, i + 1), (r + 1, i));
            for tri in [[a, d, c], [a, c, b]] {
                s += "f";
                for (rr, ii) in tri {
                    s += &format!(" {}/{}", v(rr, ii), t(rr, ii));
                }
                s += "\n";
                faces += 1;
            }
        }
    }
    let south = (rows - 1) * n + 1;
    let south_t = (rows - 1) * (n + 1) + 1;
    for i in 0..n {
        let r = rows - 1;
        s += &format!(
            "f {}/{} {south}/{south_t} {}/{}\n",
            v(r, i),
            t(r, i),
            v(r, i + 1),
            t(r, i + 1)
        );
        faces += 1;
    }
    (s, vertices, faces)
}

/// `fill_holes` (issue 40 item 2): the job runs on the filled mesh, closed, with the file's
/// vertices and faces first; frame 0 says the connectivity changed and carries the patch's
/// vertices after the file's; the result's patch has UVs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fill_holes_closes_the_hole_and_frame_zero_says_so() {
    let srv = start(|_| {}).await;
    let (obj, upload_vertices, upload_faces) = holed_uv_sphere_obj(24);
    let (st, _, job) = srv
        .submit_obj(
            &obj,
            "steps=1&fill_holes=all&method=mcf&until_converged=false",
        )
        .await;
    assert_eq!(st, 202, "{job}");
    assert_eq!(job["params"]["fill_holes"], "all");
    let vertex_count = job["vertex_count"].as_u64().expect("vertex_count") as usize;
    let face_count = job["face_count"].as_u64().expect("face_count") as usize;
    assert!(vertex_count > upload_vertices, "{job}");
    // Closed genus 0: F = 2V − 4.
    assert_eq!(face_count, 2 * vertex_count - 4, "{job}");
    assert!(face_count > upload_faces);
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");

    let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
    let events = read_sse(res, JOB_TIMEOUT).await;
    let frames: Vec<&Sse> = events.iter().filter(|e| e.event == "frame").collect();
    assert_eq!(
        frames[0].data["connectivity_changed"], true,
        "{:?}",
        frames[0]
    );
    let b64 = frames[0].data["positions_b64"].as_str().expect("positions");
    let bytes =
        base64::Engine::decode(&base64::engine::general_purpose::STANDARD, b64).expect("base64");
    let frame0 = f32_triples(&bytes);
    assert_eq!(frame0.len(), vertex_count);
    let upload = obj_vertices(&obj);
    for (a, b) in upload.iter().zip(&frame0) {
        for k in 0..3 {
            assert!(
                (a[k] - b[k] as f64).abs() < 1e-6,
                "the file's vertices come first"
            );
        }
    }
    // The patch closes the north pole: its vertices lie near the sphere's cap.
    assert!(
        frame0[upload_vertices..].iter().all(|p| p[2] > 0.8),
        "the patch is where the hole was"
    );

    let res = srv.get(&format!("/v1/jobs/{id}/result?format=obj")).await;
    assert_eq!(res.status(), 200);
    let text = res.text().await.expect("body");
    let faces: Vec<&str> = text.lines().filter(|l| l.starts_with("f ")).collect();
    assert_eq!(faces.len(), face_count);
    // The longitude seam runs into the polar hole, so its loop's corners lie on two charts:
    // the file's faces keep their UVs, the patch has none, and the job says so.
    let with_uv = |f: &&str| f.split_whitespace().skip(1).all(|c| c.contains('/'));
    assert!(
        faces[..upload_faces].iter().all(with_uv),
        "the file's faces keep their UVs"
    );
    assert!(
        !faces[upload_faces..].iter().any(with_uv),
        "the patch is written without UVs"
    );
    let notes = job["notes"].as_array().expect("notes");
    assert!(
        notes
            .iter()
            .any(|n| n.as_str().is_some_and(|n| n.contains("no UVs"))),
        "{notes:?}"
    );

    // A size that admits no hole leaves the upload as it was.
    let (st, _, job) = srv
        .submit_obj(&obj, "steps=1&fill_holes=5&method=mcf")
        .await;
    assert_eq!(st, 202, "{job}");
    assert_eq!(
        job["face_count"].as_u64(),
        Some(upload_faces as u64),
        "{job}"
    );
    // A size that is no size is refused at submission, naming the field.
    let (st, _, problem) = srv.submit_obj(&obj, "fill_holes=2").await;
    assert_eq!(st, 400, "{problem}");
    assert_eq!(problem["field"], "fill_holes", "{problem}");
    srv.stop().await;
}
