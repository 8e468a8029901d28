//! What can go wrong: [`JobError`], the error of every call into the job core, and
//! [`FailureCode`], why a job ended without running all its steps (stored with the job as
//! `JobStatus::error_code`). Each transport maps both once, in `api::status`.

use willow::curve::CurveError;
use willow::flow::FlowError;
use willow::mesh::MeshError;

/// Everything that can go wrong, typed so each transport maps it once to its own codes
/// (`api::status` holds that one table). Ids in it are the text the caller sent, which need
/// not be a valid [`JobId`](super::JobId).
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("job `{0}` not found")]
    NotFound(String),
    #[error("job `{0}` has expired and its results were deleted")]
    Gone(String),
    #[error("the queue is full ({capacity} jobs waiting); retry in about {retry_after_secs} s")]
    QueueFull {
        retry_after_secs: u64,
        capacity: usize,
    },
    /// A tenant's quota ([`TenantQuotas`](super::TenantQuotas)) is spent: retry once its jobs
    /// finish or age out.
    #[error("tenant quota `{quota}` of {limit} is spent{}; retry in about {retry_after_secs} s", quota_detail(.used))]
    QuotaExceeded {
        quota: &'static str,
        limit: u64,
        used: Option<u64>,
        retry_after_secs: u64,
    },
    #[error("invalid mesh: {0}")]
    InvalidMesh(MeshError),
    #[error("invalid parameter `{field}`: {reason}")]
    InvalidSpec { field: &'static str, reason: String },
    #[error("{what} exceeds the limit of {limit}")]
    TooLarge { what: &'static str, limit: u64 },
    /// `refine` would make more `what` (triangles or vertices) than the limits allow: known
    /// from the upload's size and the target edge before any level is built (issue 42).
    #[error(
        "`refine` would make {planned} {what}, more than the limit of {limit}: a longer \
         `refine_edge` (each doubling makes a quarter of the triangles) or no `refine`"
    )]
    RefineTooLarge {
        what: &'static str,
        planned: u64,
        limit: u64,
    },
    #[error("{0}")]
    Conflict(String),
    #[error("idempotency key reused with a different request: {0}")]
    IdempotencyMismatch(String),
    #[error("the server is shutting down and accepts no new jobs")]
    ShuttingDown,
    #[error("internal error: {0}")]
    Internal(String),
    /// The backend's server did not answer in time (NATS restarting, a network partition):
    /// retry shortly. A running job that meets it is left to be delivered again and resumes
    /// from its checkpoint; it is never failed for it.
    #[error("the job backend is unavailable: {0}")]
    Unavailable(String),
    /// The data dir's file system (or SQLite's database in it) has no room left: ENOSPC,
    /// EDQUOT, `SQLITE_FULL`. Not the request's fault and not a bug: retryable once space is
    /// freed (the expiry sweep, a DELETE, an operator). A running job that meets it is
    /// re-queued and resumes from its checkpoint; it is never failed for it. `detail` names
    /// files and is for the log, never for the client (hence not in the message).
    #[error("the server's storage is full; retry once space has been freed")]
    StorageFull { detail: String },
    /// A step that exists but kept no positions, or a step past the job's progress.
    #[error("job `{id}` has no mesh for step {step}: {detail}")]
    FrameNotFound {
        id: String,
        step: usize,
        detail: String,
    },
    /// An upload id that [`Jobs::store_upload`](super::Jobs::store_upload) never returned (or that expired).
    #[error("upload `{0}` not found")]
    UploadNotFound(String),
    /// A curve the curve flow refuses (see [`CurveError`]).
    #[error("invalid curve: {0}")]
    InvalidCurve(CurveError),
    /// Every slot for synchronous work is taken (curve fairing); retry shortly.
    #[error("all {slots} curve slots are busy; retry in about {retry_after_secs} s")]
    Busy { retry_after_secs: u64, slots: usize },
    /// The server's download memory budget had no room for a download's render within the
    /// wait ([`super::render_memory`]); retry shortly. `wanted`: the render's estimate;
    /// `budget`: the server's, both in bytes.
    #[error("the server's memory for downloads ({budget} bytes) has no room to render this one ({wanted} bytes) now; retry in about {retry_after_secs} s")]
    DownloadsBusy {
        retry_after_secs: u64,
        wanted: u64,
        budget: u64,
    },
    /// A synchronous request ran out of its time budget.
    #[error("deadline of {secs} s exceeded after step {step} of {steps}")]
    DeadlineExceeded {
        secs: f64,
        step: usize,
        steps: usize,
    },
    /// The flow broke down on this input (non-finite positions).
    #[error("numerical failure at step {step}: {reason}")]
    Numerical { step: usize, reason: String },
}

