//! `callback_url` and `percent_complete` over gRPC: JobParams field 22 reaches the job (its end
//! is delivered, signed, to a loopback receiver), Operation metadata reports the progress, and
//! a plain-http callback on a server without `allow_insecure_callbacks` is INVALID_ARGUMENT
//! naming the field.

use super::*;
use crate::webhook_support::{next, receiver, SECRET};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn callback_url_over_grpc_is_delivered_and_operations_report_percent_complete() {
    let server = Server::start(|c| {
        c.allow_insecure_callbacks = true;
        c.webhook_secret = Some(SECRET.to_vec());
    })
    .await;
    let (hook, mut rx, _) = receiver(&[]).await;
    let mut client = server.fairing().await;
    let op = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        v1::JobParams {
            callback_url: Some(hook.clone()),
            until_converged: Some(false),
            ..params(v1::Method::Conformal, 4)
        },
        "",
    )
    .await
    .expect("CreateJob");
    let job = job_from_any(op.metadata.as_ref().expect("metadata"));
    assert_eq!(
        job.params.as_ref().and_then(|p| p.callback_url.clone()),
        Some(hook)
    );

    let d = next(&mut rx).await;
    assert!(d.signature_ok, "{d:?}");
    assert_eq!(d.body["type"], "job.succeeded");
    assert_eq!(
        format!("jobs/{}", d.body["data"]["id"].as_str().expect("id")),
        op.name
    );

    let done = server
        .operations()
        .await
        .get_operation(lro::GetOperationRequest {
            name: op.name.clone(),
        })
        .await
        .expect("GetOperation")
        .into_inner();
    let meta = job_from_any(done.metadata.as_ref().expect("metadata"));
    assert_eq!(meta.percent_complete, 100.0);
    assert_eq!(meta.step, 4);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_http_callback_without_the_server_flag_is_invalid_argument() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let err = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        v1::JobParams {
            callback_url: Some("http://example.com/hook".into()),
            ..params(v1::Method::Conformal, 2)
        },
        "",
    )
    .await
    .expect_err("refused");
    assert_eq!(err.code(), Code::InvalidArgument, "{err:?}");
    let fields = violations(&err);
    assert!(
        fields.iter().any(|f| f.ends_with("callback_url")),
        "{fields:?} {err:?}"
    );
}
