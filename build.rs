//! Generates the gRPC code from `proto/` and builds the web page (`web/`) at build time.
//!
//! protox (a protobuf compiler written in Rust) parses the .proto files, so a fresh machine needs
//! no system `protoc`; tonic-prost-build turns the descriptors into prost messages and tonic
//! server and client stubs in `OUT_DIR` (see docs/service-research.md §1). The encoded descriptor set
//! is written beside them for the reflection service.
//!
//! The web page (issue 13): `npm ci` in `web/` when `web/node_modules` is missing or the lock
//! file changed since the last install, then `node web/build.mjs OUT_DIR/web`, which bundles
//! the page with three.js and uPlot (esbuild), gzips each file and writes `assets.rs` for
//! `src/api/web.rs` to include. Needs node and npm (v20) and, for the first install, the npm
//! registry.

use std::path::PathBuf;
use std::process::Command;

/// The files we compile; their imports (vendored `proto/google/...` and protox's built-in
/// `google/protobuf/...`) are pulled in by protox.
const PROTOS: &[&str] = &["proto/willow/v1/fairing.proto"];

/// Include path for imports.
const INCLUDES: &[&str] = &["proto"];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // Rebuild when any proto changes, including vendored imports, and not on every source
    // change (the default when a build script prints no rerun-if line).
    println!("cargo:rerun-if-changed=proto");
    build_web()?;

    let mut compiler = protox::Compiler::new(INCLUDES)?;
    // Imports are needed in the set: prost resolves the google.* types from them, and a
    // reflection client asking for fairing.proto must be able to fetch its dependencies.
    // Source info carries the .proto comments into the generated rustdoc.
    compiler.include_imports(true).include_source_info(true);
    compiler.open_files(PROTOS)?;

    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out_dir.join("willow_descriptor.bin"),
        compiler.encode_file_descriptor_set(),
    )?;
    let fds = compiler.file_descriptor_set();

    tonic_prost_build::configure()
        // Generated clients are used by the integration tests and by Rust callers of the library.
        .build_client(true)
        .build_server(true)
        // Mesh chunks and frame positions are megabytes: `bytes::Bytes` hands them to the job
        // core and back without copying.
        .bytes(".willow.v1")
        // google.rpc.Status (Operation.error, Job.error) is tonic-types' own type, so the error
        // details it builds (ErrorInfo, BadRequest, …) and ours are the same Rust types.
        .extern_path(".google.rpc", "::tonic_types::pb")
        // The vendored Google comments hold indented examples that rustdoc would compile as
        // doctests (and fail); ours are written to be rustdoc-safe.
        .disable_comments([".google"])
        // One file with the nested `google::…` / `willow::v1` modules, so the generated
        // cross-package paths (`super::super::google::…`) resolve.
        .include_file("willow_proto.rs")
        // tonic-prost's codec, except that a request that does not decode is INVALID_ARGUMENT
        // rather than INTERNAL (src/api/codec.rs).
        .codec_path("crate::api::codec::ProtoCodec")
        .compile_fds(fds)?;
    Ok(())
}

/// Where `npm ci` records the lock file it installed from: when it differs from
/// `web/package-lock.json`, the packages are installed again.
const WEB_STAMP: &str = "node_modules/.willow-installed-package-lock.json";

/// Install the page's npm packages if needed, then bundle the page into `OUT_DIR/web`.
fn build_web() -> Result<(), Box<dyn std::error::Error>> {
    // Precisely the inputs of the page: not node_modules (npm ci rewrites it) nor target/.
    for input in [
        "web/package.json",
        "web/package-lock.json",
        "web/build.mjs",
        "web/src",
    ] {
        println!("cargo:rerun-if-changed={input}");
    }
    let web = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?).join("web");
    let lock = std::fs::read(web.join("package-lock.json"))?;
    let installed = std::fs::read(web.join(WEB_STAMP)).ok();
    if installed.as_deref() != Some(lock.as_slice()) {
        let npm = if cfg!(windows) { "npm.cmd" } else { "npm" };
        run(
            Command::new(npm)
                .args(["ci", "--no-audit", "--no-fund", "--loglevel=error"])
                .current_dir(&web),
            "`npm ci` in web/ (installs three.js, uPlot and esbuild from the lock file; needs \
             node and npm v20 and the npm registry)",
        )?;
        std::fs::write(web.join(WEB_STAMP), &lock)?;
    }
    let out = PathBuf::from(std::env::var("OUT_DIR")?).join("web");
    run(
        Command::new("node").arg(web.join("build.mjs")).arg(&out),
        "`node web/build.mjs` (bundles the web page)",
    )?;
    Ok(())
}

/// Run `cmd`; on failure, an error that says what was being done and how it failed.
fn run(cmd: &mut Command, what: &str) -> Result<(), Box<dyn std::error::Error>> {
    let status = cmd.status().map_err(|e| {
        format!(
            "willow build: {what}: could not start {:?}: {e}",
            cmd.get_program()
        )
    })?;
    if !status.success() {
        return Err(format!("willow build: {what} failed ({status}); see the output above").into());
    }
    Ok(())
}