impl JobError {
    /// A stable machine-readable code, shared by every transport.
    pub fn code(&self) -> &'static str {
        match self {
            JobError::NotFound(_) => "not_found",
            JobError::Gone(_) => "gone",
            JobError::QueueFull { .. } => "queue_full",
            JobError::QuotaExceeded { .. } => "quota_exceeded",
            JobError::InvalidMesh(e) => e.code(),
            JobError::InvalidSpec { .. } => "invalid_parameter",
            JobError::TooLarge { .. } | JobError::RefineTooLarge { .. } => "too_large",
            JobError::Conflict(_) => "conflict",
            JobError::IdempotencyMismatch(_) => "idempotency_mismatch",
            JobError::ShuttingDown => "shutting_down",
            JobError::Internal(_) => "internal",
            JobError::Unavailable(_) => "unavailable",
            JobError::StorageFull { .. } => "storage_full",
            JobError::FrameNotFound { .. } => "frame_not_found",
            JobError::UploadNotFound(_) => "upload_not_found",
            JobError::InvalidCurve(e) => curve_error_code(e),
            JobError::Busy { .. } => "busy",
            JobError::DownloadsBusy { .. } => "downloads_busy",
            JobError::DeadlineExceeded { .. } => "deadline_exceeded",
            JobError::Numerical { .. } => "numerical",
        }
    }
}

impl JobError {
    /// Whether retrying the same request may succeed, and after how many seconds: decided here
    /// once, for every transport (HTTP `Retry-After`, gRPC `RetryInfo`). `None`: retrying as it
    /// is cannot help.
    pub fn retry_after_secs(&self) -> Option<u64> {
        match self {
            JobError::QueueFull {
                retry_after_secs, ..
            }
            | JobError::QuotaExceeded {
                retry_after_secs, ..
            }
            | JobError::Busy {
                retry_after_secs, ..
            }
            | JobError::DownloadsBusy {
                retry_after_secs, ..
            } => Some(*retry_after_secs),
            // Another replica (or this one after restart) can take it shortly.
            JobError::ShuttingDown => Some(SHUTDOWN_RETRY_SECS),
            // NATS restarting or a partition healing: seconds, not minutes.
            JobError::Unavailable(_) => Some(2),
            // Space comes back when the sweeper or a client deletes results, or an operator
            // acts: the readiness probe re-checks every `STORAGE_PROBE_SECS`.
            JobError::StorageFull { .. } => Some(STORAGE_FULL_RETRY_SECS),
            _ => None,
        }
    }
}

/// The retry hint of [`JobError::StorageFull`]: a few of the readiness probe's periods.
pub const STORAGE_FULL_RETRY_SECS: u64 = 30;

/// The retry hint of [`JobError::ShuttingDown`]: about as long as a replica takes to restart.
const SHUTDOWN_RETRY_SECS: u64 = 5;

/// A stable machine-readable code per curve refusal, shared by every transport (like
/// `MeshError::code` for meshes).
pub fn curve_error_code(e: &CurveError) -> &'static str {
    match e {
        CurveError::TooFewPoints { .. } => "too_few_points",
        CurveError::NonFinite { .. } => "non_finite",
        CurveError::ZeroLengthEdge { .. } => "zero_length_edge",
        CurveError::Cusp { .. } => "cusp",
        CurveError::Json(_) => "invalid_json",
        CurveError::Obj { .. } => "invalid_obj",
        CurveError::InvalidParameter { .. } => "invalid_parameter",
        CurveError::OutOfMemory { .. } => "out_of_memory",
    }
}

fn quota_detail(used: &Option<u64>) -> String {
    used.map(|u| format!(" ({u} in use)")).unwrap_or_default()
}

impl From<rusqlite::Error> for JobError {
    fn from(e: rusqlite::Error) -> Self {
        // SQLITE_FULL is what SQLite answers when a write meets ENOSPC (and when the database
        // reaches `max_page_count`); an I/O error whose cause is ENOSPC counts the same.
        if e.sqlite_error_code() == Some(rusqlite::ErrorCode::DiskFull) {
            return JobError::StorageFull {
                detail: format!("store: {e}"),
            };
        }
        JobError::Internal(format!("store: {e}"))
    }
}

impl From<std::io::Error> for JobError {
    fn from(e: std::io::Error) -> Self {
        if is_storage_full(&e) {
            return JobError::StorageFull {
                detail: format!("file: {e}"),
            };
        }
        JobError::Internal(format!("file: {e}"))
    }
}

/// ENOSPC (`StorageFull`) or a user's disk quota (EDQUOT, `QuotaExceeded`): no room to write.
pub fn is_storage_full(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded
    )
}

