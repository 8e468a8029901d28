//! Over gRPC: refusals without side effects.

use super::*;

// gRPC

fn inline_request() -> v1::CreateJobRequest {
    v1::CreateJobRequest {
        mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
            format: v1::MeshFormat::Obj as i32,
            data: small_obj().into_bytes().into(),
        })),
        params: Some(v1::JobParams {
            steps: Some(2),
            ..Default::default()
        }),
        request_id: String::new(),
    }
}

fn with_auth<T>(msg: T, auth: Option<&str>) -> tonic::Request<T> {
    let mut req = tonic::Request::new(msg);
    if let Some(a) = auth {
        req.metadata_mut()
            .insert("authorization", a.parse().expect("ascii metadata"));
    }
    req
}

/// gRPC: the same refusals as UNAUTHENTICATED (with an ErrorInfo reason), nothing created;
/// valid credentials work; health stays open.
#[tokio::test]
async fn grpc_refusals_have_no_side_effects() {
    use tonic_types::StatusExt as _;
    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(&[line]);
    let server = Server::start(keys_and_jwt(&keys.file)).await;
    let mut client = FairingClient::new(server.channel().await);

    let expired = hs256(&claims(|c| c["exp"] = json!(now() - 3600)));
    let wrong_aud = hs256(&claims(|c| c["aud"] = json!("someone-else")));
    let wrong_iss = hs256(&claims(|c| c["iss"] = json!("https://evil.example")));
    let bad_key = "wlw_unknown".to_string();
    let cases: Vec<(Option<String>, &str)> = vec![
        (None, "MISSING_CREDENTIALS"),
        (Some(bearer(&bad_key)), "INVALID_TOKEN"),
        (Some(bearer(&expired)), "EXPIRED_TOKEN"),
        (Some(bearer(&wrong_aud)), "INVALID_TOKEN"),
        (Some(bearer(&wrong_iss)), "INVALID_TOKEN"),
    ];
    for (auth, reason) in &cases {
        let status = client
            .create_job(with_auth(inline_request(), auth.as_deref()))
            .await
            .expect_err("refused");
        assert_eq!(status.code(), Code::Unauthenticated, "{auth:?}: {status:?}");
        let info = status.get_details_error_info().expect("ErrorInfo");
        assert_eq!(info.reason, *reason);
        assert_eq!(info.domain, "willow.v1");
        if let Some(a) = auth {
            assert!(!status.message().contains(a.trim_start_matches("Bearer ")));
        }
        let status = client
            .list_jobs(with_auth(v1::ListJobsRequest::default(), auth.as_deref()))
            .await
            .expect_err("refused");
        assert_eq!(status.code(), Code::Unauthenticated);
    }
    let all = all_jobs(&server.jobs).await;
    assert!(all.is_empty(), "refused CreateJob calls created jobs");

    // Valid: a key, a JWT.
    let auth = bearer(&key);
    client
        .create_job(with_auth(inline_request(), Some(&auth)))
        .await
        .expect("CreateJob with a key");
    let jwt = bearer(&hs256(&claims(|_| {})));
    let list = client
        .list_jobs(with_auth(v1::ListJobsRequest::default(), Some(&jwt)))
        .await
        .expect("ListJobs with a JWT")
        .into_inner();
    assert_eq!(list.jobs.len(), 1);

    // Health is open.
    let mut health = tonic_health::pb::health_client::HealthClient::new(server.channel().await);
    health
        .check(tonic_health::pb::HealthCheckRequest {
            service: String::new(),
        })
        .await
        .expect("health without credentials");
    server.stop().await;
}
