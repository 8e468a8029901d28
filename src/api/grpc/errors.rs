//! Errors: where a [`JobError`] becomes a [`tonic::Status`] (`job_error`, and `curve_error`
//! for `FairCurve`) and a failed job a `google.rpc.Status` (`job_failure`): the code from the
//! one table in [`crate::api::status`], the google.rpc error details the proto documents.

use std::collections::HashMap;
use std::time::Duration;

use tonic::{Code, Request, Status};
use tonic_types::{ErrorDetails, StatusExt};

use crate::api::problem::cap_detail;
use crate::api::status;
use crate::jobs::{Caller, JobError};

/// `google.rpc.ErrorInfo.domain` of the errors this service produces.
pub(super) const ERROR_DOMAIN: &str = "willow.v1";

/// Longest user-supplied text echoed back in an error message: a 1 MB bogus name must not
/// become a 1 MB status message (which would also exceed header size limits).
const MAX_ECHO_CHARS: usize = 80;

/// The caller the authentication layer put on the request (HTTP extensions reach tonic's
/// request). None means the layer did not run for this route: refused, never served as anyone.
pub(super) fn caller<T>(request: &Request<T>) -> Result<Caller, Status> {
    request
        .extensions()
        .get::<Caller>()
        .cloned()
        .ok_or_else(|| Status::unauthenticated("this call needs credentials and none were checked"))
}

/// INVALID_ARGUMENT with a `google.rpc.BadRequest` naming `field` (a path in the request, as
/// AIP-193 asks: `params.tau`, `inline_mesh.data`, …).
pub(super) fn bad_request(field: &str, description: impl Into<String>) -> Status {
    let description = cap_detail(description.into());
    Status::with_error_details(
        Code::InvalidArgument,
        cap_detail(format!("invalid `{field}`: {description}")),
        ErrorDetails::with_bad_request_violation(field, description),
    )
}

/// The request field a job-core parameter name corresponds to. The core names nested fields
/// by their JSON path (`filter.k`, `boundary.prescribed.axis.fixed`), which the proto mirrors
/// under `params`.
fn spec_field(core_field: &str) -> String {
    match core_field {
        "deadline_secs" => "params.deadline".into(),
        "idempotency_key" => "request_id".into(),
        "boundary.prescribed.angles.per_loop" => {
            "params.boundary.prescribed.angles.per_loop.values".into()
        }
        // Fields of the request itself rather than of its JobParams.
        "page_token" => core_field.into(),
        // The job spec as a whole.
        "params" => "params".into(),
        // Every other field is a JobSpec field, named as in JobParams: a new flow option
        // needs no entry here.
        spec_field => format!("params.{spec_field}"),
    }
}

