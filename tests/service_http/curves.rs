//! The curve endpoint: fairing a noisy curve, hostile input, bounded slots and deadlines.

use super::*;

/// r = 1 + 0.2 sin 5t plus a deterministic jitter: curvature far from constant.
fn noisy_closed_curve(n: usize) -> Vec<[f64; 2]> {
    (0..n)
        .map(|i| {
            let t = std::f64::consts::TAU * i as f64 / n as f64;
            let jitter = 0.01 * (((i * 7919) % 13) as f64 / 13.0 - 0.5);
            let r = 1.0 + 0.2 * (5.0 * t).sin() + jitter;
            [r * t.cos(), r * t.sin()]
        })
        .collect()
}

/// The library's measures of a curve: (σ(κ)/κ̄ with its own dual lengths, total length).
fn curve_measures(points: &[[f64; 2]], closed: bool) -> (f64, f64) {
    use willow::curve::{curvature_std_over_mean, dual_lengths, Curve};
    let curve = Curve::new(points.to_vec(), closed).expect("valid curve");
    let mut dual = vec![0.0; points.len()];
    dual_lengths(&curve.edge_lengths(), closed, &mut dual);
    (
        curvature_std_over_mean(&curve.curvature(), &dual),
        curve.length(),
    )
}

fn points_of(v: &serde_json::Value) -> Vec<[f64; 2]> {
    v.as_array()
        .expect("points array")
        .iter()
        .map(|p| [p[0].as_f64().expect("x"), p[1].as_f64().expect("y")])
        .collect()
}

