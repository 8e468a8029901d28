//! What a NATS error means for the core: every error the backend meets is classed here, on
//! purpose, as [`Class::Transient`] (the server away, restarting or electing: retry, never
//! fail a job for it), [`Class::StorageFull`] (JetStream has no room: the same
//! `storage_full` as a full disk on the embedded backend) or [`Class::Permanent`] (a bug or
//! a refusal that retrying cannot change: `internal`).
//!
//! async-nats folds most server answers into an error kind with the server's text as its
//! source (`failed publishing object chunks: failed getting chunk ack: no stream found for
//! given subject`), and JetStream API errors carry their code only in that text (`… (code
//! 503, error code 10077)`). So the table matches fragments of the whole error chain,
//! lower-cased, first match wins; an error no row names is permanent, and logged as such.

use super::super::JobError;

/// What an error means for the caller.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Class {
    /// Retry shortly: a request answers 503 + `Retry-After` (gRPC `UNAVAILABLE`), a running
    /// job is retried or handed back to resume from its checkpoint.
    Transient,
    /// JetStream refused to store: 507 `storage_full` (gRPC `RESOURCE_EXHAUSTED`), a running
    /// job is re-queued and waits for room.
    StorageFull,
    /// Anything else: `internal`.
    Permanent,
}

/// The table: (fragment of the lower-cased error chain, its class, why). Storage rows come
/// first: "insufficient storage resources available" must not be read by a shorter
/// transient row, and a full stream answers with a 503 status of its own.
pub(crate) const TABLE: &[(&str, Class, &str)] = &[
    // --- JetStream has no room (server error codes as async-nats names them) ---
    (
        "insufficient storage resources",
        Class::StorageFull,
        "10047 STORAGE_RESOURCES_EXCEEDED: the server's max_file_store is reached",
    ),
    (
        "insufficient memory resources",
        Class::StorageFull,
        "10028 MEMORY_RESOURCES_EXCEEDED: the server's max_memory_store is reached",
    ),
    (
        "insufficient resources",
        Class::StorageFull,
        "10023 INSUFFICIENT_RESOURCES: the server cannot place or grow a stream",
    ),
    (
        "resource limits exceeded for account",
        Class::StorageFull,
        "10002 ACCOUNT_RESOURCES_EXCEEDED: the account's JetStream limits",
    ),
    (
        "maximum bytes exceeded",
        Class::StorageFull,
        "10077 STREAM_STORE_FAILED on a stream at its max_bytes (discard new)",
    ),
    (
        "no space left on device",
        Class::StorageFull,
        "10077 STREAM_STORE_FAILED: the server's own disk is full (ENOSPC)",
    ),
    (
        "disk quota exceeded",
        Class::StorageFull,
        "10077 STREAM_STORE_FAILED: the server's disk quota (EDQUOT)",
    ),
    // --- Refusals that retrying the same write cannot change ---
    (
        "maximum messages exceeded",
        Class::Permanent,
        "the jobs stream at its capacity: the queue's push reads it as queue_full before this table",
    ),
    (
        "max payload",
        Class::Permanent,
        "a message over the server's max_payload: the same message is refused again",
    ),
    // --- The server away, restarting, or not answering yet ---
    (
        "timed out",
        Class::Transient,
        "no answer in time: the server or the network is away",
    ),
    ("timeout", Class::Transient, "no answer in time"),
    (
        "no responders",
        Class::Transient,
        "nobody serves the JetStream API subject: the server is starting or shutting down",
    ),
    (
        "broken pipe",
        Class::Transient,
        "the connection dropped mid-write",
    ),
    ("disconnected", Class::Transient, "the client is reconnecting"),
    ("not connected", Class::Transient, "the client is reconnecting"),
    (
        "connection",
        Class::Transient,
        "connection refused, reset or closed: the server is away",
    ),
    (
        "no stream found",
        Class::Transient,
        "a publish while the server stops or starts JetStream (`failed getting chunk ack: no \
         stream found for given subject`): every stream is made at connect and is back after \
         the restart",
    ),
    (
        "stream not found",
        Class::Transient,
        "10059 STREAM_NOT_FOUND: a stream not yet recovered by a restarting server",
    ),
    (
        "consumer not found",
        Class::Transient,
        "10014 CONSUMER_NOT_FOUND: a consumer not yet recovered, or removed when idle (made again on demand)",
    ),
    (
        "jetstream not enabled",
        Class::Transient,
        "10039/10076: JetStream starting, or stopped by a shutting-down server",
    ),
    (
        "temporarily unavailable",
        Class::Transient,
        "10008 CLUSTER_NOT_AVAILABLE: JetStream system temporarily unavailable",
    ),
    (
        "leader",
        Class::Transient,
        "a stream or the meta group is electing a leader (no leader, leadership change)",
    ),
    (
        "maximum consumers limit reached",
        Class::Transient,
        "10026: consumers the server removes after their inactivity threshold free up",
    ),
    (
        "slow consumer",
        Class::Transient,
        "the server cut a subscription that fell behind: subscribe again",
    ),
];

