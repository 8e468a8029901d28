//! Generates the gRPC code from `proto/` at build time.
//!
//! protox (a protobuf compiler written in Rust) parses the .proto files, so a fresh machine needs
//! no system `protoc`; tonic-prost-build turns the descriptors into prost messages and tonic
//! server and client stubs in `OUT_DIR` (see SERVICE-RESEARCH.md §1). The encoded descriptor set
//! is written beside them for the reflection service.

use std::path::PathBuf;

/// The files we compile; their imports (vendored `proto/google/...` and protox's built-in
/// `google/protobuf/...`) are pulled in by protox.
const PROTOS: &[&str] = &["proto/willow/v1/fairing.proto"];

/// Include path for imports.
const INCLUDES: &[&str] = &["proto"];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // Rebuild when any proto changes, including vendored imports, and not on every source
    // change (the default when a build script prints no rerun-if line).
    println!("cargo:rerun-if-changed=proto");

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
        .compile_fds(fds)?;
    Ok(())
}
