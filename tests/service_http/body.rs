//! Oversized bodies are read (up to a bound) before they are refused, over raw sockets.

use super::*;

/// A plain TCP connection to the test server and its `host:port`, for requests sent byte by
/// byte (a body cut in two, chunked framing) where a client library would send them whole.
async fn raw_connection(srv: &TestServer) -> (tokio::net::TcpStream, String) {
    let addr = srv
        .base
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_string();
    let socket = tokio::net::TcpStream::connect(&addr)
        .await
        .expect("connect");
    (socket, addr)
}

/// Fails if the server answers within half a second: it must still be reading the body.
async fn assert_still_reading(socket: &mut tokio::net::TcpStream) {
    use tokio::io::AsyncReadExt;
    let mut answer = vec![0u8; 4096];
    let early = tokio::time::timeout(Duration::from_millis(500), socket.read(&mut answer)).await;
    assert!(
        early.is_err(),
        "answered before the body was read: {:?}",
        early.map(|r| r.map(|n| String::from_utf8_lossy(&answer[..n]).into_owned()))
    );
}

/// The start of the server's answer (status line, headers, the body's first bytes), within 10 s.
async fn read_answer(socket: &mut tokio::net::TcpStream) -> String {
    use tokio::io::AsyncReadExt;
    let mut answer = vec![0u8; 4096];
    let n = tokio::time::timeout(Duration::from_secs(10), socket.read(&mut answer))
        .await
        .expect("an answer")
        .expect("read");
    String::from_utf8_lossy(&answer[..n]).into_owned()
}

/// A body announced over the limit is still read (up to a bound) before the 413 goes out, so
/// a client that is still sending reads the refusal instead of a broken pipe (CI saw
/// `BrokenPipe` on a 120 KB curve against a 64 KB limit). Over a raw socket: while half the
/// body is sent, no answer comes; once all of it is, the 413 does.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_body_is_read_before_it_is_refused() {
    use tokio::io::AsyncWriteExt;
    let srv = start(|c| c.limits.max_curve_bytes = 64 * 1024).await;
    let body = vec![b' '; 128 * 1024];
    let (mut socket, addr) = raw_connection(&srv).await;
    let head = format!(
        "POST /v1/curves:fair HTTP/1.1\r\nhost: {addr}\r\ncontent-type: application/json\r\n\
         content-length: {}\r\n\r\n",
        body.len()
    );
    socket.write_all(head.as_bytes()).await.expect("head");
    socket
        .write_all(&body[..body.len() / 2])
        .await
        .expect("half");
    assert_still_reading(&mut socket).await;
    socket
        .write_all(&body[body.len() / 2..])
        .await
        .expect("the rest");
    let text = read_answer(&mut socket).await;
    assert!(text.starts_with("HTTP/1.1 413"), "{text}");
    srv.stop().await;
}

/// A multipart upload sent without a length that grows past the limit and the multipart slack
/// is read on (up to the drain's bound) before its 413, as a raw body is: the parser's own
/// error used to answer at the bound, while the client was still sending.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_chunked_multipart_upload_is_read_before_it_is_refused() {
    use tokio::io::AsyncWriteExt;
    let limit = 64 * 1024;
    let srv = start(|c| c.limits.max_upload_bytes = limit).await;
    let bound = limit as usize + (1 << 20); // the limit and the multipart slack
    let mut body = b"--b\r\ncontent-disposition: form-data; name=\"mesh\"; filename=\"m.obj\"\r\n\
                     content-type: model/obj\r\n\r\n"
        .to_vec();
    body.resize(bound + 700 * 1024, b' ');
    let chunk = |data: &[u8]| {
        let mut framed = format!("{:x}\r\n", data.len()).into_bytes();
        framed.extend_from_slice(data);
        framed.extend_from_slice(b"\r\n");
        framed
    };
    let (mut socket, addr) = raw_connection(&srv).await;
    let head = format!(
        "POST /v1/jobs HTTP/1.1\r\nhost: {addr}\r\n\
         content-type: multipart/form-data; boundary=b\r\ntransfer-encoding: chunked\r\n\r\n"
    );
    socket.write_all(head.as_bytes()).await.expect("head");
    // Past the bound: the server must be draining, not answering.
    let first = bound + 300 * 1024;
    socket
        .write_all(&chunk(&body[..first]))
        .await
        .expect("past the bound");
    assert_still_reading(&mut socket).await;
    socket
        .write_all(&chunk(&body[first..]))
        .await
        .expect("the rest");
    socket.write_all(b"0\r\n\r\n").await.expect("the end");
    let text = read_answer(&mut socket).await;
    assert!(text.starts_with("HTTP/1.1 413"), "{text}");
    assert!(text.contains("too_large"), "{text}");
    srv.stop().await;
}
