//! The embedded [`JobStore`]: SQLite (`willow.sqlite3` in the data dir, WAL mode) for jobs,
//! per-step metrics, idempotency keys and upload records. Blobs are files ([`super::files`]).
//!
//! One connection behind a mutex, used only from blocking threads: the workers write one small
//! transaction per step, which SQLite in WAL mode with `synchronous=NORMAL` commits in tens of
//! microseconds, so a single connection is not the bottleneck the flow step is.
//!
//! [`JobStore`]: crate::jobs::ports::JobStore

use super::super::codec::decode_metrics;
use super::super::ports::{over_quota, Admitting, Inserted, MinuteWindows, NewJob, Usage};
use super::super::{
    format_name, join_err, now_ms, parse_format, poisoned, JobError, JobId, JobSpec, JobState,
    JobStatus,
};
use base64::Engine as _;
use rusqlite::{params, Connection, OptionalExtension};
use std::fs;
use std::path::Path;
use std::sync::{Arc, Mutex};
use willow::metrics::StepMetrics;

mod schema;
mod store;
#[cfg(test)]
mod tests;

/// The SQLite job store: one connection behind a mutex, used on tokio's blocking pool.
#[derive(Clone)]
pub struct SqliteStore {
    conn: Arc<Mutex<Connection>>,
}

const STATUS_COLUMNS: &str =
    "id, state, spec, input_format, vertex_count, face_count, step, latest, \
     error, error_code, created_at, started_at, finished_at, expires_at, expired, seq, \
     tenant, input_bytes, report, planned_bytes";

/// The `report` column: what reading the upload changed or could not keep, as JSON (NULL when
/// there is nothing, and in rows from before the column).
#[derive(serde::Serialize, serde::Deserialize, Default)]
struct Report {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    repairs: Option<willow::mesh::io::Repairs>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    notes: Vec<String>,
}

/// A row as read, before the expiry check.
struct Row {
    status: JobStatus,
    expired: bool,
}

/// A job id is stored as its text…
impl rusqlite::ToSql for JobId {
    fn to_sql(&self) -> rusqlite::Result<rusqlite::types::ToSqlOutput<'_>> {
        self.as_str().to_sql()
    }
}

/// …and checked again as it is read.
impl rusqlite::types::FromSql for JobId {
    fn column_result(v: rusqlite::types::ValueRef<'_>) -> rusqlite::types::FromSqlResult<Self> {
        let text = String::column_result(v)?;
        JobId::try_from(text).map_err(|e| rusqlite::types::FromSqlError::Other(Box::new(e)))
    }
}

fn row_to_status(r: &rusqlite::Row<'_>) -> rusqlite::Result<Result<Row, JobError>> {
    let id: JobId = r.get(0)?;
    let state: String = r.get(1)?;
    let spec: String = r.get(2)?;
    let format: String = r.get(3)?;
    let latest: Option<Vec<u8>> = r.get(7)?;
    let get_u64 = |i: usize| -> rusqlite::Result<Option<u64>> {
        Ok(r.get::<_, Option<i64>>(i)?.map(|v| v.max(0) as u64))
    };
    let created_at = get_u64(10)?.unwrap_or(0);
    let started_at = get_u64(11)?;
    let finished_at = get_u64(12)?;
    let expires_at = get_u64(13)?;
    let vertex_count: i64 = r.get(4)?;
    let face_count: i64 = r.get(5)?;
    let step: i64 = r.get(6)?;
    let error: Option<String> = r.get(8)?;
    let error_code: Option<String> = r.get(9)?;
    let expired: i64 = r.get(14)?;
    let tenant: String = r.get(16)?;
    let input_bytes = get_u64(17)?.unwrap_or(0);
    let report: Option<String> = r.get(18)?;
    let planned_bytes = get_u64(19)?.unwrap_or(0);
    Ok((|| {
        let state = JobState::parse(&state)
            .ok_or_else(|| JobError::Internal(format!("unknown stored state `{state}`")))?;
        let spec: JobSpec = serde_json::from_str(&spec)
            .map_err(|e| JobError::Internal(format!("stored spec: {e}")))?;
        let input_format = parse_format(&format)
            .ok_or_else(|| JobError::Internal(format!("unknown stored format `{format}`")))?;
        let latest = latest.map(|b| decode_metrics(&b)).transpose()?;
        let report: Report = report
            .map(|r| serde_json::from_str(&r))
            .transpose()
            .map_err(|e| JobError::Internal(format!("stored report: {e}")))?
            .unwrap_or_default();
        Ok(Row {
            status: JobStatus {
                id,
                tenant,
                state,
                step: step.max(0) as usize,
                total_steps: spec.steps,
                spec,
                input_format,
                vertex_count: vertex_count.max(0) as usize,
                face_count: face_count.max(0) as usize,
                input_bytes,
                planned_bytes,
                latest,
                error,
                error_code,
                created_at,
                started_at,
                finished_at,
                expires_at,
                repairs: report.repairs,
                notes: report.notes,
            },
            expired: expired != 0,
        })
    })())
}

