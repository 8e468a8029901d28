//! Issues 4 and 10: every flow option of the library as a job parameter, refused options
//! naming their field, and safeguarded steps.

use super::*;

/// A bumpy torus (genus 1).
fn bumpy_torus_obj() -> String {
    let mut torus = willow::mesh::generate::torus(1.0, 0.4, 24, 12);
    for p in &mut torus.positions {
        let s = 1.0 + 0.05 * (5.0 * p[0]).sin() * (4.0 * p[1]).cos();
        *p = [p[0] * s, p[1] * s, p[2] * s];
    }
    obj_text(&torus)
}

/// The library run the job should have been: the same OBJ, `params`, `steps` steps; the
/// metrics of the last step.
fn library_run(obj: &str, params: &willow::flow::FlowParams, steps: usize) -> serde_json::Value {
    use willow::mesh::io::{Asset, Format};
    let asset = Asset::read(
        obj.as_bytes(),
        Format::Obj,
        &willow::mesh::Limits::default(),
    )
    .expect("test mesh parses");
    let mut flow = willow::flow::new_flow(asset.surface(), params).expect("library flow builds");
    let mut last = None;
    for _ in 0..steps {
        last = Some(flow.step().expect("library step"));
    }
    serde_json::to_value(last.expect("at least one step")).expect("metrics serialize")
}

/// The metrics a job and a library run must agree on (not the step time).
const COMPARED: [&str; 4] = ["willmore_energy", "q_mean", "closure_residual", "area"];

fn relative_gap(a: &serde_json::Value, b: &serde_json::Value) -> f64 {
    COMPARED
        .iter()
        .map(|k| {
            let (x, y) = (
                a[k].as_f64().unwrap_or(f64::NAN),
                b[k].as_f64().unwrap_or(f64::NAN),
            );
            (x - y).abs() / x.abs().max(y.abs()).max(1e-300)
        })
        .fold(0.0, f64::max)
}

/// Submit `obj` with `query`, wait for the end, and return the final job view.
async fn run_job(srv: &TestServer, obj: &str, query: &str) -> serde_json::Value {
    let (status, _, job) = srv.submit_obj(obj, query).await;
    assert_eq!(status, 202, "{query}: {job}");
    let id = job["id"].as_str().expect("id").to_string();
    srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await
}