/// Map a job-core error to its status. `mesh_field` is the request field that carried the mesh
/// (or the job name), so field violations point at what the client sent. The code comes from
/// the one table ([`status::of_error`]) and the retry hint from the core; the details are
/// gRPC's own.
pub(super) fn job_error(err: JobError, mesh_field: &str) -> Status {
    let code = status::of_error(&err).grpc;
    if let JobError::Internal(detail) = &err {
        // The detail may name files and SQL: log it, don't send it.
        tracing::error!(error = %detail, "internal error in a gRPC call");
        return Status::internal("internal error");
    }
    // The core's messages may echo user input (a parameter value, a parser's complaint about
    // the mesh): capped so the status stays small enough to travel in a header.
    let message = cap_detail(err.to_string());
    let mut details = ErrorDetails::new();
    if let Some(secs) = err.retry_after_secs() {
        details.set_retry_info(Some(Duration::from_secs(secs)));
    }
    match &err {
        JobError::NotFound(id) => {
            details.set_resource_info(
                "willow.v1.Job",
                format!("jobs/{}", clip(id)),
                "",
                "no such job",
            );
        }
        JobError::Gone(id) => {
            details.set_resource_info(
                "willow.v1.Job",
                format!("jobs/{}", clip(id)),
                "",
                "the job expired and its results were deleted",
            );
            details.set_error_info("EXPIRED", ERROR_DOMAIN, HashMap::new());
        }
        JobError::UploadNotFound(id) => {
            details.set_resource_info(
                "willow.v1.Upload",
                format!("uploads/{}", clip(id)),
                "",
                "no such upload (uploads expire like jobs)",
            );
        }
        JobError::FrameNotFound { id, step, detail } => {
            details.set_resource_info(
                "willow.v1.Frame",
                format!("jobs/{}/frames/{step}", clip(id)),
                "",
                detail.clone(),
            );
        }
        JobError::QueueFull { capacity, .. } => {
            details.set_error_info(
                "QUEUE_FULL",
                ERROR_DOMAIN,
                HashMap::from([("capacity".to_string(), capacity.to_string())]),
            );
        }
        JobError::QuotaExceeded {
            quota, limit, used, ..
        } => {
            details.add_quota_failure_violation(
                format!("tenant_quota:{quota}"),
                format!("tenant quota `{quota}` of {limit} is spent"),
            );
            let mut meta = HashMap::from([
                ("quota".to_string(), quota.to_string()),
                ("limit".to_string(), limit.to_string()),
            ]);
            if let Some(used) = used {
                meta.insert("used".to_string(), used.to_string());
            }
            details.set_error_info("QUOTA_EXCEEDED", ERROR_DOMAIN, meta);
        }
        JobError::StorageFull { detail } => {
            // The file names stay in the log; the client learns which resource ran out.
            tracing::warn!(error = %detail, "storage full in a gRPC call");
            details.add_quota_failure_violation(
                "storage",
                "the server's data volume is full; retry once space has been freed",
            );
            details.set_error_info("STORAGE_FULL", ERROR_DOMAIN, HashMap::new());
        }
        JobError::InvalidMesh(mesh) => {
            details.add_bad_request_violation(mesh_field, cap_detail(mesh.to_string()));
            details.set_error_info(
                mesh.code().to_ascii_uppercase(),
                ERROR_DOMAIN,
                HashMap::new(),
            );
        }
        JobError::InvalidSpec { field, reason } => {
            details.add_bad_request_violation(spec_field(field), cap_detail(reason.clone()));
        }
        JobError::TooLarge {
            what: "steps",
            limit,
        } => {
            details.add_bad_request_violation(
                "params.steps",
                format!("must be at most {limit} (the server's limit)"),
            );
        }
        // The refinement the request asks for, too large: its parameter named.
        JobError::RefineTooLarge { what, limit, .. } => {
            details.add_quota_failure_violation(
                format!("refined {what}"),
                format!("refined {what} exceed the limit of {limit}"),
            );
            details.add_bad_request_violation("params.refine", cap_detail(err.to_string()));
        }
        // A mesh over a size limit: the limit named, and no RetryInfo (retrying cannot help).
        JobError::TooLarge { what, limit } => {
            details
                .add_quota_failure_violation(*what, format!("{what} exceeds the limit of {limit}"));
            details.add_bad_request_violation(
                mesh_field,
                format!("{what} exceeds the limit of {limit}"),
            );
        }
        JobError::Conflict(reason) => {
            details.add_precondition_failure_violation("STATE", mesh_field, reason.clone());
        }
        JobError::IdempotencyMismatch(_) => {
            details.add_bad_request_violation(
                "request_id",
                "already used for a different request; use a new request_id",
            );
            details.set_error_info("REQUEST_ID_REUSED", ERROR_DOMAIN, HashMap::new());
        }
        JobError::InvalidCurve(curve) => {
            details.add_bad_request_violation(mesh_field, cap_detail(curve.to_string()));
            details.set_error_info(
                crate::jobs::curve::curve_error_code(curve).to_ascii_uppercase(),
                ERROR_DOMAIN,
                HashMap::new(),
            );
        }
        JobError::Busy { slots, .. } => {
            details.set_error_info(
                "BUSY",
                ERROR_DOMAIN,
                HashMap::from([("slots".to_string(), slots.to_string())]),
            );
        }
        JobError::Numerical { .. } => {
            details.set_error_info("NUMERICAL", ERROR_DOMAIN, HashMap::new());
        }
        JobError::DownloadsBusy { wanted, budget, .. } => {
            details.set_error_info(
                "DOWNLOADS_BUSY",
                ERROR_DOMAIN,
                HashMap::from([
                    ("scope".to_string(), "render".to_string()),
                    ("wanted_bytes".to_string(), wanted.to_string()),
                    ("budget_bytes".to_string(), budget.to_string()),
                ]),
            );
        }
        JobError::Unavailable(detail) => {
            tracing::warn!(error = %detail, "backend unavailable in a gRPC call");
        }
        JobError::ShuttingDown | JobError::DeadlineExceeded { .. } | JobError::Internal(_) => {}
    }
    Status::with_error_details(code, message, details)
}