async fn post_curve(
    srv: &TestServer,
    content_type: &str,
    body: impl Into<reqwest::Body>,
    query: &str,
) -> (u16, serde_json::Value) {
    let res = srv
        .client
        .post(srv.url(&format!("/v1/curves:fair?{query}")))
        .header("content-type", content_type)
        .body(body)
        .send()
        .await
        .expect("POST /v1/curves:fair");
    let status = res.status().as_u16();
    if status != 200 {
        assert_eq!(
            res.headers()
                .get("content-type")
                .and_then(|v| v.to_str().ok()),
            Some("application/problem+json"),
            "status {status}"
        );
    }
    (status, res.json().await.unwrap_or(serde_json::Value::Null))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn curve_endpoint_rounds_a_noisy_curve_keeping_its_length() {
    use willow::curve::{Curve, CurveFlow, CurveParams};
    let srv = start(|_| {}).await;
    let input = noisy_closed_curve(256);
    let (before, length) = curve_measures(&input, true);
    assert!(before > 0.5, "the test curve is noisy: σ/κ̄ = {before}");

    let body = serde_json::json!({"points": input, "closed": true}).to_string();
    let (status, out) = post_curve(&srv, "application/json", body, "steps=6&tau=0.5").await;
    assert_eq!(status, 200, "{out}");
    assert_eq!(out["curve"]["closed"], true);
    let faired = points_of(&out["curve"]["points"]);
    assert_eq!(faired.len(), input.len());
    let (after, new_length) = curve_measures(&faired, true);
    assert!(after < 1e-2 * before, "σ/κ̄ from {before} to {after}");
    assert!(
        (new_length / length - 1.0).abs() < 1e-3,
        "length {length} → {new_length}"
    );
    // The same numbers as the library's own flow.
    let mut flow = CurveFlow::new(
        Curve::new(input.clone(), true).expect("curve"),
        CurveParams { tau: 0.5 },
    )
    .expect("flow");
    for _ in 0..6 {
        flow.step();
    }
    for (a, b) in faired.iter().zip(flow.points()) {
        assert!((a[0] - b[0]).abs() < 1e-12 && (a[1] - b[1]).abs() < 1e-12);
    }
    let metrics = out["metrics"].as_array().expect("metrics");
    assert_eq!(metrics.len(), 7, "step 0 and six steps");
    assert_eq!(metrics[0]["step"], 0);
    assert_eq!(metrics[6]["step"], 6);
    let last = metrics[6]["curvature_std_over_mean"]
        .as_f64()
        .expect("number");
    assert!((last - flow.last_metrics().curvature_std_over_mean).abs() < 1e-12);
    assert!(metrics[0]["curvature_std_over_mean"].as_f64() > Some(0.5));
    assert_eq!(out["params"]["steps"], 6);
    assert_eq!(out["params"]["tau"], 0.5);
    assert_eq!(
        out["params"]["deadline_secs"], 10.0,
        "the server default applied"
    );
    assert!(out.get("frames").is_none(), "no frames unless asked");

    // OBJ in (`l` closing on its first index), frames out: steps 0, 2, 4 and the last.
    let mut obj = String::new();
    for p in &input {
        obj.push_str(&format!("v {} {} 0\n", p[0], p[1]));
    }
    obj.push('l');
    for i in 1..=input.len() {
        obj.push_str(&format!(" {i}"));
    }
    obj.push_str(" 1\n");
    let (status, out) = post_curve(&srv, "model/obj", obj, "steps=5&frame_interval=2").await;
    assert_eq!(status, 200, "{out}");
    assert_eq!(out["curve"]["closed"], true);
    let steps: Vec<u64> = out["frames"]
        .as_array()
        .expect("frames")
        .iter()
        .map(|f| f["step"].as_u64().expect("step"))
        .collect();
    assert_eq!(steps, vec![0, 2, 4, 5]);
    // Within an ulp: this test parses with serde_json's default (not round-trip exact) reader.
    let close = |a: &[[f64; 2]], b: &[[f64; 2]]| {
        a.len() == b.len()
            && a.iter().zip(b).all(|(p, q)| {
                (p[0] - q[0]).abs() <= 1e-15 * p[0].abs().max(1.0)
                    && (p[1] - q[1]).abs() <= 1e-15 * p[1].abs().max(1.0)
            })
    };
    assert!(
        close(&points_of(&out["frames"][0]["points"]), &input),
        "frame 0 is the input"
    );
    assert_eq!(
        points_of(&out["frames"][3]["points"]),
        points_of(&out["curve"]["points"]),
        "the last frame is the result"
    );

    // An open curve (a bare array) straightens, its length kept.
    let open: Vec<[f64; 2]> = (0..50)
        .map(|i| {
            let x = i as f64 / 49.0;
            [x, 0.1 * (9.0 * x).sin()]
        })
        .collect();
    let (_, open_length) = curve_measures(&open, false);
    let (status, out) = post_curve(
        &srv,
        "application/json; charset=utf-8",
        serde_json::to_string(&open).expect("json"),
        "steps=20",
    )
    .await;
    assert_eq!(status, 200, "{out}");
    assert_eq!(out["curve"]["closed"], false);
    let (_, straightened) = curve_measures(&points_of(&out["curve"]["points"]), false);
    assert!((straightened / open_length - 1.0).abs() < 1e-3);

    // The OpenAPI document has the endpoint and the new job parameters, dotted names included.
    let (_, doc) = srv.get_json("/openapi.json").await;
    assert!(
        doc["paths"]["/v1/curves:fair"]["post"].is_object(),
        "{}",
        doc["paths"]
    );
    let names: Vec<&str> = doc["paths"]["/v1/jobs"]["post"]["parameters"]
        .as_array()
        .expect("parameters")
        .iter()
        .filter_map(|p| p["name"].as_str())
        .collect();
    for want in [
        "exactness",
        "mobius_balancing",
        "filter.sigma",
        "filter.k",
        "boundary",
        "boundary.prescribed.frame_angle",
        "boundary.prescribed.axis.fixed",
        "boundary.prescribed.angles.per_loop",
    ] {
        assert!(names.contains(&want), "{want} not in {names:?}");
    }
    assert!(doc["components"]["schemas"]["BoundarySpec"].is_object());
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn curve_endpoint_refuses_hostile_input_with_specific_problems() {
    let srv = start(|c| {
        c.limits.max_curve_points = 1000;
        c.limits.max_curve_bytes = 64 * 1024;
        c.limits.max_curve_frame_points = 5000;
    })
    .await;
    let json = "application/json";
    let circle = noisy_closed_curve(100);
    let good = serde_json::json!({"points": circle, "closed": true}).to_string();

    // Curves the flow cannot take: 422 with the library's reason as the code.
    let mut repeated = circle.clone();
    repeated.push(circle[0]);
    for (ct, body, code) in [
        (json, String::new(), "invalid_json"),
        (json, "{}".to_string(), "invalid_json"),
        (
            json,
            r#"{"points": [], "closed": true}"#.to_string(),
            "too_few_points",
        ),
        (
            json,
            r#"{"points": [[0, 0], [1, 0]], "closed": true}"#.to_string(),
            "too_few_points",
        ),
        (
            json,
            r#"{"points": [[0, 0], [1e999, 0], [0, 1]], "closed": true}"#.to_string(),
            "invalid_json",
        ),
        (
            json,
            r#"{"points": [[0, 0], [1, 0], [0, 1]], "closed": true, "extra": 1}"#.to_string(),
            "invalid_json",
        ),
        (
            json,
            serde_json::json!({"points": repeated, "closed": true}).to_string(),
            "zero_length_edge",
        ),
        (json, "[[0, 0], [1, 0], [0, 0]]".to_string(), "cusp"),
        (
            "model/obj",
            "v 0 0 0\nv nan 0 0\nv 0 1 0\nl 1 2 3 1\n".to_string(),
            "non_finite",
        ),
        (
            "model/obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 1\n".to_string(),
            "too_few_points",
        ),
        (
            "model/obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_string(),
            "invalid_obj",
        ),
        (
            "model/obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 5\nl 1 2 3 1\n".to_string(),
            "invalid_obj",
        ),
        (
            "model/obj",
            "v 0 0 0\nv 1 0 0\nl 1 2 9\n".to_string(),
            "invalid_obj",
        ),
    ] {
        let (status, p) = post_curve(&srv, ct, body.clone(), "").await;
        assert_eq!(status, 422, "{body}: {p}");
        assert_eq!(p["code"], code, "{body}: {p}");
        assert_eq!(p["instance"], "/v1/curves:fair");
    }
    let (_, p) = post_curve(
        &srv,
        json,
        serde_json::json!({"points": repeated, "closed": true}).to_string(),
        "",
    )
    .await;
    assert_eq!(p["index"], 100, "the closing edge: {p}");

    // Parameters: each names its field.
    for (query, field) in [
        ("steps=0", "steps"),
        ("tau=1", "tau"),
        ("tau=0", "tau"),
        ("tau=NaN", "tau"),
        ("frame_interval=0", "frame_interval"),
        ("deadline_secs=0", "deadline_secs"),
        ("deadline_secs=1000", "deadline_secs"),
        // 100 points × 101 frames is over the 5000-point limit of this server.
        ("steps=100&frame_interval=1", "frame_interval"),
    ] {
        let (status, p) = post_curve(&srv, json, good.clone(), query).await;
        assert_eq!(status, 400, "{query}: {p}");
        assert_eq!(p["field"], field, "{query}: {p}");
    }
    let (status, p) = post_curve(&srv, json, good.clone(), "steps=100&frame_interval=1").await;
    assert!(
        p["detail"]
            .as_str()
            .is_some_and(|d| d.contains("at least 3")),
        "{status} {p}"
    );
    let (status, p) = post_curve(&srv, json, good.clone(), "stepz=3").await;
    assert_eq!(status, 400, "{p}");
    // Limits: steps, points, bytes (announced or not).
    let (status, p) = post_curve(&srv, json, good.clone(), "steps=5000").await;
    assert_eq!((status, p["what"].as_str()), (413, Some("steps")), "{p}");
    let many = serde_json::json!({"points": noisy_closed_curve(1001), "closed": true}).to_string();
    let (status, p) = post_curve(&srv, json, many, "").await;
    assert_eq!(
        (status, p["what"].as_str()),
        (413, Some("curve points")),
        "{p}"
    );
    assert_eq!(p["limit"], 1000);
    let huge = format!("[{}[0,0]]", "[0,0],".repeat(20_000));
    let (status, p) = post_curve(&srv, json, huge.clone(), "").await;
    assert_eq!(
        (status, p["what"].as_str()),
        (413, Some("curve bytes")),
        "{p}"
    );
    let stream = futures::stream::iter(vec![Ok::<_, std::io::Error>(huge.into_bytes())]);
    let (status, p) = post_curve(&srv, json, reqwest::Body::wrap_stream(stream), "").await;
    assert_eq!(
        (status, p["what"].as_str()),
        (413, Some("curve bytes")),
        "chunked: {p}"
    );
    // Content types.
    let (status, p) = post_curve(&srv, "text/plain", good.clone(), "").await;
    assert_eq!(status, 415, "{p}");
    // Still serving after all that.
    let (status, _) = post_curve(&srv, json, good, "").await;
    assert_eq!(status, 200);
    srv.stop().await;
}

/// The curve slots are bounded: with one slot held by a long request, the next waits a second
/// and gets 429 + Retry-After; the long one ends at its deadline with 504; then the slot is
/// free again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn curve_slots_are_bounded_and_deadlines_end_long_requests() {
    let srv = start(|c| c.curve_slots = 1).await;
    // 100k points × 1000 steps: several seconds even in release, so the deadline ends it.
    let long =
        serde_json::json!({"points": noisy_closed_curve(100_000), "closed": true}).to_string();
    let url = srv.url("/v1/curves:fair?steps=1000&deadline_secs=4");
    let client = srv.client.clone();
    let holder = tokio::spawn(async move {
        let res = client
            .post(url)
            .header("content-type", "application/json")
            .body(long)
            .send()
            .await
            .expect("long request");
        let status = res.status().as_u16();
        (
            status,
            res.json::<serde_json::Value>().await.unwrap_or_default(),
        )
    });
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let small = serde_json::json!({"points": noisy_closed_curve(64), "closed": true}).to_string();
    let res = srv
        .client
        .post(srv.url("/v1/curves:fair"))
        .header("content-type", "application/json")
        .body(small.clone())
        .send()
        .await
        .expect("second request");
    assert_eq!(res.status(), 429);
    assert_eq!(
        res.headers()
            .get("retry-after")
            .and_then(|v| v.to_str().ok()),
        Some("1")
    );
    let p: serde_json::Value = res.json().await.expect("problem");
    assert_eq!(p["code"], "busy", "{p}");
    let (status, p) = tokio::time::timeout(JOB_TIMEOUT, holder)
        .await
        .expect("the long request ends")
        .expect("task");
    assert_eq!(status, 504, "{p}");
    assert_eq!(p["code"], "deadline_exceeded", "{p}");
    assert!(p["step"].as_u64() < Some(1000), "{p}");
    let (status, out) = post_curve(&srv, "application/json", small, "").await;
    assert_eq!(status, 200, "{out}");
    srv.stop().await;
}
