//! Health (draining flips it) and reflection.

use super::*;

/// grpc.health.v1 answers SERVING while the core is ready and NOT_SERVING once it drains;
/// reflection lists every service, health included, and serves their descriptors.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;

    let server = Server::start(|_| {}).await;
    let mut health = HealthClient::new(server.channel().await);
    let check = |service: &str| HealthCheckRequest {
        service: service.to_string(),
    };
    // Workers mark themselves alive just after start: allow them a moment.
    let mut status = 0;
    for _ in 0..100 {
        status = health
            .check(check(""))
            .await
            .expect("Check")
            .into_inner()
            .status;
        if status == ServingStatus::Serving as i32 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(status, ServingStatus::Serving as i32);
    for service in willow_service::api::grpc::SERVICE_NAMES {
        let s = health
            .check(check(service))
            .await
            .expect("Check")
            .into_inner();
        assert_eq!(s.status, ServingStatus::Serving as i32, "{service}");
    }
    let unknown = health
        .check(check("no.such.Service"))
        .await
        .expect_err("unknown");
    assert_eq!(unknown.code(), Code::NotFound);

    let mut reflection = ServerReflectionClient::new(server.channel().await);
    let ask = |m: MessageRequest| ServerReflectionRequest {
        host: String::new(),
        message_request: Some(m),
    };
    let mut replies = reflection
        .server_reflection_info(futures::stream::iter(vec![
            ask(MessageRequest::ListServices(String::new())),
            ask(MessageRequest::FileContainingSymbol(
                "willow.v1.Fairing".into(),
            )),
        ]))
        .await
        .expect("reflection stream")
        .into_inner();
    let mut services = Vec::new();
    let mut files = 0;
    while let Some(reply) = replies.message().await.expect("reflection reply") {
        match reply.message_response {
            Some(MessageResponse::ListServicesResponse(list)) => {
                services.extend(list.service.into_iter().map(|s| s.name))
            }
            Some(MessageResponse::FileDescriptorResponse(fds)) => {
                files += fds.file_descriptor_proto.len()
            }
            other => panic!("unexpected reflection reply {other:?}"),
        }
    }
    for want in [
        "willow.v1.Fairing",
        "google.longrunning.Operations",
        "grpc.health.v1.Health",
        "grpc.reflection.v1.ServerReflection",
    ] {
        assert!(
            services.iter().any(|s| s == want),
            "{want} not in {services:?}"
        );
    }
    assert!(files >= 1, "fairing.proto's descriptor is served");

    // Draining flips health at once.
    server.jobs.begin_drain();
    let s = health.check(check("")).await.expect("Check").into_inner();
    assert_eq!(s.status, ServingStatus::NotServing as i32);
    let refused = create(
        &mut server.fairing().await,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Mcf, 1),
        "",
    )
    .await
    .expect_err("no new jobs while draining");
    assert_eq!(refused.code(), Code::Unavailable);
    assert!(refused.get_details_retry_info().is_some());
}