/// Why a job failed, was cancelled or (`NoProgress`) stopped early: the machine-readable
/// outcome of a finished job. Stored as its text ([`FailureCode::as_str`]) in
/// `JobStatus::error_code`, in SQLite rows and NATS records alike, so the strings never change:
/// records written by older versions read back as the same code.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FailureCode {
    /// Cancelled by its owner, while queued or between two steps.
    Cancelled,
    /// The job's wall-clock budget ran out between two steps.
    DeadlineExceeded,
    /// The flow broke down on this input (non-finite positions).
    Numerical,
    /// The stored upload no longer reads as a mesh.
    InvalidMesh,
    /// A parameter the flow refuses on this mesh.
    InvalidParameter,
    /// The flow cannot handle this mesh (e.g. an option its topology does not allow).
    Unsupported,
    /// A failure of the server itself (store, files, a panic in the flow).
    Internal,
    /// Delivered more than `Config::max_deliveries` times without any worker finishing it.
    Redelivered,
    /// Lost the race for the queue's last slot; the record is deleted at once.
    QueueFull,
    /// On a **succeeded** job: the safeguard found no acceptable step and stopped early.
    NoProgress,
    /// On a **succeeded** job: its run ended before its steps for this reason (`converged`,
    /// `target_reached`, `max_deviation`, `feature_scale_reached`, `stalled`, `already_fair`:
    /// the outcome's own name, `willow::flow::stopping`). The result is the surface the run
    /// ended on.
    EndedEarly(willow::flow::stopping::Outcome),
}

impl FailureCode {
    /// Every code, for tests and documentation.
    pub const ALL: [FailureCode; 10] = [
        FailureCode::Cancelled,
        FailureCode::DeadlineExceeded,
        FailureCode::Numerical,
        FailureCode::InvalidMesh,
        FailureCode::InvalidParameter,
        FailureCode::Unsupported,
        FailureCode::Internal,
        FailureCode::Redelivered,
        FailureCode::QueueFull,
        FailureCode::NoProgress,
    ];

    /// The stored and wire text (`deadline_exceeded`, …).
    pub fn as_str(self) -> &'static str {
        match self {
            FailureCode::Cancelled => "cancelled",
            FailureCode::DeadlineExceeded => "deadline_exceeded",
            FailureCode::Numerical => "numerical",
            FailureCode::InvalidMesh => "invalid_mesh",
            FailureCode::InvalidParameter => "invalid_parameter",
            FailureCode::Unsupported => "unsupported",
            FailureCode::Internal => "internal",
            FailureCode::Redelivered => "redelivered",
            FailureCode::QueueFull => "queue_full",
            FailureCode::NoProgress => "no_progress",
            FailureCode::EndedEarly(outcome) => outcome.name(),
        }
    }

    /// The note a succeeded job keeps for how its run ended: none when it ran its steps.
    pub fn of_outcome(outcome: willow::flow::stopping::Outcome) -> Option<FailureCode> {
        use willow::flow::stopping::Outcome;
        match outcome {
            Outcome::Completed => None,
            Outcome::NoProgress => Some(FailureCode::NoProgress),
            other => Some(FailureCode::EndedEarly(other)),
        }
    }

    /// The inverse of [`FailureCode::as_str`]; `None` for a text this version does not know.
    pub fn parse(s: &str) -> Option<FailureCode> {
        FailureCode::ALL
            .into_iter()
            .find(|c| c.as_str() == s)
            .or_else(|| FailureCode::of_outcome(willow::flow::stopping::Outcome::parse(s)?))
    }

    /// The outcome of a flow that refused or broke down.
    pub fn of_flow(e: &FlowError) -> FailureCode {
        match e {
            FlowError::InvalidParameter { .. } => FailureCode::InvalidParameter,
            FlowError::Unsupported(_) => FailureCode::Unsupported,
            FlowError::Numerical { .. } => FailureCode::Numerical,
            FlowError::NoProgress { .. } => FailureCode::NoProgress,
        }
    }
}

impl std::fmt::Display for FailureCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run that ended early keeps its outcome's own name as its code, and reads back.
    #[test]
    fn early_ends_are_stored_by_their_outcome_name() {
        use willow::flow::stopping::Outcome;
        assert_eq!(FailureCode::of_outcome(Outcome::Completed), None);
        assert_eq!(
            FailureCode::of_outcome(Outcome::NoProgress),
            Some(FailureCode::NoProgress)
        );
        for o in Outcome::ALL
            .into_iter()
            .filter(|&o| o != Outcome::Completed)
        {
            let code = FailureCode::of_outcome(o).expect("an early end");
            assert_eq!(code.as_str(), o.name());
            assert_eq!(FailureCode::parse(o.name()), Some(code));
        }
        assert_eq!(FailureCode::parse("completed"), None);
    }

    #[test]
    fn failure_codes_read_back_from_their_stored_text() {
        // The texts older versions stored: each must still parse to its code.
        let stored = [
            "cancelled",
            "deadline_exceeded",
            "numerical",
            "invalid_mesh",
            "invalid_parameter",
            "unsupported",
            "internal",
            "redelivered",
            "queue_full",
            "no_progress",
        ];
        for text in stored {
            let code = FailureCode::parse(text).unwrap_or_else(|| panic!("{text} parses"));
            assert_eq!(code.as_str(), text);
        }
        assert_eq!(FailureCode::ALL.len(), stored.len());
        assert_eq!(FailureCode::parse("no_such_code"), None);
    }
}