/// Unix ms as SQLite's integer.
fn ms(t: u64) -> i64 {
    i64::try_from(t).unwrap_or(i64::MAX)
}

impl SqliteStore {
    /// Open (creating if needed) `willow.sqlite3` in `dir`.
    pub fn open(dir: &Path) -> Result<SqliteStore, JobError> {
        fs::create_dir_all(dir)?;
        let conn = Connection::open(dir.join("willow.sqlite3"))?;
        schema::prepare(&conn)?;
        Ok(SqliteStore {
            conn: Arc::new(Mutex::new(conn)),
        })
    }

    fn conn(&self) -> Result<std::sync::MutexGuard<'_, Connection>, JobError> {
        self.conn.lock().map_err(poisoned)
    }

    /// Run `f` on the blocking pool: SQLite calls block.
    async fn blocking<T: Send + 'static>(
        &self,
        f: impl FnOnce(&SqliteStore) -> Result<T, JobError> + Send + 'static,
    ) -> Result<T, JobError> {
        let me = self.clone();
        tokio::task::spawn_blocking(move || f(&me))
            .await
            .map_err(join_err)?
    }

    fn row(&self, id: &str) -> Result<Row, JobError> {
        JobId::parse(id)?;
        let conn = self.conn()?;
        let row = conn
            .prepare_cached(&format!("SELECT {STATUS_COLUMNS} FROM jobs WHERE id = ?1"))?
            .query_row(params![id], row_to_status)
            .optional()?;
        match row {
            None => Err(JobError::NotFound(id.to_string())),
            Some(r) => r,
        }
    }

    /// The status of a live job: `NotFound` if unknown or another tenant's, `Gone` once
    /// expired (even before the sweeper deleted its files).
    fn status_now(&self, id: &str, tenant: Option<&str>) -> Result<JobStatus, JobError> {
        let row = self.row(id)?;
        if tenant.is_some_and(|t| t != row.status.tenant) {
            return Err(JobError::NotFound(id.to_string()));
        }
        let expired_now = row.status.expires_at.is_some_and(|t| t <= now_ms());
        if row.expired || expired_now {
            return Err(JobError::Gone(id.to_string()));
        }
        Ok(row.status)
    }

    fn idempotent_now(
        &self,
        tenant: &str,
        key: &str,
        hash: &str,
    ) -> Result<Option<JobStatus>, JobError> {
        let found: Option<(String, String)> = self
            .conn()?
            .prepare_cached("SELECT request_hash, job_id FROM idempotency WHERE key = ?1")?
            .query_row(params![scoped_key(tenant, key)], |r| {
                Ok((r.get(0)?, r.get(1)?))
            })
            .optional()?;
        match found {
            None => Ok(None),
            Some((stored, _)) if stored != hash => Err(JobError::IdempotencyMismatch(format!(
                "key `{key}` was first used with a different mesh or parameters"
            ))),
            Some((_, job_id)) => self.status_now(&job_id, Some(tenant)).map(Some),
        }
    }

    fn insert_now(&self, job: &NewJob) -> Result<Inserted, JobError> {
        let spec = serde_json::to_string(&job.spec)
            .map_err(|e| JobError::Internal(format!("spec: {e}")))?;
        let report = (job.repairs.is_some() || !job.notes.is_empty())
            .then(|| {
                serde_json::to_string(&Report {
                    repairs: job.repairs.clone(),
                    notes: job.notes.clone(),
                })
            })
            .transpose()
            .map_err(|e| JobError::Internal(format!("report: {e}")))?;
        {
            let mut conn = self.conn()?;
            let tx = conn.transaction()?;
            if let Some((key, hash)) = &job.idempotency {
                let found: Option<(String, String)> = tx
                    .prepare_cached("SELECT request_hash, job_id FROM idempotency WHERE key = ?1")?
                    .query_row(params![scoped_key(&job.tenant, key)], |r| {
                        Ok((r.get(0)?, r.get(1)?))
                    })
                    .optional()?;
                if let Some((stored, existing)) = found {
                    drop(tx);
                    drop(conn);
                    if &stored != hash {
                        return Err(JobError::IdempotencyMismatch(format!(
                            "key `{key}` was first used with a different mesh or parameters"
                        )));
                    }
                    return self
                        .status_now(&existing, Some(&job.tenant))
                        .map(Inserted::Existing);
                }
            }
            // In the transaction: concurrent submissions of one tenant cannot both take the
            // last unit of a quota.
            if job.quotas.any() {
                let usage = usage_on(&tx, &job.tenant, now_ms())?;
                let admitting = Admitting::Job {
                    received: job.received,
                };
                let bytes = job.input_bytes.saturating_add(job.planned_bytes);
                if let Some(over) = over_quota(&job.quotas, &usage, bytes, admitting) {
                    return Ok(Inserted::OverQuota(over));
                }
            }
            tx.prepare_cached(
                "INSERT INTO jobs (id, state, spec, input_format, vertex_count, face_count, created_at,
                                   tenant, input_bytes, received, callback_pending, report,
                                   planned_bytes)
                 VALUES (?1, 'queued', ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)",
            )?
            .execute(params![
                    job.id,
                    spec,
                    format_name(job.format),
                    job.vertex_count as i64,
                    job.face_count as i64,
                    ms(job.created_at),
                    job.tenant,
                    ms(job.input_bytes),
                    job.received,
                    job.spec.callback_url.is_some(),
                    report,
                    ms(job.planned_bytes)
                ],
            )?;
            if let Some((key, hash)) = &job.idempotency {
                tx.prepare_cached(
                    "INSERT INTO idempotency (key, request_hash, job_id) VALUES (?1, ?2, ?3)",
                )?
                .execute(params![scoped_key(&job.tenant, key), hash, job.id])?;
            }
            tx.commit()?;
        }
        self.status_now(&job.id, None).map(Inserted::New)
    }

    fn list_now(
        &self,
        tenant: &str,
        state: Option<JobState>,
        size: usize,
        token: Option<&str>,
    ) -> Result<(Vec<JobStatus>, Option<String>), JobError> {
        // Newest first by (created_at, id); the token is the last job of the previous page,
        // the tenant's own: a global sequence here would let a tenant count other tenants'
        // jobs between two of its pages.
        let before: Option<(i64, String)> = match token {
            None | Some("") => None,
            Some(t) => Some(
                base64::engine::general_purpose::URL_SAFE_NO_PAD
                    .decode(t)
                    .ok()
                    .and_then(|b| String::from_utf8(b).ok())
                    .and_then(|s| {
                        let (at, id) = s.strip_prefix("at:")?.split_once(':')?;
                        Some((at.parse().ok()?, id.to_string()))
                    })
                    .ok_or_else(|| JobError::InvalidSpec {
                        field: "page_token",
                        reason: "not a token this server returned".into(),
                    })?,
            ),
        };
        let (before_at, before_id) = before.map_or((None, None), |(t, id)| (Some(t), Some(id)));
        let now = ms(now_ms());
        let conn = self.conn()?;
        let sql = format!(
            "SELECT {STATUS_COLUMNS} FROM jobs
             WHERE tenant = ?5 AND expired = 0
               AND (?1 IS NULL OR created_at < ?1 OR (created_at = ?1 AND id < ?6))
               AND (expires_at IS NULL OR expires_at > ?2) AND (?3 IS NULL OR state = ?3)
             ORDER BY created_at DESC, id DESC LIMIT ?4"
        );
        let mut st = conn.prepare(&sql)?;
        let rows = st.query_map(
            params![
                before_at,
                now,
                state.map(|s| s.as_str()),
                (size + 1) as i64,
                tenant,
                before_id
            ],
            row_to_status,
        )?;
        let mut out = Vec::with_capacity(size + 1);
        for r in rows {
            out.push(r??);
        }
        let next = if out.len() > size {
            out.truncate(size);
            out.last().map(|r| {
                base64::engine::general_purpose::URL_SAFE_NO_PAD
                    .encode(format!("at:{}:{}", r.status.created_at, r.status.id))
            })
        } else {
            None
        };
        Ok((out.into_iter().map(|r| r.status).collect(), next))
    }

    fn frame_rows_now(
        &self,
        id: &str,
        from: usize,
        limit: usize,
    ) -> Result<Vec<(StepMetrics, bool)>, JobError> {
        let from = i64::try_from(from).unwrap_or(i64::MAX);
        let limit = i64::try_from(limit).unwrap_or(i64::MAX);
        let conn = self.conn()?;
        let mut st = conn.prepare(
            "SELECT metrics, has_positions FROM frames WHERE job_id = ?1 AND step >= ?2 ORDER BY step LIMIT ?3",
        )?;
        let rows = st.query_map(params![id, from, limit], |r| {
            Ok((r.get::<_, Vec<u8>>(0)?, r.get::<_, i64>(1)?))
        })?;
        let mut out = Vec::new();
        for r in rows {
            let (b, p) = r?;
            out.push((decode_metrics(&b)?, p != 0));
        }
        Ok(out)
    }
}

