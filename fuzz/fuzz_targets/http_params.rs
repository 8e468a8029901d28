//! The job parameters of `POST /v1/jobs`: the query string (`spec_from_query`: the dotted
//! generic parameters through the spec's JSON, the compact `boundary.*` and `region.*` forms
//! through serde_urlencoded) or, when the input starts with a NUL byte, the rest as a
//! multipart `params` JSON part; then the core's validation. Errors must be 4xx problems,
//! never panics.
#![no_main]
willow_fuzz::capped_allocator!();

use libfuzzer_sys::fuzz_target;
use willow_service::api::http::fuzzing::create_job_params;

fuzz_target!(|data: &[u8]| {
    let result = match data.split_first() {
        Some((0, json)) => create_job_params("", Some(json)),
        _ => match std::str::from_utf8(data) {
            Ok(query) => create_job_params(query, None),
            // hyper refuses a request target that is not visible ASCII.
            Err(_) => return,
        },
    };
    if let Err(problem) = result {
        let status = problem.status.as_u16();
        assert!(
            (400..500).contains(&status),
            "a parameter error is {status}: {problem:?}"
        );
    }
});
