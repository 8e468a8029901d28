//! Half-open connections are closed, the connection and per-connection request limits hold,
//! and long responses (SSE, gRPC server streams) outlive every timeout.

use super::*;

#[tokio::test]
async fn forty_half_open_connections_are_closed_and_do_not_block_others() {
    let srv = start(limits(|_| {})).await;
    let timeout = Duration::from_secs(2);
    let opened = Instant::now();
    let mut idle = Vec::new();
    for _ in 0..40 {
        idle.push(TcpStream::connect(addr(&srv)).await.expect("connect"));
    }
    let slowest = normal_clients(&srv.base).await;
    eprintln!("with 40 half-open connections, slowest normal request {slowest:?}");
    assert!(
        slowest < Duration::from_secs(2),
        "normal requests took {slowest:?}"
    );
    let mut last = opened;
    for s in &mut idle {
        let left = (opened + timeout + MARGIN).saturating_duration_since(Instant::now());
        let (sent, closed) = read_until_closed(s, left).await;
        let closed = closed.expect("a half-open connection is closed within the timeout");
        assert!(sent.is_empty() || String::from_utf8_lossy(&sent).starts_with("HTTP/1.1 408"));
        last = last.max(closed);
    }
    let all = last - opened;
    eprintln!("40 half-open connections all closed {all:?} after opening (timeout {timeout:?})");
    assert!(
        all >= timeout - Duration::from_millis(500),
        "closed at {all:?}"
    );
    assert!(all <= timeout + MARGIN);
    srv.stop().await;
}

#[tokio::test]
async fn at_the_connection_limit_new_connections_wait_until_one_closes() {
    let srv = start(limits(|c| {
        c.max_connections = 3;
        c.header_read_timeout = Duration::from_secs(60);
        c.idle_timeout = Duration::from_secs(60);
    }))
    .await;
    let mut held = Vec::new();
    for _ in 0..3 {
        held.push(TcpStream::connect(addr(&srv)).await.expect("connect"));
    }
    // The fourth connects (the kernel's backlog) but is not served…
    let mut fourth = TcpStream::connect(addr(&srv)).await.expect("connect");
    fourth
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: willow\r\nConnection: close\r\n\r\n")
        .await
        .expect("send");
    let mut byte = [0u8; 1];
    let early = tokio::time::timeout(Duration::from_millis(1500), fourth.peek(&mut byte)).await;
    assert!(early.is_err(), "served beyond the connection limit");
    // …until one of the three closes.
    drop(held.remove(0));
    let t = Instant::now();
    let res = tokio::time::timeout(Duration::from_secs(10), read_response(&mut fourth))
        .await
        .expect("served once a connection closed")
        .expect("a response");
    eprintln!(
        "queued connection served {:?} after a slot freed",
        t.elapsed()
    );
    assert_eq!(res.status, 200);
    srv.stop().await;
}

#[tokio::test]
async fn requests_per_connection_are_limited() {
    let srv = start(limits(|c| {
        c.max_requests_per_connection = 3;
        c.header_read_timeout = Duration::from_secs(30);
        c.idle_timeout = Duration::from_secs(30);
    }))
    .await;
    let mut s = TcpStream::connect(addr(&srv)).await.expect("connect");
    for n in 1..=3 {
        s.write_all(HEALTHZ).await.expect("send");
        let res = read_response(&mut s).await.expect("a response");
        assert_eq!(res.status, 200);
        if n < 3 {
            assert_eq!(res.header("connection"), None, "request {n}");
        } else {
            assert_eq!(res.header("connection"), Some("close"), "request {n}");
        }
    }
    let (_, closed) = read_until_closed(&mut s, MARGIN).await;
    assert!(
        closed.is_some(),
        "the connection closes after the 3rd response"
    );

    // HTTP/2 (gRPC): the 3rd request starts a graceful GOAWAY; the channel reconnects and
    // every call succeeds.
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    let channel = tonic::transport::Channel::from_shared(srv.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("h2c");
    let mut health = HealthClient::new(channel);
    for n in 0..10 {
        health
            .check(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .unwrap_or_else(|e| panic!("call {n}: {e:?}"));
    }
    srv.stop().await;
}

#[tokio::test]
async fn sse_and_grpc_streams_outlive_the_timeouts() {
    use willow_service::api::grpc::pb::willow::v1;
    use willow_service::api::grpc::pb::willow::v1::stream_frames_response::Event;
    let srv = start(limits(|c| {
        c.header_read_timeout = Duration::from_secs(1);
        c.body_timeout = Duration::from_secs(1);
        c.idle_timeout = Duration::from_secs(1);
        c.keepalive_interval = Duration::from_secs(1);
    }))
    .await;
    // The only worker is busy with a long job; the job under test waits behind it.
    let (status, _, blocker) = srv
        .submit_obj(&slow_obj(), "steps=10000&until_converged=false")
        .await;
    assert_eq!(status, 202, "{blocker}");
    let blocker = blocker["id"].as_str().expect("id").to_string();
    srv.poll_until(&blocker, Duration::from_secs(60), |v| {
        v["state"] == "running"
    })
    .await;
    let (status, _, job) = srv
        .submit_obj(&small_obj(), "steps=4&frame_interval=1")
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();

    let opened = Instant::now();
    let sse = fresh_client()
        .get(srv.url(&format!("/v1/jobs/{id}/events")))
        .send()
        .await
        .expect("SSE");
    assert_eq!(sse.status(), 200);
    let channel = tonic::transport::Channel::from_shared(srv.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("h2c");
    let mut grpc = v1::fairing_client::FairingClient::new(channel)
        .stream_frames(v1::StreamFramesRequest {
            name: format!("jobs/{id}"),
            from_step: 0,
        })
        .await
        .expect("StreamFrames")
        .into_inner();

    // Well past every timeout, then let the job run.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let res = fresh_client()
        .post(srv.url(&format!("/v1/jobs/{blocker}/cancel")))
        .send()
        .await
        .expect("cancel");
    assert!(res.status().is_success(), "{}", res.status());

    let grpc_events = async {
        let mut events = Vec::new();
        while let Some(m) = grpc.message().await.expect("the gRPC stream stays healthy") {
            events.push(m.event.expect("an event"));
        }
        events
    };
    let (events, grpc_events) = tokio::join!(read_sse(sse, Duration::from_secs(120)), async {
        tokio::time::timeout(Duration::from_secs(120), grpc_events)
            .await
            .expect("the gRPC stream ends")
    });
    let open = opened.elapsed();
    eprintln!(
        "SSE and gRPC streams open {open:?} (idle/header/body timeouts 1 s): {} SSE events, {} gRPC events",
        events.len(),
        grpc_events.len()
    );
    assert!(open >= Duration::from_secs(3));
    let done = events.last().expect("SSE events");
    assert_eq!(done.event, "done", "{events:?}");
    assert!(events.iter().any(|e| e.event == "frame"), "{events:?}");
    assert!(grpc_events.iter().any(|e| matches!(e, Event::Frame(_))));
    match grpc_events.last() {
        Some(Event::Job(job)) => {
            assert_eq!(job.state, v1::job::State::Succeeded as i32, "{job:?}")
        }
        other => panic!("the gRPC stream ends with the job, got {other:?}"),
    }
    srv.stop().await;
}
