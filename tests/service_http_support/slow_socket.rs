//! The real server on a loopback listener whose accepted sockets have a small, fixed send
//! buffer, for the slow-reader tests: a client that does not read blocks the server's writes
//! after a few KiB. (Linux: accepted sockets inherit the listener's buffer. With the kernel's
//! autotuning a loopback socket absorbs up to 4 MiB, more than the results a test can afford
//! to compute.)

use std::time::Duration;
use tokio::net::TcpSocket;
use willow_service::api::server::{serve_with, ServeOptions};
use willow_service::jobs::{Config, Jobs};

/// Start it with one worker and `options`: its address, the sender that shuts it down, and
/// the job core.
pub async fn start(options: ServeOptions) -> (String, tokio::sync::oneshot::Sender<()>, Jobs) {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = Config::new(dir.path());
    config.workers = 1;
    let (jobs, core) = Jobs::start(config).await.expect("job core starts");
    let socket = TcpSocket::new_v4().expect("socket");
    socket.set_send_buffer_size(16 << 10).expect("SO_SNDBUF");
    socket
        .bind("127.0.0.1:0".parse().expect("address"))
        .expect("bind loopback");
    let listener = socket.listen(1024).expect("listen");
    let addr = listener.local_addr().expect("local addr").to_string();
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let handle = jobs.clone();
    tokio::spawn(async move {
        let _dir = dir;
        let shutdown = async move {
            let _ = rx.await;
        };
        serve_with(
            listener,
            jobs,
            core,
            shutdown,
            Duration::from_secs(2),
            options,
        )
        .await
    });
    (addr, tx, handle)
}
