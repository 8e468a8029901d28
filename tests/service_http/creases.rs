//! Issue 40, item 1 over HTTP: `feature_angle` in the query and in `params`, reported back,
//! the creases counted in every frame's metrics (`crease_edges`), and bad angles refused at
//! submission naming the field.

use super::*;

/// A cylinder of radius 1 and height 2, both rims chamfered at 45°: four crease rings of 64
/// edges (the library's test part).
fn chamfered_cylinder_obj() -> String {
    obj_text(&willow::mesh::generate::chamfered_cylinder(0.1, 64))
}

async fn run(srv: &TestServer, obj: &str, query: &str) -> serde_json::Value {
    let (status, _, job) = srv.submit_obj(obj, query).await;
    assert_eq!(status, 202, "{query}: {job}");
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{query}: {done}");
    done
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn creases_are_held_counted_and_reported_back() {
    let srv = start(|_| {}).await;
    let part = chamfered_cylinder_obj();
    let common = "method=conformal&steps=2&tau=0.05&until_converged=false";

    // The default (`auto`) finds the four rings and every frame counts them.
    let done = run(&srv, &part, common).await;
    assert_eq!(done["params"]["feature_angle"], "auto", "{done}");
    assert_eq!(done["metrics"]["latest"]["crease_edges"], 4 * 64, "{done}");
    let id = done["id"].as_str().expect("id");
    let events = read_sse(srv.get(&format!("/v1/jobs/{id}/events")).await, JOB_TIMEOUT).await;
    let counts: Vec<_> = events
        .iter()
        .filter(|e| e.event == "frame")
        .map(|e| e.data["metrics"]["crease_edges"].clone())
        .collect();
    // (The coarse part's patches between the held bands settle at once: the run may end
    // `converged` after its first step.)
    assert!(frame_steps(&events).starts_with(&[0, 1]), "{done}");
    assert!(counts.iter().all(|c| *c == 4 * 64), "{counts:?}");

    // `none` keeps none; an angle above the chamfers' 45° finds none either (not a refusal:
    // the part simply has no edge that sharp).
    for query in ["feature_angle=none", "feature_angle=60"] {
        let done = run(&srv, &part, &format!("{common}&{query}")).await;
        assert!(
            done["metrics"]["latest"].get("crease_edges").is_none(),
            "{query}: {done}"
        );
    }
    let done = run(&srv, &part, &format!("{common}&feature_angle=44.5")).await;
    assert_eq!(done["params"]["feature_angle"], 44.5, "{done}");
    assert_eq!(done["metrics"]["latest"]["crease_edges"], 4 * 64, "{done}");

    // The JSON form takes the number and the names.
    for (params, reported) in [
        (serde_json::json!(30), serde_json::json!(30.0)),
        (serde_json::json!("none"), serde_json::json!("none")),
    ] {
        let params =
            serde_json::json!({"method": "conformal", "steps": 1, "feature_angle": params});
        let (status, job) = srv.submit_obj_with_params(&part, &params.to_string()).await;
        assert_eq!(status, 202, "{job}");
        assert_eq!(job["params"]["feature_angle"], reported, "{job}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_feature_angles_are_refused_at_submission() {
    let srv = start(|_| {}).await;
    let part = chamfered_cylinder_obj();
    for (query, words) in [
        ("feature_angle=180", "between 0 and 180"),
        ("feature_angle=0", "between 0 and 180"),
        ("feature_angle=-3", "between 0 and 180"),
        ("feature_angle=sharp", "expected `auto`, `none` or an angle"),
        ("method=mcf&feature_angle=40", "not by `mcf`"),
        ("feature_angle=40&preserve=volume", "preserve"),
    ] {
        let (status, _, body) = srv.submit_obj(&part, query).await;
        assert_eq!(status, 400, "{query}: {body}");
        assert_eq!(body["field"], "feature_angle", "{query}: {body}");
        let detail = body["detail"].as_str().expect("detail");
        assert!(detail.contains(words), "{query}: {detail}");
    }
}