/// Each option reaches the flow: the job's last metrics are those of the library run with the
/// `FlowParams` the option names, and (where the option changes anything on that mesh) not
/// those of the run without it. Also: every method runs to completion, and `params` reports
/// the option back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_flow_option_reaches_the_flow_and_is_reported_back() {
    use willow::flow::filter::SpectralFilter;
    use willow::flow::{Boundary, BoundaryAngles, FlowParams, Method, PrescribedVectors};
    let srv = start(|_| {}).await;
    let sphere = small_obj();
    let cap = obj_text(&willow::mesh::generate::bumpy_cap(3, 0.06));
    let torus = bumpy_torus_obj();
    let plain = FlowParams::default();
    struct Case<'a> {
        mesh: &'a str,
        query: &'a str,
        params: FlowParams,
        steps: usize,
        /// Whether the option changes the result on this mesh (closed surfaces ignore the
        /// boundary condition, for example).
        changes: bool,
        reported: serde_json::Value,
    }
    let cases = [
        Case {
            mesh: &sphere,
            query: "steps=3&filter.sigma=0.01&filter.k=2",
            params: FlowParams {
                filter: Some(SpectralFilter { sigma: 0.01, k: 2 }),
                ..plain.clone()
            },
            steps: 3,
            changes: true,
            reported: serde_json::json!({"filter": {"sigma": 0.01, "k": 2}}),
        },
        Case {
            mesh: &sphere,
            query: "steps=3&mobius_balancing=true",
            params: FlowParams {
                mobius_balancing: true,
                ..plain.clone()
            },
            steps: 3,
            changes: true,
            reported: serde_json::json!({"mobius_balancing": true}),
        },
        Case {
            mesh: &torus,
            query: "steps=2&exactness=false",
            params: FlowParams {
                exactness: false,
                ..plain.clone()
            },
            steps: 2,
            changes: true,
            reported: serde_json::json!({"exactness": false}),
        },
        Case {
            mesh: &sphere,
            query: "steps=3&method=taubin&tau=0.3",
            params: FlowParams {
                method: Method::Taubin,
                tau: 0.3,
                ..plain.clone()
            },
            steps: 3,
            changes: true,
            reported: serde_json::json!({"method": "taubin", "tau": 0.3}),
        },
        Case {
            mesh: &sphere,
            query: "steps=2&method=cmcf&tau=0.05",
            params: FlowParams {
                method: Method::Cmcf,
                tau: 0.05,
                ..plain.clone()
            },
            steps: 2,
            changes: true,
            reported: serde_json::json!({"method": "cmcf"}),
        },
        Case {
            mesh: &sphere,
            query: "steps=2&method=bilaplacian&tau=0.01",
            params: FlowParams {
                method: Method::Bilaplacian,
                tau: 0.01,
                ..plain.clone()
            },
            steps: 2,
            changes: true,
            reported: serde_json::json!({"method": "bilaplacian"}),
        },
        Case {
            mesh: &cap,
            query: "steps=2&boundary=fixed",
            params: FlowParams {
                boundary: Boundary::Fixed,
                ..plain.clone()
            },
            steps: 2,
            changes: true,
            reported: serde_json::json!({"boundary": "fixed"}),
        },
        // Issue 39: no boundary given, an open surface's border is held (`auto` is `fixed`
        // under the conformal flow); `free` is the library's default, asked for.
        Case {
            mesh: &cap,
            query: "steps=2",
            params: FlowParams {
                boundary: Boundary::Fixed,
                ..plain.clone()
            },
            steps: 2,
            changes: true,
            reported: serde_json::json!({"boundary": "auto"}),
        },
        Case {
            mesh: &cap,
            query: "steps=2&boundary=free",
            params: plain.clone(),
            steps: 2,
            changes: false,
            reported: serde_json::json!({"boundary": "free"}),
        },
        Case {
            mesh: &sphere,
            query: "steps=1&boundary=fixed",
            params: FlowParams {
                boundary: Boundary::Fixed,
                ..plain.clone()
            },
            steps: 1,
            changes: false,
            reported: serde_json::json!({"boundary": "fixed"}),
        },
        // The lead's prescribed-vectors solver: until it lands, the library (and so the job)
        // answers `unsupported` here.
        Case {
            mesh: &cap,
            query: "steps=2&boundary=cmc",
            params: FlowParams {
                boundary: Boundary::Cmc,
                ..plain.clone()
            },
            steps: 2,
            changes: true,
            reported: serde_json::json!({"boundary": "cmc"}),
        },
        Case {
            mesh: &cap,
            query: "steps=2&boundary.prescribed.frame_angle=0.2&boundary.prescribed.axis.fixed=0,0,1&boundary.prescribed.angles.per_loop=0.15",
            params: FlowParams {
                boundary: Boundary::Prescribed(PrescribedVectors {
                    frame_angle: 0.2,
                    axis: willow::flow::RotationAxis::Fixed([0.0, 0.0, 1.0]),
                    angles: BoundaryAngles::PerLoop(vec![0.15]),
                }),
                ..plain.clone()
            },
            steps: 2,
            changes: true,
            reported: serde_json::json!({"boundary": {"prescribed": {
                "frame_angle": 0.2, "axis": {"fixed": [0.0, 0.0, 1.0]}, "angles": {"per_loop": [0.15]}}}}),
        },
    ];
    for case in &cases {
        let done = run_job(&srv, case.mesh, case.query).await;
        assert_eq!(
            done["state"], "succeeded",
            "{}: {} {}",
            case.query, done["error_code"], done["error"]
        );
        for (key, want) in case.reported.as_object().expect("object") {
            assert_eq!(&done["params"][key], want, "{}: params.{key}", case.query);
        }
        let job = &done["metrics"]["latest"];
        let expected = library_run(case.mesh, &case.params, case.steps);
        assert!(
            relative_gap(job, &expected) < 1e-9,
            "{}: job {job} vs library {expected}",
            case.query
        );
        let without = library_run(
            case.mesh,
            &FlowParams {
                method: case.params.method,
                tau: case.params.tau,
                ..FlowParams::default()
            },
            case.steps,
        );
        let differs = case.params.method != Method::Conformal || relative_gap(job, &without) > 1e-6;
        assert_eq!(
            differs, case.changes,
            "{}: with {job} vs without {without}",
            case.query
        );
    }

    // Without the exactness constraints a torus no longer closes up (Figure 12).
    let closure = |q: &str| {
        let q = q.to_string();
        let torus = torus.clone();
        let srv = &srv;
        async move { run_job(srv, &torus, &q).await["metrics"]["latest"]["closure_residual"].as_f64() }
    };
    let (with, without) = (
        closure("steps=2").await.expect("closure"),
        closure("steps=2&exactness=false").await.expect("closure"),
    );
    assert!(
        without > 10.0 * with,
        "closure with {with}, without {without}"
    );

    // Defaults are reported too, and the reported params submit again as they are (JSON part).
    let done = run_job(&srv, &sphere, "steps=1").await;
    let params = &done["params"];
    assert_eq!(params["exactness"], true);
    assert_eq!(params["mobius_balancing"], false);
    assert_eq!(params["filter"], serde_json::Value::Null);
    assert_eq!(params["boundary"], "auto");
    assert_eq!(params["safeguard"], true);
    let prescribed = run_job(
        &srv,
        &cap,
        "steps=1&boundary=prescribed&boundary.prescribed.angles.uniform=-0.1&boundary.prescribed.axis=tangent",
    )
    .await;
    assert_eq!(
        prescribed["params"]["boundary"],
        serde_json::json!({"prescribed": {"frame_angle": 0.0, "axis": "tangent", "angles": {"uniform": -0.1}}})
    );
    for view in [&done, &prescribed] {
        let mesh = if view["vertex_count"] == done["vertex_count"] {
            &sphere
        } else {
            &cap
        };
        let (status, again) = srv
            .submit_obj_with_params(mesh, &view["params"].to_string())
            .await;
        assert_eq!(status, 202);
        assert_eq!(again["params"], view["params"], "round trip");
        let (_, polled) = srv
            .get_json(&format!("/v1/jobs/{}", again["id"].as_str().expect("id")))
            .await;
        assert_eq!(polled["params"], view["params"], "GET reports the same");
    }
    srv.stop().await;
}

