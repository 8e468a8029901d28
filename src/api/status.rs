//! The one table of outcomes: the HTTP status and the gRPC code that each job-core error
//! ([`JobError`]) and each failed job's outcome ([`FailureCode`]) answers with. The rest is
//! decided in the core, once for both transports: the machine-readable code is
//! [`JobError::code`] (the problem `code`, the gRPC `ErrorInfo.reason`) and retryability is
//! [`JobError::retry_after_secs`] (`Retry-After`, `RetryInfo`). What each transport adds to the
//! body (problem extensions, google.rpc details) is its own: [`super::problem`] and
//! `grpc::errors`.

use crate::jobs::{FailureCode, JobError, JobState};
use axum::http::StatusCode;
use tonic::Code;

/// How one error answers on each transport.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Statuses {
    pub http: StatusCode,
    pub grpc: Code,
}

/// The statuses of a call that failed with `e`.
pub fn of_error(e: &JobError) -> Statuses {
    let (http, grpc) = match e {
        JobError::NotFound(_) | JobError::FrameNotFound { .. } | JobError::UploadNotFound(_) => {
            (StatusCode::NOT_FOUND, Code::NotFound)
        }
        // gRPC has no "gone": NOT_FOUND, with ErrorInfo `EXPIRED`.
        JobError::Gone(_) => (StatusCode::GONE, Code::NotFound),
        // The server's disk budget, not the caller's quota: what the request needs cannot be
        // stored (507, RFC 4918 §11.5), for any tenant, until stored data expires.
        JobError::QuotaExceeded {
            quota: "server_stored_bytes",
            ..
        } => (StatusCode::INSUFFICIENT_STORAGE, Code::ResourceExhausted),
        JobError::QueueFull { .. } | JobError::QuotaExceeded { .. } | JobError::Busy { .. } => {
            (StatusCode::TOO_MANY_REQUESTS, Code::ResourceExhausted)
        }
        JobError::InvalidMesh(_) | JobError::InvalidCurve(_) => {
            (StatusCode::UNPROCESSABLE_ENTITY, Code::InvalidArgument)
        }
        JobError::InvalidSpec { .. } => (StatusCode::BAD_REQUEST, Code::InvalidArgument),
        // A step count over the limit is a parameter out of range, not a resource.
        JobError::TooLarge { what: "steps", .. } => {
            (StatusCode::PAYLOAD_TOO_LARGE, Code::InvalidArgument)
        }
        // A mesh over a size limit: RESOURCE_EXHAUSTED as gRPC itself answers an oversized
        // message.
        JobError::TooLarge { .. } | JobError::RefineTooLarge { .. } => {
            (StatusCode::PAYLOAD_TOO_LARGE, Code::ResourceExhausted)
        }
        JobError::Conflict(_) => (StatusCode::CONFLICT, Code::FailedPrecondition),
        JobError::IdempotencyMismatch(_) => (StatusCode::UNPROCESSABLE_ENTITY, Code::AlreadyExists),
        JobError::ShuttingDown | JobError::Unavailable(_) | JobError::DownloadsBusy { .. } => {
            (StatusCode::SERVICE_UNAVAILABLE, Code::Unavailable)
        }
        // 507 Insufficient Storage (RFC 4918 §11.5): the server cannot store what the request
        // needs. gRPC: RESOURCE_EXHAUSTED, whose definition names "the entire file system is
        // out of space", with RetryInfo: space comes back (sweep, DELETE), unlike UNAVAILABLE
        // it is not a blip a client should retry within seconds.
        JobError::StorageFull { .. } => (StatusCode::INSUFFICIENT_STORAGE, Code::ResourceExhausted),
        // 504 as google.rpc maps DEADLINE_EXCEEDED: the server gave up within the budget.
        JobError::DeadlineExceeded { .. } => (StatusCode::GATEWAY_TIMEOUT, Code::DeadlineExceeded),
        // The input is valid but the flow broke down on it: not the client's fault, not a
        // server bug, not retryable as it is. gRPC: UNKNOWN plus the reason, as a failed job.
        JobError::Numerical { .. } => (StatusCode::UNPROCESSABLE_ENTITY, Code::Unknown),
        JobError::Internal(_) => (StatusCode::INTERNAL_SERVER_ERROR, Code::Internal),
    };
    Statuses { http, grpc }
}

