//! Jobs end to end: uploads (OBJ, GLB, multipart, textured), streamed frames and SSE
//! reconnection, results, cancellation, the queue limit, idempotency, listing and expiry.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn obj_upload_streams_every_frame_then_result_downloads() {
    let srv = start(|_| {}).await;
    let (status, headers, job) = srv
        .submit_obj(&small_obj(), "steps=5&frame_interval=2&method=conformal")
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    assert_eq!(
        headers.get("location").and_then(|v| v.to_str().ok()),
        Some(format!("/v1/jobs/{id}").as_str())
    );
    assert_eq!(job["progress"]["total_steps"], 5);
    assert_eq!(job["links"]["events"], format!("/v1/jobs/{id}/events"));
    assert!(job["created_time"]
        .as_str()
        .is_some_and(|t| t.ends_with('Z')));

    // Watch from the start: state first, then frames 0..=5 in order, then done.
    let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
    assert_eq!(res.status(), 200);
    assert!(res
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("text/event-stream")));
    let events = read_sse(res, JOB_TIMEOUT).await;
    assert_eq!(events.first().map(|e| e.event.as_str()), Some("state"));
    assert_eq!(
        frame_steps(&events),
        vec![0, 1, 2, 3, 4, 5],
        "every step once, in order"
    );
    let vertex_count = job["vertex_count"].as_u64().expect("vertex_count") as usize;
    for e in events.iter().filter(|e| e.event == "frame") {
        let step = e.data["step"].as_u64().expect("step");
        assert_eq!(
            e.id.as_deref(),
            Some(step.to_string().as_str()),
            "SSE id = step"
        );
        assert!(e.data["metrics"]["willmore_energy"].is_number());
        let has = e.data.get("positions_b64").is_some();
        // Positions at step 0, every 2nd step, and the last step.
        assert_eq!(has, step % 2 == 0 || step == 5, "positions at step {step}");
        if has {
            use base64::Engine as _;
            let raw = base64::engine::general_purpose::STANDARD
                .decode(e.data["positions_b64"].as_str().expect("b64 text"))
                .expect("valid base64");
            assert_eq!(raw.len(), vertex_count * 12, "f32 xyz per file vertex");
        }
    }
    let done = events.last().expect("done event");
    assert_eq!(done.event, "done");
    assert_eq!(done.data["state"], "succeeded", "{}", done.data);

    // Polling agrees.
    let polled = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(polled["state"], "succeeded");
    assert_eq!(polled["progress"]["step"], 5);
    assert!(polled["metrics"]["latest"]["willmore_energy"].is_number());
    assert!(polled["finished_time"].is_string() && polled["expire_time"].is_string());

    // Frames list: metrics of steps 0..=5, paged.
    let (st, page) = srv
        .get_json(&format!("/v1/jobs/{id}/frames?page_size=4"))
        .await;
    assert_eq!(st, 200);
    assert_eq!(page["frames"].as_array().map(Vec::len), Some(4));
    assert_eq!(page["next_from_step"], 4);
    let (_, rest) = srv
        .get_json(&format!("/v1/jobs/{id}/frames?from_step=4"))
        .await;
    assert_eq!(rest["frames"].as_array().map(Vec::len), Some(2));
    assert!(rest.get("next_from_step").is_none());

    // A kept frame downloads; a step without positions is a specific 404.
    let res = srv.get(&format!("/v1/jobs/{id}/frames/2?format=obj")).await;
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["content-type"], "model/obj");
    let obj = res.text().await.expect("frame body");
    assert_eq!(
        obj.lines().filter(|l| l.starts_with("v ")).count(),
        vertex_count
    );
    let (st, p) = srv
        .get_json(&format!("/v1/jobs/{id}/frames/3?format=obj"))
        .await;
    assert_eq!(st, 404);
    assert_eq!(p["code"], "frame_not_found");
    assert!(
        p["detail"]
            .as_str()
            .is_some_and(|d| d.contains("every 2 steps")),
        "{p}"
    );

    // The result as GLB (and validated by Khronos glTF-Validator when it is installed).
    let res = srv.get(&format!("/v1/jobs/{id}/result?format=glb")).await;
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["content-type"], "model/gltf-binary");
    let glb = res.bytes().await.expect("result body");
    assert_eq!(&glb[..4], b"glTF", "GLB magic");
    validate_gltf(&glb);
    let res = srv.get(&format!("/v1/jobs/{id}/result?format=obj")).await;
    assert_eq!(res.status(), 200);
    srv.stop().await;
}