/// Each bad value of a flow option is a 400 naming the field, before anything is queued.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_flow_options_are_refused_with_the_field_named() {
    let srv = start(|_| {}).await;
    let sphere = small_obj();
    let cap = obj_text(&willow::mesh::generate::bumpy_cap(3, 0.06));
    let cases: [(&str, &str, &str); 22] = [
        (&sphere, "filter.sigma=0.1&filter.k=4", "filter.k"),
        (&sphere, "filter.sigma=0&filter.k=2", "filter.sigma"),
        (&sphere, "filter.sigma=NaN&filter.k=2", "filter.sigma"),
        (&sphere, "filter.sigma=inf&filter.k=2", "filter.sigma"),
        (&sphere, "filter.sigma=0.1", "filter.k"),
        (&sphere, "filter.k=1", "filter.sigma"),
        (&sphere, "boundary=clamped", "boundary"),
        (
            &cap,
            "boundary.prescribed.frame_angle=1.6",
            "boundary.prescribed.frame_angle",
        ),
        (
            &cap,
            "boundary.prescribed.frame_angle=-1.55",
            "boundary.prescribed.frame_angle",
        ),
        (
            &cap,
            "boundary.prescribed.frame_angle=NaN",
            "boundary.prescribed.frame_angle",
        ),
        (
            &cap,
            "boundary.prescribed.axis.fixed=0,0,0",
            "boundary.prescribed.axis.fixed",
        ),
        (
            &cap,
            "boundary.prescribed.axis.fixed=1,2",
            "boundary.prescribed.axis.fixed",
        ),
        (
            &cap,
            "boundary.prescribed.axis.fixed=inf,0,0",
            "boundary.prescribed.axis.fixed",
        ),
        (
            &cap,
            "boundary.prescribed.axis=north",
            "boundary.prescribed.axis",
        ),
        (
            &cap,
            "boundary.prescribed.angles.uniform=NaN",
            "boundary.prescribed.angles.uniform",
        ),
        (
            &cap,
            "boundary.prescribed.angles.per_loop=0.1,x",
            "boundary.prescribed.angles.per_loop",
        ),
        // The cap has one boundary loop, the sphere none: the count is checked on the upload.
        (
            &cap,
            "boundary.prescribed.angles.per_loop=0.1,0.2",
            "boundary.prescribed.angles.per_loop",
        ),
        (
            &sphere,
            "boundary.prescribed.angles.per_loop=0.1",
            "boundary.prescribed.angles.per_loop",
        ),
        (
            &cap,
            "boundary=fixed&boundary.prescribed.frame_angle=0.1",
            "boundary",
        ),
        // Options of the conformal flow with another method.
        (&sphere, "method=mcf&filter.sigma=0.1&filter.k=1", "filter"),
        (&sphere, "method=taubin&exactness=false", "exactness"),
        (&sphere, "method=cmcf&boundary=cmc", "boundary"),
    ];
    for (mesh, query, field) in cases {
        let (status, _, p) = srv.submit_obj(mesh, query).await;
        assert_eq!(status, 400, "{query}: {p}");
        assert_eq!(p["code"], "invalid_parameter", "{query}: {p}");
        assert_eq!(p["field"], field, "{query}: {p}");
    }
    let (status, _, p) = srv
        .submit_obj(&sphere, "method=mcf&mobius_balancing=true")
        .await;
    assert_eq!(
        (status.as_u16(), p["field"].as_str()),
        (400, Some("mobius_balancing"))
    );
    // Unparseable values name their parameter in the detail.
    let (status, _, p) = srv.submit_obj(&sphere, "exactness=maybe").await;
    assert_eq!(status, 400, "{p}");
    assert!(
        p["detail"]
            .as_str()
            .is_some_and(|d| d.contains("exactness")),
        "{p}"
    );
    // The conformal flow's τ < 1 is the conformal flow's: other methods may go above.
    let (status, _, p) = srv.submit_obj(&sphere, "method=mcf&tau=1.5&steps=1").await;
    assert_eq!(status, 202, "{p}");
    // Nothing refused above was queued.
    let (_, list) = srv.get_json("/v1/jobs").await;
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(1), "{list}");

    // The JSON params part: nested shapes, unknown fields refused, per-vertex angles library-only.
    for (params, field) in [
        (r#"{"filter": {"sigma": 0.1, "k": 9}}"#, "filter.k"),
        (
            r#"{"boundary": {"prescribed": {"frame_angle": 2.0}}}"#,
            "boundary.prescribed.frame_angle",
        ),
        // Shape errors in the JSON name their field too.
        (
            r#"{"boundary": {"prescribed": {"frame_angel": 0.1}}}"#,
            "boundary.prescribed.frame_angel",
        ),
        (
            r#"{"boundary": {"prescribed": {"angles": {"per_vertex": [[0, 0.1]]}}}}"#,
            "boundary.prescribed.angles",
        ),
        (r#"{"filter": {"sigma": 0.1}}"#, "filter"),
        (r#"{"boundary": "clamped"}"#, "boundary"),
        ("[1, 2]", "params"),
    ] {
        // The conformal flow's options, asked of the conformal flow (not the default method).
        let params = match params.strip_prefix('{') {
            Some(rest) => format!(r#"{{"method": "conformal", {rest}"#),
            None => params.to_string(),
        };
        let form = reqwest::multipart::Form::new()
            .part(
                "mesh",
                reqwest::multipart::Part::text(cap.clone()).file_name("cap.obj"),
            )
            .text("params", params.clone());
        let res = srv
            .client
            .post(srv.url("/v1/jobs"))
            .multipart(form)
            .send()
            .await
            .expect("POST multipart");
        assert_eq!(res.status(), 400, "{params}");
        let p: serde_json::Value = res.json().await.expect("problem");
        assert_eq!(p["field"], field, "{params}: {p}");
    }
    srv.stop().await;
}

/// Little-endian f32 xyz triples of a frame's `positions_b64`.
fn frame_positions(frame: &serde_json::Value) -> Vec<[f32; 3]> {
    use base64::Engine as _;
    let raw = base64::engine::general_purpose::STANDARD
        .decode(frame["positions_b64"].as_str().expect("positions_b64"))
        .expect("valid base64");
    f32_triples(&raw)
}

/// `safeguard` is reported back and reaches the flow; frames carry the τ each step used and
/// its rejected tries; and a job whose flow can make no acceptable step (implicit MCF at
/// τ = 1000 on `bumpy_sphere(2, 0.4)`: steps 1 and 2 are kept, step 3 raises W even at
/// τ/1024) ends succeeded after step 2 with code `no_progress` and the reason, its result
/// being the surface of the last frame.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn safeguard_option_frame_tau_and_no_progress_keeps_the_last_good_mesh() {
    let srv = start(|_| {}).await;
    let bumpy = obj_text(&willow::mesh::generate::bumpy_sphere(2, 0.4));

    // On an easy mesh, every step is taken at the requested τ, guarded or not.
    for (query, guarded) in [("steps=3", true), ("steps=3&safeguard=false", false)] {
        let (status, _, job) = srv.submit_obj(&bumpy, query).await;
        assert_eq!(status, 202, "{query}: {job}");
        assert_eq!(job["params"]["safeguard"], guarded, "{query}");
        let id = job["id"].as_str().expect("id").to_string();
        let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
        let events = read_sse(res, JOB_TIMEOUT).await;
        let frames: Vec<_> = events.iter().filter(|e| e.event == "frame").collect();
        assert_eq!(frames.len(), 4, "{query}");
        assert_eq!(frames[0].data["metrics"]["tau"], 0.0, "step 0 is the input");
        for f in &frames[1..] {
            assert_eq!(
                f.data["metrics"]["tau"], 0.5,
                "{query}: {}",
                f.data["metrics"]
            );
            assert_eq!(f.data["metrics"]["rejected"], 0, "{query}");
        }
        let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
        assert_eq!(done["state"], "succeeded", "{done}");
        assert_eq!(done["params"]["safeguard"], guarded);
        assert_eq!(done["metrics"]["latest"]["tau"], 0.5);
        // The stored frames (replayed from the database) keep tau and rejected too.
        let (_, listed) = srv.get_json(&format!("/v1/jobs/{id}/frames")).await;
        let stored: Vec<_> = listed["frames"]
            .as_array()
            .expect("frames")
            .iter()
            .map(|m| (m["tau"].as_f64(), m["rejected"].as_u64()))
            .collect();
        assert_eq!(
            stored,
            vec![
                (Some(0.0), Some(0)),
                (Some(0.5), Some(0)),
                (Some(0.5), Some(0)),
                (Some(0.5), Some(0))
            ]
        );
    }

    // No progress: the job ends early with the last accepted surface as its result.
    let (status, _, job) = srv.submit_obj(&bumpy, "steps=6&method=mcf&tau=1000").await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
    let events = read_sse(res, JOB_TIMEOUT).await;
    assert_eq!(frame_steps(&events), vec![0, 1, 2], "steps 1 and 2 kept");
    let last = events
        .iter()
        .rfind(|e| e.event == "frame")
        .expect("a frame");
    assert_eq!(last.data["metrics"]["tau"], 1000.0);
    let done = events.last().expect("done");
    assert_eq!(done.event, "done");
    for view in [
        done.data.clone(),
        srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await,
    ] {
        assert_eq!(view["state"], "succeeded", "{view}");
        assert_eq!(view["error_code"], "no_progress", "{view}");
        let reason = view["error"].as_str().unwrap_or_default();
        assert!(
            reason.contains("no progress at step 3")
                && reason.contains("Willmore energy would rise"),
            "{reason}"
        );
        assert_eq!(view["progress"]["step"], 2);
        assert_eq!(view["progress"]["total_steps"], 6);
    }
    let res = srv.get(&format!("/v1/jobs/{id}/result?format=obj")).await;
    assert_eq!(res.status(), 200);
    let text = res.text().await.expect("OBJ text");
    assert_obj_result_is_frame(&text, &frame_positions(&last.data), 162);
    srv.stop().await;
}

/// Issue 42: every refusal the mesh's topology, resolution and size allow happens at
/// submission: 400 naming the field, no job accepted to fail later.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn what_the_upload_shows_is_refused_at_submission_by_field() {
    let srv = start(|_| {}).await;
    let sphere = small_obj();
    let cap = obj_text(&willow::mesh::generate::bumpy_cap(3, 0.06));
    let torus = bumpy_torus_obj();
    let cases: [(&str, &str, &str, &str); 9] = [
        (
            &torus,
            "method=cmcf&steps=1",
            "method",
            "spherical topology",
        ),
        (&cap, "method=cmcf&steps=1", "method", "boundary loop"),
        (
            &sphere,
            "steps=1&feature_size=1e-6",
            "feature_size",
            "resolution",
        ),
        (
            &sphere,
            "steps=1&feature_size=1e6",
            "feature_size",
            "larger than the mesh",
        ),
        (
            &sphere,
            "steps=1&feature_size=1e308",
            "feature_size",
            "larger than the mesh",
        ),
        (
            &cap,
            "steps=1&preserve=volume",
            "preserve",
            "border is held",
        ),
        (
            &sphere,
            "steps=1&preserve=volume&region.sphere=0,0,1,0.5",
            "preserve",
            "with a region",
        ),
        (
            &sphere,
            "method=taubin&steps=1&tau=1e-320",
            "tau",
            "at least",
        ),
        (
            &sphere,
            "method=taubin&steps=1&tau=1e-10",
            "tau",
            "at least",
        ),
    ];
    for (mesh, query, field, words) in cases {
        let (status, _, body) = srv.submit_obj(mesh, query).await;
        assert_eq!(status, 400, "{query}: {body}");
        assert_eq!(body["field"], field, "{query}: {body}");
        let detail = body["detail"].as_str().expect("detail");
        assert!(detail.contains(words), "{query}: {detail}");
    }
    // The same uploads with what they allow are accepted.
    for (mesh, query) in [
        (&sphere, "method=cmcf&steps=1"),
        (&cap, "steps=1&preserve=volume&boundary=free"),
        (&sphere, "method=taubin&steps=1&tau=1e-9"),
    ] {
        let (status, _, body) = srv.submit_obj(mesh, query).await;
        assert_eq!(status, 202, "{query}: {body}");
    }
}