/// What `tenant` holds at `now` (see [`JobStore::usage`]): one row of `tenant_usage`, read
/// in the admission's transaction.
fn usage_on(conn: &Connection, tenant: &str, now: u64) -> Result<Usage, JobError> {
    let row: Option<(i64, i64, i64, i64, i64)> = conn
        .prepare_cached(
            "SELECT bytes, live, window_start, window_count, previous_count
             FROM tenant_usage WHERE tenant = ?1",
        )?
        .query_row(params![tenant], |r| {
            Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?, r.get(4)?))
        })
        .optional()?;
    // One row per tenant: the sum is cheap, and inside an admission's transaction it is
    // exact across tenants too (the server's disk budget).
    let server: i64 = conn
        .prepare_cached("SELECT COALESCE(SUM(bytes), 0) FROM tenant_usage")?
        .query_row([], |r| r.get(0))?;
    let n = |v: i64| u64::try_from(v).unwrap_or(0);
    let Some((bytes, live, window_start, current, previous)) = row else {
        return Ok(Usage {
            server_stored_bytes: n(server),
            ..Usage::default()
        });
    };
    Ok(Usage {
        server_stored_bytes: n(server),
        live_jobs: usize::try_from(n(live)).unwrap_or(usize::MAX),
        stored_bytes: n(bytes),
        uploads_last_minute: MinuteWindows {
            start: n(window_start),
            current: n(current),
            previous: n(previous),
        }
        .last_minute(now),
    })
}

/// Idempotency keys are per tenant: the stored key is the tenant, a `/` (which no tenant id
/// holds) and the client's key.
fn scoped_key(tenant: &str, key: &str) -> String {
    format!("{tenant}/{key}")
}