/// The gRPC code of a finished job's `google.rpc.Status` (Job.error, Operation.error), from
/// its state and its stored outcome (`None`: none stored, or one this version does not know).
pub fn of_failure(state: JobState, code: Option<FailureCode>) -> Code {
    match (state, code) {
        // google.longrunning: a cancelled operation's error has code CANCELLED.
        (JobState::Cancelled, _) | (_, Some(FailureCode::Cancelled)) => Code::Cancelled,
        (_, Some(FailureCode::DeadlineExceeded)) => Code::DeadlineExceeded,
        (_, Some(FailureCode::InvalidMesh | FailureCode::InvalidParameter)) => {
            Code::InvalidArgument
        }
        (_, Some(FailureCode::Unsupported)) => Code::Unimplemented,
        (_, Some(FailureCode::Internal)) => Code::Internal,
        // A numerical breakdown of the flow on this mesh, a job no worker could finish: not the
        // client's fault, not a server bug, not retryable. UNKNOWN plus the reason says so.
        (
            _,
            Some(
                FailureCode::Numerical
                | FailureCode::Redelivered
                | FailureCode::QueueFull
                | FailureCode::NoProgress
                | FailureCode::EndedEarly(_),
            )
            | None,
        ) => Code::Unknown,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_job_answers_as_the_call_that_failed_the_same_way() {
        // The outcomes a job shares with a synchronous call: the same gRPC code either way.
        let pairs = [
            (
                FailureCode::InvalidParameter,
                JobError::InvalidSpec {
                    field: "tau",
                    reason: "bad".into(),
                },
            ),
            (
                FailureCode::DeadlineExceeded,
                JobError::DeadlineExceeded {
                    secs: 1.0,
                    step: 1,
                    steps: 2,
                },
            ),
            (
                FailureCode::Numerical,
                JobError::Numerical {
                    step: 1,
                    reason: "nan".into(),
                },
            ),
            (FailureCode::Internal, JobError::Internal("x".into())),
        ];
        for (code, err) in pairs {
            assert_eq!(
                of_failure(JobState::Failed, Some(code)),
                of_error(&err).grpc,
                "{code}"
            );
        }
    }

    /// A full disk: 507 and RESOURCE_EXHAUSTED, retryable (space comes back), whether the
    /// file system or SQLite said so.
    #[test]
    fn a_full_disk_answers_507_and_resource_exhausted() {
        let io = JobError::from(std::io::Error::from(std::io::ErrorKind::StorageFull));
        let sqlite = JobError::from(rusqlite::Error::SqliteFailure(
            rusqlite::ffi::Error::new(rusqlite::ffi::SQLITE_FULL),
            None,
        ));
        for e in [io, sqlite] {
            assert_eq!(e.code(), "storage_full", "{e:?}");
            assert_eq!(
                of_error(&e),
                Statuses {
                    http: StatusCode::INSUFFICIENT_STORAGE,
                    grpc: Code::ResourceExhausted
                }
            );
            assert!(e.retry_after_secs().is_some_and(|s| s >= 1));
        }
        let other = JobError::from(std::io::Error::from(std::io::ErrorKind::PermissionDenied));
        assert_eq!(of_error(&other).http, StatusCode::INTERNAL_SERVER_ERROR);
    }

    #[test]
    fn cancelled_jobs_answer_cancelled_whatever_their_code() {
        for code in FailureCode::ALL.map(Some).into_iter().chain([None]) {
            assert_eq!(of_failure(JobState::Cancelled, code), Code::Cancelled);
        }
        assert_eq!(of_failure(JobState::Failed, None), Code::Unknown);
    }

    #[test]
    fn retryable_errors_answer_429_or_503() {
        let retryable = [
            JobError::QueueFull {
                retry_after_secs: 3,
                capacity: 1,
            },
            JobError::Busy {
                retry_after_secs: 1,
                slots: 1,
            },
            JobError::ShuttingDown,
            JobError::Unavailable("nats".into()),
            JobError::DownloadsBusy {
                retry_after_secs: 5,
                wanted: 2048,
                budget: 1024,
            },
        ];
        for e in retryable {
            assert!(e.retry_after_secs().is_some(), "{e}");
            let s = of_error(&e);
            assert!(
                matches!(
                    (s.http, s.grpc),
                    (StatusCode::TOO_MANY_REQUESTS, Code::ResourceExhausted)
                        | (StatusCode::SERVICE_UNAVAILABLE, Code::Unavailable)
                ),
                "{e}: {s:?}"
            );
        }
        assert_eq!(JobError::Internal("x".into()).retry_after_secs(), None);
    }
}