/// The class of an error from its chain's text (see [`TABLE`]).
pub(crate) fn classify(text: &str) -> Class {
    let lower = text.to_ascii_lowercase();
    TABLE
        .iter()
        .find(|(fragment, _, _)| lower.contains(fragment))
        .map_or(Class::Permanent, |&(_, class, _)| class)
}

/// A NATS error as the core sees it, classed by [`TABLE`]. `what` says what was being done
/// (it is in the message, never in the match).
pub(crate) fn nats_err(what: &str, e: impl std::fmt::Display) -> JobError {
    let cause = e.to_string();
    let text = format!("nats: {what}: {cause}");
    match classify(&cause) {
        Class::Transient => JobError::Unavailable(text),
        Class::StorageFull => JobError::StorageFull { detail: text },
        Class::Permanent => JobError::Internal(text),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use async_nats::jetstream::context::{PublishError, PublishErrorKind};
    use async_nats::jetstream::object_store::{PutError, PutErrorKind};

    /// The errors as async-nats renders them: a kind whose source is the server's text.
    fn chunk_ack_error(server: &str) -> String {
        PutError::with_source(
            PutErrorKind::PublishChunks,
            format!("failed getting chunk ack: {server}"),
        )
        .to_string()
    }

    #[test]
    fn the_campaigns_blob_write_error_during_a_restart_is_transient() {
        let stream_gone = PublishError::new(PublishErrorKind::StreamNotFound).to_string();
        let text = chunk_ack_error(&stream_gone);
        assert_eq!(
            text,
            "failed publishing object chunks: failed getting chunk ack: no stream found for given subject"
        );
        assert_eq!(classify(&text), Class::Transient);
        assert!(matches!(
            nats_err("storing a blob", &text),
            JobError::Unavailable(m) if m.contains("no stream found")
        ));
    }

    #[test]
    fn outage_errors_are_transient() {
        let texts = [
            PublishError::new(PublishErrorKind::TimedOut).to_string(),
            PublishError::new(PublishErrorKind::BrokenPipe).to_string(),
            "request failed: no responders".to_string(),
            "timed out".to_string(),
            "failed to read: connection reset by peer".to_string(),
            "stream not found (code 404, error code 10059)".to_string(),
            "consumer not found (code 404, error code 10014)".to_string(),
            "jetstream not enabled (code 503, error code 10076)".to_string(),
            "JetStream system temporarily unavailable (code 503, error code 10008)".to_string(),
            "no suitable peers for placement: stream leader not found (code 503, error code 10005)"
                .to_string(),
            "maximum consumers limit reached (code 400, error code 10026)".to_string(),
        ];
        for t in texts {
            assert_eq!(classify(&t), Class::Transient, "{t}");
        }
    }

    #[test]
    fn jetstream_storage_refusals_are_storage_full() {
        let texts = [
            "insufficient storage resources available (code 503, error code 10047)",
            "insufficient memory resources available (code 503, error code 10028)",
            "insufficient resources (code 503, error code 10023)",
            "resource limits exceeded for account (code 400, error code 10002)",
            "maximum bytes exceeded (code 503, error code 10077)",
            "write /data/jetstream/x.blk: no space left on device (code 500, error code 10077)",
        ];
        for t in texts {
            assert_eq!(classify(t), Class::StorageFull, "{t}");
            let published = chunk_ack_error(t);
            assert_eq!(classify(&published), Class::StorageFull, "{published}");
            let e = nats_err("storing a blob", &published);
            assert_eq!(e.code(), "storage_full", "{published}");
            // The client is told to come back later, as for a full disk.
            assert!(e.retry_after_secs().is_some());
        }
    }

    #[test]
    fn refusals_and_unknown_errors_are_permanent() {
        let texts = [
            "maximum messages exceeded (code 503, error code 10077)".to_string(),
            PublishError::new(PublishErrorKind::MaxPayloadExceeded).to_string(),
            "wrong last sequence: 41".to_string(),
            "invalid object name".to_string(),
            "something nobody has seen before".to_string(),
        ];
        for t in texts {
            assert_eq!(classify(&t), Class::Permanent, "{t}");
            assert_eq!(nats_err("x", &t).code(), "internal", "{t}");
        }
    }

    /// Every row is reachable: no earlier row's fragment swallows it, so each row's class is
    /// what its own fragment classifies as.
    #[test]
    fn every_row_decides_its_own_fragment() {
        for (fragment, class, why) in TABLE {
            assert_eq!(classify(fragment), *class, "{fragment}: {why}");
            assert_eq!(
                *fragment,
                fragment.to_ascii_lowercase(),
                "fragments are lower case"
            );
        }
    }

    /// The message names what was being done and keeps the server's words.
    #[test]
    fn the_message_keeps_what_and_why() {
        let e = nats_err("reading a job", "timed out");
        assert_eq!(
            e.to_string(),
            "the job backend is unavailable: nats: reading a job: timed out"
        );
    }
}
