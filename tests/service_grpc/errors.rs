//! Every bad input gets its status and detail, and the error contract of issue 12: malformed
//! requests, refused waits, capped messages.

use super::*;

/// Every bad input gets its canonical code and a detail naming what was wrong.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_bad_input_gets_its_status_and_detail() {
    let server = Server::start(|c| c.limits.max_upload_bytes = 200_000).await;
    let mut client = server.fairing().await;
    let mut ops = server.operations().await;
    let obj = || inline(v1::MeshFormat::Obj, small_obj());
    let mcf = |steps| params(v1::Method::Mcf, steps);

    // Meshes, and where they come from: each refusal names the request field.
    for (mesh, field) in [
        (
            inline(v1::MeshFormat::Obj, b"v 0 0 0\nf 1 2 3\n".to_vec()),
            "inline_mesh.data",
        ),
        (
            inline(v1::MeshFormat::Unspecified, small_obj()),
            "inline_mesh.format",
        ),
        (None, "mesh"),
        (
            Some(v1::create_job_request::Mesh::Upload("nope".into())),
            "upload",
        ),
    ] {
        assert_bad_field(create(&mut client, mesh, mcf(1), "").await, field);
    }
    // Two triangles sharing an edge with a third: non-manifold, refused with its rule named
    // when repair is off (by default it is split).
    let fin = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nf 1 2 3\nf 2 1 4\nf 1 2 5\n".to_vec();
    let unrepaired = v1::JobParams {
        repair: Some(false),
        ..mcf(1)
    };
    let status = create(
        &mut client,
        inline(v1::MeshFormat::Obj, fin),
        unrepaired,
        "",
    )
    .await
    .expect_err("non-manifold mesh");
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_eq!(violations(&status), vec!["inline_mesh.data".to_string()]);
    let reason = status
        .get_details_error_info()
        .map(|e| e.reason)
        .unwrap_or_default();
    assert!(
        reason.starts_with("NON_MANIFOLD"),
        "{reason}: {}",
        status.message()
    );

    // Parameters: one step's MCF with one field set wrong.
    let mcf_with = |edit: fn(&mut v1::JobParams)| {
        let mut p = mcf(1);
        edit(&mut p);
        p
    };
    for (params, field) in [
        (mcf(0), "params.steps"),
        (mcf(1_000_000), "params.steps"),
        (mcf_with(|p| p.tau = Some(-1.0)), "params.tau"),
        (mcf_with(|p| p.tau = Some(f64::NAN)), "params.tau"),
        (mcf_with(|p| p.method = 99), "params.method"),
        (mcf_with(|p| p.iterations = Some(0)), "params.iterations"),
        (
            mcf_with(|p| p.frame_interval = Some(0)),
            "params.frame_interval",
        ),
        (
            mcf_with(|p| {
                p.deadline = Some(prost_types::Duration {
                    seconds: -1,
                    nanos: 0,
                })
            }),
            "params.deadline",
        ),
    ] {
        assert_bad_field(create(&mut client, obj(), params, "").await, field);
    }

    // Names.
    assert_bad_field(get_job(&mut client, "not-a-name").await, "name");
    assert_bad_field(get_job(&mut client, "jobs/a/b").await, "name");
    let missing = get_job(&mut client, "jobs/00000000-0000-4000-8000-000000000000")
        .await
        .expect_err("unknown job");
    assert_eq!(missing.code(), Code::NotFound);
    assert!(missing.get_details_resource_info().is_some());
    let no_upload = create(
        &mut client,
        Some(v1::create_job_request::Mesh::Upload("uploads/nope".into())),
        mcf(1),
        "",
    )
    .await
    .expect_err("unknown upload");
    assert_eq!(no_upload.code(), Code::NotFound, "{}", no_upload.message());

    // Upload streams.
    use v1::upload_mesh_chunk::Part;
    let header = |format: v1::MeshFormat, size: u64| v1::UploadMeshChunk {
        part: Some(Part::Header(v1::UploadHeader {
            format: format as i32,
            size_bytes: size,
        })),
    };
    let data = |b: &[u8]| v1::UploadMeshChunk {
        part: Some(Part::Data(Bytes::copy_from_slice(b))),
    };
    for (messages, field) in [
        (vec![], "header"),
        (vec![data(b"v 0 0 0\n")], "header"),
        (
            vec![
                header(v1::MeshFormat::Obj, 0),
                header(v1::MeshFormat::Obj, 0),
            ],
            "header",
        ),
        (
            vec![header(v1::MeshFormat::Unspecified, 0), data(b"v")],
            "header.format",
        ),
        (
            vec![header(v1::MeshFormat::Obj, 100), data(b"v 0 0 0\n")],
            "header.size_bytes",
        ),
    ] {
        assert_bad_field(upload_raw(&mut client, messages).await, field);
    }
    assert_bad_field(
        upload(&mut client, v1::MeshFormat::Glb, b"not a glb at all", 4).await,
        "data",
    );
    // Over the server's 200 000-byte limit: announced, and not announced.
    for (announce, field) in [(true, "header.size_bytes"), (false, "data")] {
        let big = vec![b'#'; 300_000];
        let size = if announce { big.len() as u64 } else { 0 };
        let msgs = vec![
            header(v1::MeshFormat::Obj, size),
            data(&big[..150_000]),
            data(&big[150_000..]),
        ];
        let status = upload_raw(&mut client, msgs)
            .await
            .expect_err("over the limit");
        assert_eq!(
            status.code(),
            Code::ResourceExhausted,
            "{}",
            status.message()
        );
        assert!(
            status.get_details_retry_info().is_none(),
            "retrying cannot help"
        );
        let quota = status.get_details_quota_failure().expect("QuotaFailure");
        assert!(
            quota.violations[0].description.contains("200000"),
            "{quota:?}"
        );
        assert_eq!(violations(&status), vec![field.to_string()]);
    }

    // Lists.
    assert_bad_field(
        client
            .list_jobs(v1::ListJobsRequest {
                page_size: -1,
                ..Default::default()
            })
            .await,
        "page_size",
    );
    assert_bad_field(
        ops.list_operations(lro::ListOperationsRequest {
            name: "jobs".into(),
            filter: "done=true".into(),
            ..Default::default()
        })
        .await,
        "filter",
    );

    // A result before the job has one.
    let op = create(&mut client, obj(), mcf(1), "")
        .await
        .expect("a good job");
    let early = client
        .download_result(v1::DownloadResultRequest {
            name: op.name.clone(),
            format: v1::MeshFormat::Obj as i32,
        })
        .await;
    if let Err(status) = early {
        assert_eq!(
            status.code(),
            Code::FailedPrecondition,
            "{}",
            status.message()
        );
    } // (the 1-step job may already have succeeded: then there is a result, which is fine)
}