/// Map a [`Jobs::fair_curve`](crate::jobs::Jobs::fair_curve) error: its parameters are top-level fields of
/// `FairCurveRequest` (not `params.*` as for jobs), and the curve is `curve.xy`.
pub(super) fn curve_error(err: JobError) -> Status {
    match err {
        JobError::InvalidSpec { field, reason } => {
            let field = match field {
                "deadline_secs" => "deadline",
                "curve" => "curve.xy",
                other => other,
            };
            bad_request(field, reason)
        }
        // A step count over the limit is a parameter out of range, as for jobs.
        JobError::TooLarge {
            what: "steps",
            limit,
        } => bad_request(
            "steps",
            format!("must be at most {limit} (the server's limit for curves)"),
        ),
        other => job_error(other, "curve.xy"),
    }
}

/// At most [`MAX_ECHO_CHARS`] characters of user input, for error messages.
pub(super) fn clip(s: &str) -> String {
    if s.chars().count() <= MAX_ECHO_CHARS {
        s.to_string()
    } else {
        let mut out: String = s.chars().take(MAX_ECHO_CHARS).collect();
        out.push('…');
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn queue_full_carries_retry_info() {
        let status = job_error(
            JobError::QueueFull {
                retry_after_secs: 7,
                capacity: 3,
            },
            "inline_mesh.data",
        );
        assert_eq!(status.code(), Code::ResourceExhausted);
        let retry = status.get_details_retry_info().and_then(|r| r.retry_delay);
        assert_eq!(retry, Some(Duration::from_secs(7)));
    }

    #[test]
    fn storage_full_is_resource_exhausted_with_quota_failure_and_retry_info() {
        let status = job_error(
            JobError::StorageFull {
                detail: "file: /data/jobs/x: No space left on device".into(),
            },
            "inline_mesh.data",
        );
        assert_eq!(status.code(), Code::ResourceExhausted);
        assert!(!status.message().contains("/data"), "{}", status.message());
        let retry = status.get_details_retry_info().and_then(|r| r.retry_delay);
        assert_eq!(
            retry,
            Some(Duration::from_secs(crate::jobs::STORAGE_FULL_RETRY_SECS))
        );
        let quota = status.get_details_quota_failure().expect("QuotaFailure");
        assert_eq!(quota.violations[0].subject, "storage");
        let info = status.get_details_error_info().expect("ErrorInfo");
        assert_eq!(info.reason, "STORAGE_FULL");
    }

    #[test]
    fn spec_fields_map_to_request_paths() {
        let status = job_error(
            JobError::InvalidSpec {
                field: "deadline_secs",
                reason: "too long".into(),
            },
            "upload",
        );
        assert_eq!(status.code(), Code::InvalidArgument);
        let fields: Vec<String> = status
            .get_details_bad_request()
            .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
            .unwrap_or_default();
        assert_eq!(fields, vec!["params.deadline".to_string()]);
        for (core, wire) in [
            ("filter.k", "params.filter.k"),
            ("exactness", "params.exactness"),
            ("max_deviation", "params.max_deviation"),
            ("region", "params.region"),
            ("page_token", "page_token"),
            (
                "boundary.prescribed.axis.fixed",
                "params.boundary.prescribed.axis.fixed",
            ),
            (
                "boundary.prescribed.angles.per_loop",
                "params.boundary.prescribed.angles.per_loop.values",
            ),
        ] {
            assert_eq!(spec_field(core), wire);
        }
    }
}
