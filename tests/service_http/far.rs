//! Far from the origin (issue 27, item 4): spot at +5e6 and +1e9 streams frames whose
//! `origin` + f32 offsets keep 1e-6 of its size against the OBJ result, live and replayed from
//! the store; around the origin frames carry no `origin`.

use super::*;

/// The last frame with positions: its f32 offsets and its `origin`.
fn last_positions(events: &[Sse]) -> (Vec<[f32; 3]>, Option<[f64; 3]>) {
    use base64::Engine as _;
    let frame = events
        .iter()
        .rev()
        .find(|e| e.event == "frame" && e.data.get("positions_b64").is_some())
        .expect("a frame with positions");
    let raw = base64::engine::general_purpose::STANDARD
        .decode(frame.data["positions_b64"].as_str().expect("b64 text"))
        .expect("valid base64");
    let origin = frame.data.get("origin").map(|o| {
        let c: Vec<f64> = o
            .as_array()
            .expect("origin is an array")
            .iter()
            .map(|x| x.as_f64().expect("a number"))
            .collect();
        assert_eq!(c.len(), 3, "{o}");
        [c[0], c[1], c[2]]
    });
    (f32_triples(&raw), origin)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn far_frames_keep_a_millionth_of_the_size_live_and_replayed() {
    let srv = start(|_| {}).await;
    for offset in [5e6, 1e9] {
        let upload = spot_at(offset);
        let (status, _, job) = srv
            .submit_obj(
                &upload,
                "steps=2&frame_interval=1&method=mcf&tau=0.001&until_converged=false",
            )
            .await;
        assert_eq!(status, 202, "{job}");
        let id = job["id"].as_str().expect("id").to_string();
        let live = read_sse(srv.get(&format!("/v1/jobs/{id}/events")).await, JOB_TIMEOUT).await;
        assert_eq!(
            live.last().map(|e| e.data["state"].clone()),
            Some("succeeded".into())
        );
        let res = srv.get(&format!("/v1/jobs/{id}/result?format=obj")).await;
        assert_eq!(res.status(), 200);
        let result = res.text().await.expect("result");
        // Every frame with positions carries the same origin, near the model.
        let origins: Vec<_> = live
            .iter()
            .filter(|e| e.data.get("positions_b64").is_some())
            .map(|e| e.data["origin"].clone())
            .collect();
        assert_eq!(origins.len(), 3, "steps 0, 1, 2");
        assert!(origins.iter().all(|o| *o == origins[0]), "{origins:?}");
        let x = origins[0][0].as_f64().expect("origin x");
        assert!((x - offset).abs() < 2.0, "{x} for {offset}");
        // Live, then replayed from the stored frames after the job ended.
        let stored = read_sse(srv.get(&format!("/v1/jobs/{id}/events")).await, JOB_TIMEOUT).await;
        for events in [&live, &stored] {
            let (relative, origin) = last_positions(events);
            let frame = frame_absolute(&relative, origin);
            assert_frame_within_a_millionth(&frame, &result, offset);
        }
    }
    // Around the origin: no `origin`, and the f32 positions are the coordinates.
    let (_, _, job) = srv
        .submit_obj(&spot_at(0.0), "steps=1&method=mcf&tau=0.001")
        .await;
    let id = job["id"].as_str().expect("id").to_string();
    let events = read_sse(srv.get(&format!("/v1/jobs/{id}/events")).await, JOB_TIMEOUT).await;
    let (relative, origin) = last_positions(&events);
    assert_eq!(origin, None);
    let result = srv.get(&format!("/v1/jobs/{id}/result?format=obj")).await;
    let result = result.text().await.expect("result");
    assert_obj_result_is_frame(&result, &relative, relative.len());
    srv.stop().await;
}
