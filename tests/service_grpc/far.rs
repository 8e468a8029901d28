//! Far from the origin over gRPC (issue 27, item 4): spot at +5e6 and +1e9 streams frames whose
//! `origin` + float32 `positions` keep 1e-6 of its size against the OBJ result. And what the
//! job stores about its upload (repairs, notes) in GetJob.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn far_frames_keep_a_millionth_of_the_size() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    use v1::stream_frames_response::Event;
    for offset in [5e6, 1e9, 0.0] {
        let upload = service_http_support::spot_at(offset);
        let op = create(
            &mut client,
            inline(v1::MeshFormat::Obj, upload.into_bytes()),
            v1::JobParams {
                frame_interval: Some(1),
                include_positions: Some(true),
                tau: Some(0.001),
                until_converged: Some(false),
                ..params(v1::Method::Mcf, 2)
            },
            &uuid(),
        )
        .await
        .expect("CreateJob");
        let events = stream_all(&mut client, &op.name, 0).await;
        let frames: Vec<&v1::Frame> = events
            .iter()
            .filter_map(|e| match e {
                Event::Frame(f) if f.positions.is_some() => Some(f),
                _ => None,
            })
            .collect();
        assert_eq!(frames.len(), 3, "steps 0, 1, 2 at {offset}");
        let origins: Vec<Option<[f64; 3]>> = frames
            .iter()
            .map(|f| f.origin.as_ref().map(|o| [o.x, o.y, o.z]))
            .collect();
        assert!(origins.iter().all(|o| *o == origins[0]), "{origins:?}");
        let last = frames.last().expect("a frame");
        let relative =
            service_http_support::f32_triples(last.positions.as_ref().expect("positions"));
        let result = download_obj(&mut client, &op.name).await;
        if offset == 0.0 {
            // Around the origin nothing changes: no origin, the floats are the coordinates.
            assert_eq!(origins[0], None);
            service_http_support::assert_obj_result_is_frame(&result, &relative, relative.len());
        } else {
            let origin = origins[0].expect("an origin far from the origin");
            assert!((origin[0] - offset).abs() < 2.0, "{origin:?} for {offset}");
            let frame = service_http_support::frame_absolute(&relative, Some(origin));
            service_http_support::assert_frame_within_a_millionth(&frame, &result, offset);
        }
    }
}

/// GetJob reports what `repair` changed and the notes of a glTF whose result drops morph
/// targets, from the stored job (a job without either has neither).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn get_job_reports_repairs_and_notes() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let submit = |format, data: Vec<u8>, repair| {
        let mut client = client.clone();
        async move {
            create(
                &mut client,
                inline(format, data),
                v1::JobParams {
                    repair: Some(repair),
                    ..params(v1::Method::Mcf, 1)
                },
                &uuid(),
            )
            .await
            .expect("CreateJob")
            .name
        }
    };
    let bowtie = submit(
        v1::MeshFormat::Obj,
        service_http_support::bowtie_obj().into_bytes(),
        true,
    )
    .await;
    let morph = submit(
        v1::MeshFormat::Glb,
        service_http_support::morph_glb(),
        false,
    )
    .await;
    let plain = submit(v1::MeshFormat::Obj, small_obj(), false).await;

    let job = get_job(&mut client, &bowtie).await.expect("GetJob");
    let r = job.repairs.expect("repairs");
    assert_eq!((r.split_vertex_count, r.added_vertices), (1, 1), "{r:?}");
    assert_eq!(
        r.split_vertices,
        vec![0],
        "the file's vertex 0 (`v` line 1)"
    );
    assert_eq!(r.dropped_face_count, 0);
    assert!(job.notes.is_empty());
    let job = get_job(&mut client, &morph).await.expect("GetJob");
    assert!(job.repairs.is_none());
    assert!(
        job.notes
            .iter()
            .any(|n| n.starts_with("morph targets dropped: 1 targets")),
        "{:?}",
        job.notes
    );
    let job = get_job(&mut client, &plain).await.expect("GetJob");
    assert!(job.repairs.is_none() && job.notes.is_empty());
}