/// A unary call with hand-made request bytes over h2c; returns `grpc-status` and
/// `grpc-message` (a request refused before the handler runs is a trailers-only response:
/// both are headers).
async fn raw_unary(addr: &str, method: &str, message: &[u8]) -> (String, String) {
    let client = reqwest::Client::builder()
        .http2_prior_knowledge()
        .build()
        .expect("h2c client");
    let mut body = vec![0u8];
    body.extend_from_slice(&(message.len() as u32).to_be_bytes());
    body.extend_from_slice(message);
    let res = client
        .post(format!("{addr}/willow.v1.Fairing/{method}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(body)
        .send()
        .await
        .expect("raw gRPC call");
    let header = |name: &str| {
        res.headers()
            .get(name)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string()
    };
    (header("grpc-status"), header("grpc-message"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_protobuf_and_invalid_utf8_are_invalid_argument() {
    let server = Server::start(|_| {}).await;
    // GetJobRequest.name (field 1, length-delimited) claims 5 bytes and has 1: truncated.
    let (status, message) = raw_unary(&server.addr, "GetJob", &[0x0a, 0x05, b'a']).await;
    assert_eq!(status, "3", "truncated message: {message}");
    // The same field holding bytes that are not UTF-8.
    let (status, message) = raw_unary(&server.addr, "GetJob", &[0x0a, 0x02, 0xff, 0xfe]).await;
    assert_eq!(status, "3", "invalid UTF-8: {message}");
    // A well-formed request still reaches the handler (NOT_FOUND for an unknown job).
    let ok = v1::GetJobRequest {
        name: format!("jobs/{}", uuid()),
    }
    .encode_to_vec();
    let (status, _) = raw_unary(&server.addr, "GetJob", &ok).await;
    assert_eq!(status, "5");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn negative_from_step_is_refused_not_waited_on() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let op = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Conformal, 2),
        &uuid(),
    )
    .await
    .expect("CreateJob");
    // A client's int32 -1 arrives in the uint32 field as u32::MAX.
    for from_step in [u32::MAX, i32::MAX as u32 + 1, 1_000_000] {
        let result = tokio::time::timeout(
            PATIENCE,
            client.stream_frames(v1::StreamFramesRequest {
                name: op.name.clone(),
                from_step,
            }),
        )
        .await
        .expect("answered, not left waiting");
        assert_bad_field(result.map(|_| ()), "from_step");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_user_text_is_capped_in_status_messages() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let long = "x".repeat(1 << 20);
    let status = client
        .get_job(v1::GetJobRequest {
            name: format!("jobs/{long}"),
        })
        .await
        .expect_err("no such job");
    assert_eq!(status.code(), Code::NotFound, "{}", &status.message()[..80]);
    assert!(
        status.message().chars().count() <= 1025,
        "{} chars",
        status.message().len()
    );
    let status = client
        .create_job(v1::CreateJobRequest {
            mesh: Some(v1::create_job_request::Mesh::Upload(format!(
                "uploads/{long}"
            ))),
            params: Some(params(v1::Method::Conformal, 2)),
            request_id: uuid(),
        })
        .await
        .expect_err("no such upload");
    assert!(
        status.message().chars().count() <= 1025,
        "{} chars",
        status.message().len()
    );
}
