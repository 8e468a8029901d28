//! Interop: a Python grpcio client, generated from `proto/` by grpcio-tools, against the real
//! `willow serve` binary on an ephemeral loopback port (gRPC merged into the HTTP router).
//!
//! The client is `tests/python/client_test.py`; its pinned packages live in `.venv`, made by
//! `scripts/python-env.sh` (which `scripts/test.sh` runs). A missing `.venv` fails this test
//! with that instruction, unless `WILLOW_SKIP_PYTHON=1` says to skip it on purpose.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

mod service_http_support;
use service_http_support::obj_text;
use willow::mesh::generate;
use willow::mesh::io::{Asset, Format};

/// How long the server gets to print its address, and the Python suite to finish. Bounded so
/// a hang fails the test instead of stalling CI; generous for a loaded 2-core machine.
const SERVER_START: Duration = Duration::from_secs(60);
const CLIENT_RUN: Duration = Duration::from_secs(600);

/// Kills the child on drop, so a failed assertion never leaves a server running.
struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Writes the meshes the Python suite uses and returns their paths by flag name.
fn write_meshes(dir: &Path) -> Vec<(&'static str, PathBuf)> {
    let small = obj_text(&generate::bumpy_sphere(2, 0.1));
    let asset = Asset::read(
        small.as_bytes(),
        Format::Obj,
        &willow::mesh::Limits::default(),
    )
    .expect("generated OBJ parses");
    let glb = asset
        .write(&asset.surface().positions, Format::Glb)
        .expect("GLB writes");
    let files: [(&str, &str, Vec<u8>); 4] = [
        ("--small-obj", "small.obj", small.into_bytes()),
        ("--small-glb", "small.glb", glb),
        // 163 842 vertices, ~16 MiB: only a chunked upload can carry it.
        (
            "--large-obj",
            "large.obj",
            obj_text(&generate::icosphere(7)).into_bytes(),
        ),
        // 2562 vertices: thousands of steps keep the one worker busy.
        (
            "--slow-obj",
            "slow.obj",
            obj_text(&generate::bumpy_sphere(4, 0.1)).into_bytes(),
        ),
    ];
    files
        .into_iter()
        .map(|(flag, name, bytes)| {
            let path = dir.join(name);
            std::fs::write(&path, bytes).expect("write mesh file");
            (flag, path)
        })
        .collect()
}

/// Start `willow serve` on 127.0.0.1:0 and return it with the `host:port` it printed.
fn start_server(data_dir: &Path) -> (KillOnDrop, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_willow"))
        .args(["serve", "--addr", "127.0.0.1:0", "--workers", "1"])
        .args(["--queue-capacity", "1", "--log-format", "text"])
        .arg("--data-dir")
        .arg(data_dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn willow serve");
    let stdout = child.stdout.take().expect("piped stdout");
    let server = KillOnDrop(child);
    let (tx, rx) = mpsc::channel();
    // Keep reading stdout for the server's whole life: logs go there too, and a full pipe
    // would block the server.
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(addr) = line.trim().strip_prefix("listening on http://") {
                let _ = tx.send(addr.to_string());
            }
        }
    });
    let addr = rx
        .recv_timeout(SERVER_START)
        .expect("`willow serve` printed `listening on http://ADDR`");
    (server, addr)
}

#[test]
fn python_grpcio_client_against_willow_serve() {
    if std::env::var("WILLOW_SKIP_PYTHON").as_deref() == Ok("1") {
        eprintln!("skipped: WILLOW_SKIP_PYTHON=1");
        return;
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = root.join(".venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run scripts/test.sh (or scripts/python-env.sh) to create the Python \
         environment of this test, or set WILLOW_SKIP_PYTHON=1 to skip it",
        python.display()
    );

    let dir = tempfile::tempdir().expect("temp dir");
    let meshes = write_meshes(dir.path());
    let (_server, addr) = start_server(&dir.path().join("data"));

    let mut command = Command::new(&python);
    command
        .arg(root.join("tests/python/client_test.py"))
        .args(["--addr", &addr])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    for (flag, path) in &meshes {
        command.arg(flag).arg(path);
    }
    let mut client = KillOnDrop(command.spawn().expect("run the Python client"));

    // Read both pipes on threads so neither can fill up while we wait with a deadline.
    let mut stdout = client.0.stdout.take().expect("piped stdout");
    let mut stderr = client.0.stderr.take().expect("piped stderr");
    let out = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut stdout, &mut s);
        s
    });
    let err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut stderr, &mut s);
        s
    });
    let started = Instant::now();
    let status = loop {
        if let Some(status) = client.0.try_wait().expect("wait for the client") {
            break Some(status);
        }
        if started.elapsed() > CLIENT_RUN {
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    drop(client); // kills it if it timed out
    let out = out.join().unwrap_or_default();
    let err = err.join().unwrap_or_default();
    let report = format!("--- client stdout ---\n{out}\n--- client stderr ---\n{err}");
    let status = status.unwrap_or_else(|| panic!("the Python client timed out\n{report}"));
    assert!(
        status.success(),
        "the Python client failed ({status})\n{report}"
    );
    assert!(
        out.contains(" passed, 0 failed"),
        "no closing summary from the client\n{report}"
    );
}
