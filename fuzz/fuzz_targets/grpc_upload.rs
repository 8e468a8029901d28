//! The gRPC request decoding and `UploadMesh` assembly. The input is a sequence of messages,
//! each a 2-byte little-endian length and that many bytes (the last one takes the rest):
//! decoded as `UploadMeshChunk`s and assembled under a small upload limit (so the limit
//! checks are reachable), and the first one also decoded as a `CreateJobRequest` and turned
//! into a validated job spec. Every failure must be a client-error status, never a panic.
#![no_main]
willow_fuzz::capped_allocator!();

use libfuzzer_sys::fuzz_target;
use willow_service::api::grpc::fuzzing::{create_job, upload_mesh};

/// Upload limit of the assembly: small, so that inputs of a few KiB can exceed it.
const LIMIT: u64 = 4096;

fn client_fault(status: &tonic::Status) -> bool {
    use tonic::Code::*;
    matches!(
        status.code(),
        InvalidArgument | ResourceExhausted | OutOfRange | FailedPrecondition
    )
}

fuzz_target!(|data: &[u8]| {
    let mut messages: Vec<&[u8]> = Vec::new();
    let mut rest = data;
    while let [lo, hi, tail @ ..] = rest {
        let n = usize::from(u16::from_le_bytes([*lo, *hi])).min(tail.len());
        let (message, after) = tail.split_at(n);
        messages.push(message);
        rest = after;
    }
    if !rest.is_empty() {
        messages.push(rest);
    }
    if let Err(status) = upload_mesh(&messages, LIMIT) {
        assert!(client_fault(&status), "upload: {status:?}");
    }
    if let Err(status) = create_job(messages.first().copied().unwrap_or_default()) {
        assert!(client_fault(&status), "create_job: {status:?}");
    }
});