/// The Khronos glTF validator (tests/tools, installed by scripts/test.sh) accepts `bytes`. A
/// missing validator or node fails the test: it never passes having validated nothing.
fn validate_gltf(bytes: &[u8]) {
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/tools/validate_gltf.js");
    assert!(
        script.exists(),
        "{} is part of the repository",
        script.display()
    );
    let dir = tempfile::tempdir().expect("temp dir");
    let file = dir.path().join("result.glb");
    std::fs::write(&file, bytes).expect("write glb");
    let out = std::process::Command::new("node")
        .arg(&script)
        .arg(&file)
        .output()
        .unwrap_or_else(|e| {
            panic!("node runs the glTF validator (scripts/test.sh installs it): {e}")
        });
    assert!(
        out.status.success(),
        "glTF validator rejected the result:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A client applies the last streamed positions to the `v` lines of the OBJ it uploaded
/// (shuffled vertex order, unused vertices) and gets the downloaded result.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamed_positions_applied_to_the_upload_give_the_obj_result() {
    use base64::Engine as _;
    let srv = start(|_| {}).await;
    let upload = shuffled_obj();
    let (status, _, job) = srv
        .submit_obj(&upload, "steps=3&frame_interval=1&method=conformal")
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    let v_lines = upload.lines().filter(|l| l.starts_with("v ")).count();
    assert_eq!(job["vertex_count"].as_u64(), Some(v_lines as u64));
    let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
    let events = read_sse(res, JOB_TIMEOUT).await;
    let done = events.last().expect("done event");
    assert_eq!(done.data["state"], "succeeded", "{}", done.data);
    let last = events
        .iter()
        .rev()
        .find_map(|e| e.data.get("positions_b64").and_then(|p| p.as_str()))
        .expect("a frame with positions");
    let frame = f32_triples(
        &base64::engine::general_purpose::STANDARD
            .decode(last)
            .expect("base64"),
    );
    let res = srv.get(&format!("/v1/jobs/{id}/result?format=obj")).await;
    assert_eq!(res.status(), 200);
    let result = res.text().await.expect("OBJ text");
    assert_frame_applies_to_upload(&upload, &frame, &result);
    assert_ne!(result, upload, "the result is faired, not the upload");
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sse_reconnect_with_last_event_id_resumes_after_that_step() {
    let srv = start(|_| {}).await;
    let (status, _, job) = srv.submit_obj(&small_obj(), "steps=6").await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();

    // First connection: read until step 2, then drop it (the client "disconnects").
    let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
    let mut stream = res.bytes_stream();
    let mut seen = String::new();
    use futures::StreamExt;
    while !seen.contains("id: 2\n") && !seen.contains("id:2\n") {
        let chunk = tokio::time::timeout(JOB_TIMEOUT, stream.next())
            .await
            .expect("frames arrive")
            .expect("stream open")
            .expect("chunk");
        seen.push_str(&String::from_utf8_lossy(&chunk));
    }
    drop(stream);

    // Reconnect as EventSource does: Last-Event-ID = the last id seen.
    let res = srv
        .client
        .get(srv.url(&format!("/v1/jobs/{id}/events")))
        .header("Last-Event-ID", "2")
        .send()
        .await
        .expect("events again");
    let events = read_sse(res, JOB_TIMEOUT).await;
    assert_eq!(frame_steps(&events), vec![3, 4, 5, 6]);
    assert_eq!(events.last().map(|e| e.event.as_str()), Some("done"));

    // A finished job replays entirely from the store, and `from_step` works too.
    let res = srv.get(&format!("/v1/jobs/{id}/events?from_step=5")).await;
    let events = read_sse(res, JOB_TIMEOUT).await;
    assert_eq!(frame_steps(&events), vec![5, 6]);
    assert_eq!(
        events.last().map(|e| e.data["state"].clone()),
        Some("succeeded".into())
    );
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn multipart_glb_upload_with_params_part_runs() {
    let srv = start(|_| {}).await;
    let glb = small_glb();
    let form = reqwest::multipart::Form::new()
        .part(
            "mesh",
            reqwest::multipart::Part::bytes(glb)
                .file_name("sphere.glb")
                .mime_str("model/gltf-binary")
                .expect("mime"),
        )
        .text(
            "params",
            r#"{"method": "conformal", "steps": 3, "include_positions": false}"#,
        );
    let res = srv
        .client
        .post(srv.url("/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .expect("POST multipart");
    assert_eq!(res.status(), 202);
    let job: serde_json::Value = res.json().await.expect("json");
    assert_eq!(job["input_format"], "glb");
    assert_eq!(job["params"]["steps"], 3);
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let res = srv.get(&format!("/v1/jobs/{id}/events")).await;
    let events = read_sse(res, JOB_TIMEOUT).await;
    assert_eq!(frame_steps(&events), vec![0, 1, 2, 3]);
    assert!(
        events.iter().all(|e| e.data.get("positions_b64").is_none()),
        "include_positions=false sends metrics only"
    );
    // A GLB input downloads as glTF JSON too.
    let res = srv.get(&format!("/v1/jobs/{id}/result?format=gltf")).await;
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["content-type"], "model/gltf+json");
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_queued_and_running_jobs_and_full_queue_gets_429() {
    let srv = start(|c| {
        c.workers = 1;
        c.queue_capacity = 1;
    })
    .await;
    let slow = slow_obj();
    // A: runs (many steps on a bigger sphere), B: waits, C: refused.
    let (st, _, a) = srv
        .submit_obj(&slow, "steps=5000&until_converged=false")
        .await;
    assert_eq!(st, 202, "{a}");
    let a_id = a["id"].as_str().expect("id").to_string();
    srv.poll_until(&a_id, JOB_TIMEOUT, |v| v["state"] == "running")
        .await;
    let (st, _, b) = srv.submit_obj(&small_obj(), "steps=3").await;
    assert_eq!(st, 202, "{b}");
    let b_id = b["id"].as_str().expect("id").to_string();
    assert_eq!(b["state"], "queued");

    let (st, headers, p) = srv.submit_obj(&small_obj(), "steps=3").await;
    assert_eq!(st, 429, "{p}");
    let retry: u64 = headers
        .get("retry-after")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .expect("Retry-After in seconds");
    assert!(retry >= 1);
    assert_eq!(
        headers.get("content-type").and_then(|v| v.to_str().ok()),
        Some("application/problem+json")
    );
    assert_eq!(p["code"], "queue_full");
    assert_eq!(p["status"], 429);
    assert_eq!(p["capacity"], 1);
    assert!(p["detail"]
        .as_str()
        .is_some_and(|d| d.contains("queue is full")));

    // Cancel the queued one: it is cancelled at once and never runs.
    let res = srv
        .client
        .post(srv.url(&format!("/v1/jobs/{b_id}/cancel")))
        .send()
        .await
        .expect("cancel B");
    assert_eq!(res.status(), 202);
    let b2: serde_json::Value = res.json().await.expect("json");
    assert_eq!(b2["state"], "cancelled");
    assert!(b2["started_time"].is_null());

    // Cancel the running one: it stops at its next step.
    let res = srv
        .client
        .post(srv.url(&format!("/v1/jobs/{a_id}/cancel")))
        .send()
        .await
        .expect("cancel A");
    assert_eq!(res.status(), 202);
    let a2 = srv.poll_until(&a_id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(a2["state"], "cancelled");
    assert_eq!(a2["error_code"], "cancelled");
    let steps_done = a2["progress"]["step"].as_u64().expect("step");
    assert!(steps_done < 5000, "stopped early, at step {steps_done}");

    // A finished job cannot be cancelled again.
    let res = srv
        .client
        .post(srv.url(&format!("/v1/jobs/{a_id}/cancel")))
        .send()
        .await
        .expect("cancel again");
    assert_eq!(res.status(), 409);
    let p: serde_json::Value = res.json().await.expect("json");
    assert_eq!(p["code"], "conflict");
    // The result of a cancelled job is a conflict, not a download.
    let (st, p) = srv.get_json(&format!("/v1/jobs/{a_id}/result")).await;
    assert_eq!(st, 409, "{p}");

    // With the queue free again, submissions are accepted.
    let (st, _, _) = srv.submit_obj(&small_obj(), "steps=1").await;
    assert_eq!(st, 202);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idempotency_key_returns_the_same_job_and_refuses_a_different_request() {
    let srv = start(|_| {}).await;
    let obj = small_obj();
    let post = |body: String, q: &'static str| {
        srv.client
            .post(srv.url(&format!("/v1/jobs?{q}")))
            .header("content-type", "model/obj")
            .header("Idempotency-Key", "key-123")
            .body(body)
            .send()
    };
    let r1 = post(obj.clone(), "steps=2").await.expect("first");
    assert_eq!(r1.status(), 202);
    let j1: serde_json::Value = r1.json().await.expect("json");
    let r2 = post(obj.clone(), "steps=2").await.expect("retry");
    assert_eq!(r2.status(), 202);
    let j2: serde_json::Value = r2.json().await.expect("json");
    assert_eq!(
        j1["id"], j2["id"],
        "a retry returns the job the key created"
    );

    let r3 = post(obj.clone(), "steps=3").await.expect("other params");
    assert_eq!(r3.status(), 422);
    let p: serde_json::Value = r3.json().await.expect("json");
    assert_eq!(p["code"], "idempotency_mismatch");
    assert!(p["detail"].as_str().is_some_and(|d| d.contains("key-123")));

    let (_, list) = srv.get_json("/v1/jobs").await;
    assert_eq!(
        list["jobs"].as_array().map(Vec::len),
        Some(1),
        "one job for one key"
    );
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn list_delete_and_expiry() {
    let srv = start(|c| {
        c.result_ttl = Duration::from_millis(1500);
        c.sweep_interval = Duration::from_millis(200);
    })
    .await;
    let obj = small_obj();
    let mut ids = Vec::new();
    for _ in 0..3 {
        let (st, _, j) = srv.submit_obj(&obj, "steps=1").await;
        assert_eq!(st, 202);
        ids.push(j["id"].as_str().expect("id").to_string());
    }
    for id in &ids {
        srv.poll_until(id, JOB_TIMEOUT, is_terminal).await;
    }
    // Paged, newest first.
    let (_, p1) = srv.get_json("/v1/jobs?page_size=2").await;
    let first: Vec<&str> = p1["jobs"]
        .as_array()
        .expect("jobs")
        .iter()
        .filter_map(|j| j["id"].as_str())
        .collect();
    assert_eq!(first, vec![ids[2].as_str(), ids[1].as_str()]);
    let token = p1["next_page_token"]
        .as_str()
        .expect("next page")
        .to_string();
    let (_, p2) = srv
        .get_json(&format!("/v1/jobs?page_size=2&page_token={token}"))
        .await;
    let second: Vec<&str> = p2["jobs"]
        .as_array()
        .expect("jobs")
        .iter()
        .filter_map(|j| j["id"].as_str())
        .collect();
    assert_eq!(second, vec![ids[0].as_str()]);
    assert!(p2.get("next_page_token").is_none());
    let (_, by_state) = srv.get_json("/v1/jobs?state=succeeded").await;
    assert_eq!(by_state["jobs"].as_array().map(Vec::len), Some(3));
    let (_, none) = srv.get_json("/v1/jobs?state=running").await;
    assert_eq!(none["jobs"].as_array().map(Vec::len), Some(0));

    // Delete one: 204, then 404; its files are gone.
    let res = srv
        .client
        .delete(srv.url(&format!("/v1/jobs/{}", ids[0])))
        .send()
        .await
        .expect("delete");
    assert_eq!(res.status(), 204);
    let (st, _) = srv.get_json(&format!("/v1/jobs/{}", ids[0])).await;
    assert_eq!(st, 404);
    assert!(!srv.dir.path().join("jobs").join(&ids[0]).exists());

    // The others expire: 410 Gone, and the sweeper removes their files.
    tokio::time::sleep(Duration::from_millis(2000)).await;
    let (st, p) = srv.get_json(&format!("/v1/jobs/{}", ids[1])).await;
    assert_eq!(st, 410, "{p}");
    assert_eq!(p["code"], "gone");
    let (st, _) = srv.get_json(&format!("/v1/jobs/{}/result", ids[2])).await;
    assert_eq!(st, 410);
    assert!(
        !srv.dir.path().join("jobs").join(&ids[1]).exists(),
        "expired files swept"
    );
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn textured_upload_keeps_uvs_in_the_validated_result() {
    use willow::mesh::io::{Asset, Format};
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("crates/willow/tests/data/spot_triangulated.obj");
    let input = std::fs::read(&path)
        .expect("crates/willow/tests/data/spot_triangulated.obj (Spot, with UVs)");
    let limits = willow::mesh::Limits::default();
    let input_asset = Asset::read(&input, Format::Obj, &limits).expect("spot parses");
    let input_uvs = input_asset.corner_uvs().expect("spot has UVs");

    let srv = start(|_| {}).await;
    let res = srv
        .client
        .post(srv.url("/v1/jobs?steps=1&include_positions=false&method=conformal"))
        .header("content-type", "model/obj")
        .body(input)
        .send()
        .await
        .expect("POST spot");
    assert_eq!(res.status(), 202);
    let job: serde_json::Value = res.json().await.expect("json");
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");

    for format in [Format::Glb, Format::Obj] {
        let name = match format {
            Format::Glb => "glb",
            _ => "obj",
        };
        let res = srv
            .get(&format!("/v1/jobs/{id}/result?format={name}"))
            .await;
        assert_eq!(res.status(), 200);
        let bytes = res.bytes().await.expect("body");
        if format == Format::Glb {
            validate_gltf(&bytes);
        }
        let out = Asset::read(&bytes, format, &limits).expect("result parses");
        // OBJ keeps the `v` lines; GLB has one vertex per distinct v/vt corner. Per corner,
        // the UVs are the same either way.
        let file_vertices = if format == Format::Obj { 2930 } else { 3225 };
        assert_eq!(out.file_vertex_count(), file_vertices);
        assert_eq!(
            out.corner_uvs().expect("result keeps UVs"),
            input_uvs,
            "UVs identical ({name})"
        );
        let moved = out
            .surface()
            .positions
            .iter()
            .zip(&input_asset.surface().positions)
            .any(|(a, b)| a != b);
        assert!(
            moved,
            "the result is the faired surface, not the input ({name})"
        );
    }
    srv.stop().await;
}

/// A stored frame rendering names the positions it was rendered from: when a step's positions
/// are written again (a job resumed from a checkpoint before the step takes it again), the
/// next download renders the new positions instead of serving the first run's rendering.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rewritten_frame_is_rendered_again() {
    let srv = start(|_| {}).await;
    let (status, _, job) = srv
        .submit_obj(&small_obj(), "steps=2&frame_interval=1")
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let path = format!("/v1/jobs/{id}/frames/1?format=obj");
    let download = || async {
        let res = srv.get(&path).await;
        assert_eq!(res.status(), 200);
        obj_vertices(&res.text().await.expect("frame body"))
    };
    let first = download().await;
    assert!(!first.is_empty());

    // Step 1's welded positions written again, moved by +1 in x, as a put writes them: a new
    // file renamed into place.
    let file = srv.dir.path().join(format!("jobs/{id}/frames/1.f64"));
    let old = std::fs::read(&file).expect("the step's welded positions");
    assert_eq!(old.len() % 24, 0, "f64 xyz");
    let moved: Vec<u8> = old
        .chunks_exact(8)
        .enumerate()
        .flat_map(|(i, c)| {
            let v = f64::from_le_bytes(c.try_into().expect("8 bytes"));
            (if i % 3 == 0 { v + 1.0 } else { v }).to_le_bytes()
        })
        .collect();
    let tmp = file.with_extension("rewrite");
    std::fs::write(&tmp, &moved).expect("write");
    std::fs::rename(&tmp, &file).expect("rename into place");

    for n in 0..2 {
        let again = download().await;
        assert_eq!(again.len(), first.len());
        for (a, b) in first.iter().zip(&again) {
            assert!(
                (b[0] - (a[0] + 1.0)).abs() < 1e-6,
                "download {n}: {a:?} -> {b:?}"
            );
            assert!((b[1] - a[1]).abs() < 1e-6 && (b[2] - a[2]).abs() < 1e-6);
        }
    }
    srv.stop().await;
}

/// Issue 39: a job with no parameters is denoised. A noisy upload comes back smoother, in
/// frames, with the method reported; a clean one is left exactly as it is (`already_fair`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_with_no_parameters_denoises_and_leaves_a_clean_mesh_alone() {
    let srv = start(|_| {}).await;
    let post = |obj: String| {
        let (client, url) = (srv.client.clone(), srv.url("/v1/jobs"));
        async move {
            let res = client
                .post(url)
                .header("content-type", "model/obj")
                .body(obj)
                .send()
                .await
                .expect("POST /v1/jobs");
            assert_eq!(res.status(), 202);
            let job: serde_json::Value = res.json().await.expect("json");
            job["id"].as_str().expect("id").to_string()
        }
    };
    let clean = willow::mesh::generate::icosphere(4);
    let noisy = willow::mesh::generate::with_noise(clean.clone(), 0.3, 9);
    for (mesh, outcome) in [(&noisy, "completed"), (&clean, "already_fair")] {
        let id = post(obj_text(mesh)).await;
        let done = srv
            .poll_until(&id, Duration::from_secs(60), is_terminal)
            .await;
        assert_eq!(done["state"], "succeeded", "{done}");
        assert_eq!(done["outcome"], outcome, "{done}");
        assert_eq!(done["params"]["method"], "denoise", "{done}");
        if outcome == "completed" {
            // Its filtering settled before the 20 steps a job has by default: said so, not
            // "ran its 20 steps".
            let reason = done["outcome_reason"].as_str().expect("reason");
            let step = done["progress"]["step"].as_u64().expect("step");
            assert!(step < 20, "{done}");
            assert_eq!(
                reason,
                format!("the method ended on its own after {step} of its 20 steps")
            );
        }
        let result = srv.get(&format!("/v1/jobs/{id}/result?format=obj")).await;
        assert_eq!(result.status(), 200);
        let out = obj_vertices(&result.text().await.expect("body"));
        let theta =
            willow::denoise::score::mean_normal_angle(&out, &clean.positions, &clean.triangles);
        let before = willow::denoise::score::mean_normal_angle(
            &mesh.positions,
            &clean.positions,
            &clean.triangles,
        );
        if outcome == "completed" {
            assert!(theta < before / 3.0, "θ {before} → {theta}");
        } else {
            assert!(theta < 1e-4, "a clean mesh came back changed: θ {theta}");
        }
    }
}
