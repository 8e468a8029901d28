//! Slowloris headers and bodies are cut within the configured time while normal clients are
//! served; a trickling gRPC upload ends `DEADLINE_EXCEEDED`.

use super::*;

#[tokio::test]
async fn slowloris_headers_are_cut_while_normal_clients_are_served() {
    let srv = start(limits(|_| {})).await;
    let timeout = Duration::from_secs(2);
    let stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    let slow = trickle_until_cut(
        stream,
        b"GET /healthz HTTP/1.1\r\nHost: willow\r\n",
        b"X-Slow: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa",
        timeout + MARGIN + Duration::from_secs(5),
    );
    let (slow, slowest) = tokio::join!(slow, normal_clients(&srv.base));
    let (sent, after) = slow;
    eprintln!("slowloris (headers) cut after {after:?}, timeout {timeout:?}; slowest normal request {slowest:?}");
    assert!(
        after >= timeout - Duration::from_millis(500),
        "cut at {after:?}: before the timeout"
    );
    assert!(after <= timeout + MARGIN, "cut only after {after:?}");
    assert_nothing_or_408(&sent);
    assert!(
        slowest < Duration::from_secs(2),
        "normal requests took {slowest:?}"
    );

    // The same on a keep-alive connection: the second request's head is trickled.
    let mut stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    stream.write_all(HEALTHZ).await.expect("send");
    let first = read_response(&mut stream).await.expect("first response");
    assert_eq!(first.status, 200);
    assert_eq!(first.body, b"ok");
    let (sent, after) = trickle_until_cut(
        stream,
        b"GET /healthz HTTP/1.1\r\n",
        b"Host: willowwwwwwwwwwwwwwwwwwwwww",
        timeout + MARGIN + Duration::from_secs(5),
    )
    .await;
    eprintln!("slowloris (keep-alive headers) cut after {after:?}, timeout {timeout:?}");
    assert!(after <= timeout + MARGIN, "cut only after {after:?}");
    assert_nothing_or_408(&sent);
    srv.stop().await;
}

#[tokio::test]
async fn slow_and_stalled_bodies_are_cut_and_real_uploads_work() {
    let srv = start(limits(|_| {})).await;
    let timeout = Duration::from_secs(2);
    let head = "POST /v1/jobs?steps=1 HTTP/1.1\r\nHost: willow\r\nContent-Type: model/obj\r\n\
                Content-Length: 100000\r\n\r\nv 0 0 0\n";

    // 1 byte a second.
    let stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    let (sent, after) = trickle_until_cut(
        stream,
        head.as_bytes(),
        b"v 1 1 1\n",
        timeout + MARGIN + Duration::from_secs(5),
    )
    .await;
    let text = String::from_utf8_lossy(&sent).to_string();
    eprintln!("slow body cut after {after:?}, body timeout {timeout:?}");
    assert!(
        text.starts_with("HTTP/1.1 408"),
        "a trickled body gets 408: {text}"
    );
    assert!(
        text.to_ascii_lowercase().contains("connection: close"),
        "{text}"
    );
    assert!(text.contains("body_timeout"), "{text}");
    assert!(
        after >= timeout - Duration::from_millis(500),
        "cut at {after:?}: before the timeout"
    );
    assert!(after <= timeout + MARGIN, "cut only after {after:?}");

    // A body that stops half-way.
    let mut stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    stream.write_all(head.as_bytes()).await.expect("send");
    stream
        .write_all("v 1 2 3\n".repeat(1000).as_bytes())
        .await
        .expect("send");
    let t = Instant::now();
    let res = tokio::time::timeout(timeout + MARGIN, read_response(&mut stream))
        .await
        .expect("answered within the body timeout")
        .expect("a response");
    eprintln!("stalled body answered after {:?}", t.elapsed());
    assert_eq!(res.status, 408);
    assert_eq!(res.header("connection"), Some("close"));
    let (_, closed) = read_until_closed(&mut stream, MARGIN).await;
    assert!(closed.is_some(), "the connection closes after the 408");

    // A real upload, at loopback speed, is untouched; so are normal clients meanwhile.
    let obj = slow_obj();
    let (status, _, job) = srv.submit_obj(&obj, "steps=2").await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("job id").to_string();
    let done = srv
        .poll_until(
            &id,
            Duration::from_secs(120),
            service_http_support::is_terminal,
        )
        .await;
    assert_eq!(done["state"], "succeeded", "{done}");
    eprintln!("real upload of {} bytes accepted and run", obj.len());
    srv.stop().await;
}

#[tokio::test]
async fn grpc_upload_trickling_is_deadline_exceeded() {
    use willow_service::api::grpc::pb::willow::v1;
    use willow_service::api::grpc::pb::willow::v1::upload_mesh_chunk::Part;
    let srv = start(limits(|_| {})).await;
    let channel = tonic::transport::Channel::from_shared(srv.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("h2c");
    let mut client = v1::fairing_client::FairingClient::new(channel);
    let header = v1::UploadMeshChunk {
        part: Some(Part::Header(v1::UploadHeader {
            format: v1::MeshFormat::Obj as i32,
            size_bytes: 1_000_000,
        })),
    };
    // One small chunk a second, forever.
    let chunks = futures::stream::unfold(true, |first| async move {
        if !first {
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        Some((
            v1::UploadMeshChunk {
                part: Some(Part::Data(bytes::Bytes::from_static(b"v 0 0 0\n"))),
            },
            false,
        ))
    });
    let t = Instant::now();
    let result = tokio::time::timeout(
        Duration::from_secs(2) + MARGIN + Duration::from_secs(5),
        client.upload_mesh(futures::stream::once(async { header }).chain_with(chunks)),
    )
    .await
    .expect("the trickled upload is ended by the server");
    eprintln!("gRPC trickled upload ended after {:?}", t.elapsed());
    let status = result.expect_err("a trickled upload fails");
    assert_eq!(status.code(), tonic::Code::DeadlineExceeded, "{status:?}");
    assert!(t.elapsed() <= Duration::from_secs(2) + MARGIN);
    // The connection (other streams) is untouched: the same channel still works.
    let res = client
        .get_job(v1::GetJobRequest {
            name: "jobs/00000000000000000000000000000000".into(),
        })
        .await;
    assert!(
        matches!(&res, Err(s) if s.code() == tonic::Code::NotFound || s.code() == tonic::Code::InvalidArgument),
        "{res:?}"
    );
    srv.stop().await;
}

/// `futures::StreamExt::chain`, spelled so the two streams' types need not match exactly.
trait ChainWith: futures::Stream + Sized {
    fn chain_with<S: futures::Stream<Item = Self::Item>>(
        self,
        other: S,
    ) -> futures::stream::Chain<Self, S> {
        futures::StreamExt::chain(self, other)
    }
}
impl<T: futures::Stream> ChainWith for T {}
