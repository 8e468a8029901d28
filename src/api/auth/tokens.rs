//! Stream tokens: short-lived HMAC tokens bound to (tenant, job), minted by an authenticated
//! call and accepted only as `?access_token=` on that job's events and frame downloads.

use super::keys::random_bytes;
use super::{Auth, Refusal, B64, STREAM_TOKEN_PREFIX};
use crate::api::problem::Problem;
use crate::jobs::{rfc3339, Caller, Jobs};
use axum::extract::{Path, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::{Extension, Json, Router};
use base64::Engine as _;
use serde::{Deserialize, Serialize};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

pub(super) struct StreamTokens {
    pub(super) key: ring::hmac::Key,
    pub(super) ttl: Duration,
}

/// What a stream token says (signed, not secret).
#[derive(Serialize, Deserialize)]
struct StreamClaims {
    /// Tenant.
    t: String,
    /// Subject.
    s: String,
    /// Job id.
    j: String,
    /// Expiry, Unix seconds.
    e: u64,
}

pub(super) fn now_secs() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

impl StreamTokens {
    pub(super) fn new(secret: Option<&[u8]>, ttl: Duration) -> Result<StreamTokens, String> {
        let key = match secret {
            Some(s) if s.len() < 32 => {
                return Err("--stream-token-secret-file must hold at least 32 bytes".into())
            }
            Some(s) => ring::hmac::Key::new(ring::hmac::HMAC_SHA256, s),
            None => {
                let mut s = [0u8; 32];
                random_bytes(&mut s)?;
                ring::hmac::Key::new(ring::hmac::HMAC_SHA256, &s)
            }
        };
        Ok(StreamTokens { key, ttl })
    }

    /// `wst_<base64url claims>.<base64url HMAC-SHA256(claims)>` and its expiry (Unix secs).
    pub(super) fn mint(&self, caller: &Caller, job_id: &str) -> (String, u64) {
        let exp = now_secs().saturating_add(self.ttl.as_secs().max(1));
        let claims = StreamClaims {
            t: caller.tenant.clone(),
            s: caller.subject.clone(),
            j: job_id.to_string(),
            e: exp,
        };
        let payload = serde_json::to_vec(&claims).unwrap_or_default();
        let tag = ring::hmac::sign(&self.key, &payload);
        let token = format!(
            "{STREAM_TOKEN_PREFIX}{}.{}",
            B64.encode(&payload),
            B64.encode(tag.as_ref())
        );
        (token, exp)
    }

    /// The caller a token for `job_id` stands for. The MAC is checked first (in constant
    /// time, by ring), so nothing of an unsigned payload is trusted.
    pub(super) fn verify(&self, token: &str, job_id: &str) -> Result<Caller, Refusal> {
        let bad = || Refusal::invalid("invalid_token", "the stream token is not valid");
        let rest = token.strip_prefix(STREAM_TOKEN_PREFIX).ok_or_else(bad)?;
        let (payload, tag) = rest.split_once('.').ok_or_else(bad)?;
        let payload = B64.decode(payload).map_err(|_| bad())?;
        let tag = B64.decode(tag).map_err(|_| bad())?;
        ring::hmac::verify(&self.key, &payload, &tag).map_err(|_| bad())?;
        let claims: StreamClaims = serde_json::from_slice(&payload).map_err(|_| bad())?;
        if claims.e <= now_secs() {
            return Err(Refusal::invalid(
                "expired_token",
                "the stream token has expired; mint another with POST /v1/jobs/{id}/stream-token",
            ));
        }
        if claims.j != job_id {
            return Err(Refusal::invalid(
                "invalid_token",
                "the stream token was minted for another job",
            ));
        }
        Caller::new(&claims.t, &claims.s).map_err(|_| bad())
    }
}

// ---------------------------------------------------------------------------------------------
// Minting stream tokens

/// A stream token: pass it as `?access_token=` to the job's events (`EventSource`) or frame
/// downloads.
#[derive(Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StreamToken {
    /// The token. Valid only for this job, until `expires_at`.
    pub token: String,
    /// RFC 3339 UTC.
    pub expires_at: String,
    /// Seconds from now.
    pub expires_in: u64,
}

#[derive(Clone)]
pub struct MintState {
    jobs: Jobs,
    auth: Auth,
}

/// `POST /v1/jobs/{id}/stream-token`, to merge into the REST routes (behind the layer).
pub fn routes(jobs: Jobs, auth: Auth) -> Router {
    Router::new()
        .route("/v1/jobs/{id}/stream-token", post(mint_stream_token))
        .with_state(MintState { jobs, auth })
}

/// A short-lived token for this job's events and frames, for clients that cannot send headers
/// (a browser's `EventSource`): `GET /v1/jobs/{id}/events?access_token=…`.
#[utoipa::path(post, path = "/v1/jobs/{id}/stream-token", tag = "jobs",
    params(("id" = String, Path)),
    responses((status = 200, description = "A token for `?access_token=` on this job's events and frames", body = StreamToken),
        (status = 401, description = "No or bad credentials", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json")))]
pub async fn mint_stream_token(
    State(st): State<MintState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Response {
    let instance = format!("/v1/jobs/{id}/stream-token");
    // The caller's own job only: another tenant's is 404, like one that does not exist.
    if let Err(e) = st.jobs.get(&caller, &id).await {
        return Problem::from(e).instance(instance).into_response();
    }
    let (token, exp) = st.inner_mint(&caller, &id);
    let body = StreamToken {
        token,
        expires_at: rfc3339(exp.saturating_mul(1000)),
        expires_in: exp.saturating_sub(now_secs()),
    };
    let mut res = (StatusCode::OK, Json(body)).into_response();
    res.headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    res
}

impl MintState {
    fn inner_mint(&self, caller: &Caller, job_id: &str) -> (String, u64) {
        self.auth.inner.stream.mint(caller, job_id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stream_tokens_bind_job_and_expire() {
        let st = StreamTokens::new(None, Duration::from_secs(60)).unwrap();
        let caller = Caller::new("acme", "ci").unwrap();
        let (token, _) = st.mint(&caller, "job-a");
        assert_eq!(st.verify(&token, "job-a").unwrap(), caller);
        assert_eq!(
            st.verify(&token, "job-b").unwrap_err().reason,
            "invalid_token"
        );
        // Another process's secret: refused.
        let other = StreamTokens::new(None, Duration::from_secs(60)).unwrap();
        assert!(other.verify(&token, "job-a").is_err());
        // A tampered payload: refused.
        let forged = token.replacen("wst_e", "wst_f", 1);
        assert!(st.verify(&forged, "job-a").is_err());
        let e = st.verify("garbage", "job-a").unwrap_err();
        assert!(!e.detail.contains("garbage"));
    }
}
