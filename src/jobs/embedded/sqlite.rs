//! The embedded [`JobStore`]: SQLite (`willow.sqlite3` in the data dir, WAL mode) for jobs,
//! per-step metrics, idempotency keys and upload records. Blobs are files ([`super::files`]).
//!
//! One connection behind a mutex, used only from blocking threads: the workers write one small
//! transaction per step, which SQLite in WAL mode with `synchronous=NORMAL` commits in tens of
//! microseconds, so a single connection is not the bottleneck the flow step is.

use super::super::codec::{decode_metrics, encode_metrics};
use super::super::ports::{over_quota, Inserted, JobStore, NewJob, Recovered, Swept, Usage};
use super::super::{
    format_name, join_err, now_ms, parse_format, poisoned, JobError, JobSpec, JobState, JobStatus,
};
use crate::mesh::io::Format;
use crate::metrics::StepMetrics;
use async_trait::async_trait;
use base64::Engine as _;
use rusqlite::{params, Connection, OptionalExtension};
use std::fs;
use std::path::Path;
use std::sync::{Arc, Mutex};

/// How long a connection waits for a lock held by another connection (only relevant if an
/// operator opens the database alongside the server) before failing the call.
const BUSY_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS jobs (
    seq             INTEGER PRIMARY KEY AUTOINCREMENT,
    id              TEXT NOT NULL UNIQUE,
    state           TEXT NOT NULL,
    spec            TEXT NOT NULL,
    input_format    TEXT NOT NULL,
    vertex_count    INTEGER NOT NULL,
    face_count      INTEGER NOT NULL,
    step            INTEGER NOT NULL DEFAULT 0,
    latest          BLOB,
    error           TEXT,
    error_code      TEXT,
    created_at      INTEGER NOT NULL,
    started_at      INTEGER,
    finished_at     INTEGER,
    expires_at      INTEGER,
    expired         INTEGER NOT NULL DEFAULT 0,
    crashes         INTEGER NOT NULL DEFAULT 0,
    tenant          TEXT NOT NULL DEFAULT 'default',
    input_bytes     INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs(state, seq);
CREATE INDEX IF NOT EXISTS jobs_by_expiry ON jobs(expires_at) WHERE expired = 0;
CREATE TABLE IF NOT EXISTS frames (
    job_id          TEXT NOT NULL,
    step            INTEGER NOT NULL,
    metrics         BLOB NOT NULL,
    has_positions   INTEGER NOT NULL,
    PRIMARY KEY (job_id, step)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS idempotency (
    key             TEXT PRIMARY KEY,
    request_hash    TEXT NOT NULL,
    job_id          TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS uploads (
    id              TEXT PRIMARY KEY,
    format          TEXT NOT NULL,
    size            INTEGER NOT NULL,
    created_at      INTEGER NOT NULL,
    expires_at      INTEGER NOT NULL,
    tenant          TEXT NOT NULL DEFAULT 'default'
);
";

/// Columns added after the first release, with their definitions: databases from before them
/// get them at open (SQLite has no `ADD COLUMN IF NOT EXISTS`). Rows from before tenants
/// belong to the default tenant.
const ADDED_COLUMNS: [(&str, &str, &str); 4] = [
    ("jobs", "crashes", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "tenant", "TEXT NOT NULL DEFAULT 'default'"),
    ("jobs", "input_bytes", "INTEGER NOT NULL DEFAULT 0"),
    ("uploads", "tenant", "TEXT NOT NULL DEFAULT 'default'"),
];

/// Created after the columns they index exist. `tenant_bytes` is each tenant's stored bytes
/// (inputs of unexpired jobs and uploads), kept by triggers on every path that adds, expires or
/// removes one, and recomputed at every open (so it also heals from anything older).
const INDEXES: &str = "
CREATE INDEX IF NOT EXISTS jobs_by_tenant ON jobs(tenant, seq);
CREATE INDEX IF NOT EXISTS jobs_by_tenant_state ON jobs(tenant, state);
CREATE INDEX IF NOT EXISTS jobs_by_tenant_created ON jobs(tenant, created_at);
CREATE INDEX IF NOT EXISTS uploads_by_tenant ON uploads(tenant, created_at);
CREATE TABLE IF NOT EXISTS tenant_bytes (
    tenant          TEXT PRIMARY KEY,
    bytes           INTEGER NOT NULL
) WITHOUT ROWID;
CREATE TRIGGER IF NOT EXISTS tenant_bytes_job_in AFTER INSERT ON jobs WHEN NEW.expired = 0
BEGIN
    INSERT INTO tenant_bytes (tenant, bytes) VALUES (NEW.tenant, NEW.input_bytes)
    ON CONFLICT (tenant) DO UPDATE SET bytes = bytes + excluded.bytes;
END;
CREATE TRIGGER IF NOT EXISTS tenant_bytes_job_expired AFTER UPDATE OF expired ON jobs
WHEN OLD.expired = 0 AND NEW.expired != 0
BEGIN
    UPDATE tenant_bytes SET bytes = bytes - OLD.input_bytes WHERE tenant = OLD.tenant;
END;
CREATE TRIGGER IF NOT EXISTS tenant_bytes_job_out AFTER DELETE ON jobs WHEN OLD.expired = 0
BEGIN
    UPDATE tenant_bytes SET bytes = bytes - OLD.input_bytes WHERE tenant = OLD.tenant;
END;
CREATE TRIGGER IF NOT EXISTS tenant_bytes_upload_in AFTER INSERT ON uploads
BEGIN
    INSERT INTO tenant_bytes (tenant, bytes) VALUES (NEW.tenant, NEW.size)
    ON CONFLICT (tenant) DO UPDATE SET bytes = bytes + excluded.bytes;
END;
CREATE TRIGGER IF NOT EXISTS tenant_bytes_upload_out AFTER DELETE ON uploads
BEGIN
    UPDATE tenant_bytes SET bytes = bytes - OLD.size WHERE tenant = OLD.tenant;
END;
DELETE FROM tenant_bytes;
INSERT INTO tenant_bytes (tenant, bytes)
    SELECT tenant, SUM(b) FROM (
        SELECT tenant, input_bytes AS b FROM jobs WHERE expired = 0
        UNION ALL SELECT tenant, size FROM uploads
    ) GROUP BY tenant;
";

/// The SQLite job store: one connection behind a mutex, used on tokio's blocking pool.
#[derive(Clone)]
pub struct SqliteStore {
    conn: Arc<Mutex<Connection>>,
}

const STATUS_COLUMNS: &str =
    "id, state, spec, input_format, vertex_count, face_count, step, latest, \
     error, error_code, created_at, started_at, finished_at, expires_at, expired, seq, \
     tenant, input_bytes";

/// A row as read, before the expiry check.
struct Row {
    status: JobStatus,
    expired: bool,
    seq: i64,
}

fn row_to_status(r: &rusqlite::Row<'_>) -> rusqlite::Result<Result<Row, JobError>> {
    let id: String = r.get(0)?;
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
    let seq: i64 = r.get(15)?;
    let tenant: String = r.get(16)?;
    let input_bytes = get_u64(17)?.unwrap_or(0);
    Ok((|| {
        let state = JobState::parse(&state)
            .ok_or_else(|| JobError::Internal(format!("unknown stored state `{state}`")))?;
        let spec: JobSpec = serde_json::from_str(&spec)
            .map_err(|e| JobError::Internal(format!("stored spec: {e}")))?;
        let input_format = parse_format(&format)
            .ok_or_else(|| JobError::Internal(format!("unknown stored format `{format}`")))?;
        let latest = latest.map(|b| decode_metrics(&b)).transpose()?;
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
                latest,
                error,
                error_code,
                created_at,
                started_at,
                finished_at,
                expires_at,
            },
            expired: expired != 0,
            seq,
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
        conn.busy_timeout(BUSY_TIMEOUT)?;
        // WAL: readers never block the writer; NORMAL: a commit survives a process crash
        // (SIGKILL), and power loss can lose only the last transactions, not corrupt the file.
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "NORMAL")?;
        conn.execute_batch(SCHEMA)?;
        for (table, column, definition) in ADDED_COLUMNS {
            let present: bool = conn
                .prepare("SELECT 1 FROM pragma_table_info(?1) WHERE name = ?2")?
                .exists(params![table, column])?;
            if !present {
                conn.execute(
                    &format!("ALTER TABLE {table} ADD COLUMN {column} {definition}"),
                    [],
                )?;
                if (table, column) == ("jobs", "tenant") {
                    // Keys stored before tenants were the client's text alone; they are the
                    // default tenant's now (see `scoped_key`).
                    conn.execute("UPDATE idempotency SET key = 'default/' || key", [])?;
                }
            }
        }
        conn.execute_batch(INDEXES)?;
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
        check_id(id)?;
        let conn = self.conn()?;
        let row = conn
            .query_row(
                &format!("SELECT {STATUS_COLUMNS} FROM jobs WHERE id = ?1"),
                params![id],
                row_to_status,
            )
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
            .query_row(
                "SELECT request_hash, job_id FROM idempotency WHERE key = ?1",
                params![scoped_key(tenant, key)],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
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
        {
            let mut conn = self.conn()?;
            let tx = conn.transaction()?;
            if let Some((key, hash)) = &job.idempotency {
                let found: Option<(String, String)> = tx
                    .query_row(
                        "SELECT request_hash, job_id FROM idempotency WHERE key = ?1",
                        params![scoped_key(&job.tenant, key)],
                        |r| Ok((r.get(0)?, r.get(1)?)),
                    )
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
                let since = now_ms().saturating_sub(60_000);
                let usage = usage_on(&tx, &job.tenant, since)?;
                if let Some(over) = over_quota(&job.quotas, &usage, job.input_bytes, true) {
                    return Ok(Inserted::OverQuota(over));
                }
            }
            tx.execute(
                "INSERT INTO jobs (id, state, spec, input_format, vertex_count, face_count, created_at,
                                   tenant, input_bytes)
                 VALUES (?1, 'queued', ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
                params![
                    job.id,
                    spec,
                    format_name(job.format),
                    job.vertex_count as i64,
                    job.face_count as i64,
                    ms(job.created_at),
                    job.tenant,
                    ms(job.input_bytes)
                ],
            )?;
            if let Some((key, hash)) = &job.idempotency {
                tx.execute(
                    "INSERT INTO idempotency (key, request_hash, job_id) VALUES (?1, ?2, ?3)",
                    params![scoped_key(&job.tenant, key), hash, job.id],
                )?;
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
        let before = match token {
            None | Some("") => i64::MAX,
            Some(t) => base64::engine::general_purpose::URL_SAFE_NO_PAD
                .decode(t)
                .ok()
                .and_then(|b| String::from_utf8(b).ok())
                .and_then(|s| s.strip_prefix("seq:").and_then(|n| n.parse::<i64>().ok()))
                .ok_or_else(|| JobError::InvalidSpec {
                    field: "page_token",
                    reason: "not a token this server returned".into(),
                })?,
        };
        let now = ms(now_ms());
        let conn = self.conn()?;
        let sql = format!(
            "SELECT {STATUS_COLUMNS} FROM jobs
             WHERE tenant = ?5 AND seq < ?1 AND expired = 0
               AND (expires_at IS NULL OR expires_at > ?2) AND (?3 IS NULL OR state = ?3)
             ORDER BY seq DESC LIMIT ?4"
        );
        let mut st = conn.prepare(&sql)?;
        let rows = st.query_map(
            params![
                before,
                now,
                state.map(|s| s.as_str()),
                (size + 1) as i64,
                tenant
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
                base64::engine::general_purpose::URL_SAFE_NO_PAD.encode(format!("seq:{}", r.seq))
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

/// What `tenant` holds (see [`JobStore::usage`]), on `conn` (or a transaction). Each count is
/// an index range of the tenant's live or recent rows, and the bytes one row of
/// `tenant_bytes`, so the cost does not grow with the jobs a tenant keeps.
fn usage_on(conn: &Connection, tenant: &str, since: u64) -> Result<Usage, JobError> {
    let live: i64 = conn.query_row(
        "SELECT COUNT(*) FROM jobs WHERE tenant = ?1 AND state IN ('queued', 'running')",
        params![tenant],
        |r| r.get(0),
    )?;
    let recent: i64 = conn.query_row(
        "SELECT (SELECT COUNT(*) FROM jobs WHERE tenant = ?1 AND created_at >= ?2)
              + (SELECT COUNT(*) FROM uploads WHERE tenant = ?1 AND created_at >= ?2)",
        params![tenant, ms(since)],
        |r| r.get(0),
    )?;
    let bytes: Option<i64> = conn
        .query_row(
            "SELECT bytes FROM tenant_bytes WHERE tenant = ?1",
            params![tenant],
            |r| r.get(0),
        )
        .optional()?;
    let n = |v: i64| usize::try_from(v).unwrap_or(0);
    Ok(Usage {
        live_jobs: n(live),
        stored_bytes: u64::try_from(bytes.unwrap_or(0)).unwrap_or(0),
        uploads_since: n(recent),
    })
}

/// Idempotency keys are per tenant: the stored key is the tenant, a `/` (which no tenant id
/// holds) and the client's key.
fn scoped_key(tenant: &str, key: &str) -> String {
    format!("{tenant}/{key}")
}

/// Ids come from URLs: only our own UUID text is looked up (and, in the file store, becomes a
/// path).
pub(crate) fn check_id(id: &str) -> Result<(), JobError> {
    if id.is_empty() || id.len() > 64 || !id.bytes().all(|b| b.is_ascii_hexdigit() || b == b'-') {
        return Err(JobError::NotFound(id.to_string()));
    }
    Ok(())
}

#[async_trait]
impl JobStore for SqliteStore {
    async fn insert(&self, job: NewJob) -> Result<Inserted, JobError> {
        self.blocking(move |s| s.insert_now(&job)).await
    }

    async fn idempotent(
        &self,
        tenant: &str,
        key: &str,
        hash: &str,
    ) -> Result<Option<JobStatus>, JobError> {
        let (tenant, key, hash) = (tenant.to_string(), key.to_string(), hash.to_string());
        self.blocking(move |s| s.idempotent_now(&tenant, &key, &hash))
            .await
    }

    async fn status(&self, id: &str, tenant: Option<&str>) -> Result<JobStatus, JobError> {
        let (id, tenant) = (id.to_string(), tenant.map(str::to_string));
        self.blocking(move |s| s.status_now(&id, tenant.as_deref()))
            .await
    }

    async fn list(
        &self,
        tenant: &str,
        state: Option<JobState>,
        size: usize,
        token: Option<String>,
    ) -> Result<(Vec<JobStatus>, Option<String>), JobError> {
        let tenant = tenant.to_string();
        self.blocking(move |s| s.list_now(&tenant, state, size, token.as_deref()))
            .await
    }

    async fn start(&self, id: &str, at: u64) -> Result<Option<JobStatus>, JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            // `started_at` keeps the first start: a resumed job has been running since then.
            let n = s.conn()?.execute(
                "UPDATE jobs SET state = 'running', started_at = COALESCE(started_at, ?2)
                 WHERE id = ?1 AND state IN ('queued', 'running') AND expired = 0",
                params![id, ms(at)],
            )?;
            if n == 0 {
                return Ok(None);
            }
            s.status_now(&id, None).map(Some)
        })
        .await
    }

    async fn record_frame(
        &self,
        id: &str,
        m: StepMetrics,
        has_positions: bool,
    ) -> Result<(), JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            let blob = encode_metrics(&m);
            let mut conn = s.conn()?;
            let tx = conn.transaction()?;
            tx.execute(
                "INSERT OR REPLACE INTO frames (job_id, step, metrics, has_positions) VALUES (?1, ?2, ?3, ?4)",
                params![id, m.step as i64, blob, has_positions as i64],
            )?;
            tx.execute(
                "UPDATE jobs SET step = ?2, latest = ?3 WHERE id = ?1",
                params![id, m.step as i64, blob],
            )?;
            tx.commit()?;
            Ok(())
        })
        .await
    }

    async fn rewind(&self, id: &str, step: usize) -> Result<(), JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            let step = i64::try_from(step).unwrap_or(i64::MAX);
            let mut conn = s.conn()?;
            let tx = conn.transaction()?;
            tx.execute(
                "DELETE FROM frames WHERE job_id = ?1 AND step > ?2",
                params![id, step],
            )?;
            let latest: Option<Vec<u8>> = tx
                .query_row(
                    "SELECT metrics FROM frames WHERE job_id = ?1 AND step = ?2",
                    params![id, step],
                    |r| r.get(0),
                )
                .optional()?;
            tx.execute(
                "UPDATE jobs SET step = ?2, latest = ?3 WHERE id = ?1",
                params![id, if latest.is_some() { step } else { 0 }, latest],
            )?;
            tx.commit()?;
            Ok(())
        })
        .await
    }

    async fn frame_rows(
        &self,
        id: &str,
        from: usize,
        limit: usize,
    ) -> Result<Vec<(StepMetrics, bool)>, JobError> {
        let id = id.to_string();
        self.blocking(move |s| s.frame_rows_now(&id, from, limit))
            .await
    }

    async fn finish(
        &self,
        id: &str,
        state: JobState,
        error: Option<(String, String)>,
        at: u64,
        expires_at: u64,
    ) -> Result<Option<JobStatus>, JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            let (code, msg) = error.unzip();
            let n = s.conn()?.execute(
                "UPDATE jobs SET state = ?2, error_code = ?3, error = ?4, finished_at = ?5, expires_at = ?6
                 WHERE id = ?1 AND state IN ('queued', 'running')",
                params![id, state.as_str(), code, msg, ms(at), ms(expires_at)],
            )?;
            if n == 0 {
                return Ok(None);
            }
            s.row(&id).map(|r| Some(r.status))
        })
        .await
    }

    async fn requeue(&self, id: &str) -> Result<(), JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            s.conn()?.execute(
                "UPDATE jobs SET state = 'queued' WHERE id = ?1 AND state = 'running'",
                params![id],
            )?;
            Ok(())
        })
        .await
    }

    async fn delete(&self, tenant: &str, id: &str) -> Result<(), JobError> {
        let (tenant, id) = (tenant.to_string(), id.to_string());
        self.blocking(move |s| {
            let row = s.row(&id)?;
            if row.status.tenant != tenant {
                return Err(JobError::NotFound(id));
            }
            if !row.expired && !row.status.state.is_terminal() {
                return Err(JobError::Conflict(format!(
                    "job `{id}` is {}: cancel it first, only finished jobs can be deleted",
                    row.status.state.as_str()
                )));
            }
            let mut conn = s.conn()?;
            let tx = conn.transaction()?;
            tx.execute("DELETE FROM frames WHERE job_id = ?1", params![id])?;
            tx.execute("DELETE FROM idempotency WHERE job_id = ?1", params![id])?;
            tx.execute("DELETE FROM jobs WHERE id = ?1", params![id])?;
            tx.commit()?;
            Ok(())
        })
        .await
    }

    async fn sweep_expired(&self, now: u64) -> Result<Swept, JobError> {
        self.blocking(move |s| {
            let mut conn = s.conn()?;
            let tx = conn.transaction()?;
            let jobs: Vec<String> = {
                let mut st = tx.prepare(
                    "SELECT id FROM jobs WHERE expired = 0 AND expires_at IS NOT NULL AND expires_at <= ?1",
                )?;
                let rows = st.query_map(params![ms(now)], |r| r.get(0))?;
                rows.collect::<Result<_, _>>()?
            };
            for id in &jobs {
                tx.execute("DELETE FROM frames WHERE job_id = ?1", params![id])?;
                tx.execute("UPDATE jobs SET expired = 1 WHERE id = ?1", params![id])?;
            }
            let uploads: Vec<(String, String)> = {
                let mut st = tx.prepare("SELECT id, format FROM uploads WHERE expires_at <= ?1")?;
                let rows = st.query_map(params![ms(now)], |r| Ok((r.get(0)?, r.get(1)?)))?;
                rows.collect::<Result<_, _>>()?
            };
            tx.execute("DELETE FROM uploads WHERE expires_at <= ?1", params![ms(now)])?;
            tx.commit()?;
            let uploads = uploads
                .into_iter()
                .filter_map(|(id, f)| parse_format(&f).map(|f| (id, f)))
                .collect();
            Ok(Swept { jobs, uploads })
        })
        .await
    }

    async fn recover(&self) -> Result<Vec<Recovered>, JobError> {
        self.blocking(move |s| {
            let mut conn = s.conn()?;
            let tx = conn.transaction()?;
            let running: Vec<String> = {
                let mut st = tx.prepare("SELECT id FROM jobs WHERE state = 'running'")?;
                let rows = st.query_map([], |r| r.get(0))?;
                rows.collect::<Result<_, _>>()?
            };
            // Running jobs go back to the queue, at their place; their frames and checkpoint
            // stay, and the worker that takes them resumes from the checkpoint. They died with
            // the process (a clean shutdown re-queues first), which counts as a delivery: a
            // job that keeps killing the server fails `redelivered` instead of looping.
            tx.execute(
                "UPDATE jobs SET state = 'queued', crashes = crashes + 1 WHERE state = 'running'",
                [],
            )?;
            let queued: Vec<Recovered> = {
                let mut st = tx.prepare(
                    "SELECT id, crashes, tenant FROM jobs WHERE state = 'queued' ORDER BY seq",
                )?;
                let rows = st.query_map([], |r| {
                    Ok(Recovered {
                        id: r.get(0)?,
                        delivered: u32::try_from(r.get::<_, i64>(1)?).unwrap_or(u32::MAX),
                        tenant: r.get(2)?,
                    })
                })?;
                rows.collect::<Result<_, _>>()?
            };
            tx.commit()?;
            for id in &running {
                tracing::warn!(job_id = %id, "job was running when the previous process stopped: re-queued, it resumes from its checkpoint");
            }
            Ok(queued)
        })
        .await
    }

    async fn put_upload(
        &self,
        tenant: &str,
        id: &str,
        format: Format,
        size: u64,
        expires_at: u64,
    ) -> Result<(), JobError> {
        let (tenant, id) = (tenant.to_string(), id.to_string());
        self.blocking(move |s| {
            s.conn()?.execute(
                "INSERT INTO uploads (id, format, size, created_at, expires_at, tenant)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                params![
                    id,
                    format_name(format),
                    ms(size),
                    ms(now_ms()),
                    ms(expires_at),
                    tenant
                ],
            )?;
            Ok(())
        })
        .await
    }

    async fn upload(&self, tenant: &str, id: &str) -> Result<Format, JobError> {
        let (tenant, id) = (tenant.to_string(), id.to_string());
        self.blocking(move |s| {
            let found: Option<(String, i64)> = s
                .conn()?
                .query_row(
                    "SELECT format, expires_at FROM uploads WHERE id = ?1 AND tenant = ?2",
                    params![id, tenant],
                    |r| Ok((r.get(0)?, r.get(1)?)),
                )
                .optional()?;
            let (format, expires_at) = found.ok_or_else(|| JobError::UploadNotFound(id.clone()))?;
            if expires_at <= ms(now_ms()) {
                return Err(JobError::UploadNotFound(id));
            }
            parse_format(&format)
                .ok_or_else(|| JobError::Internal(format!("unknown stored format `{format}`")))
        })
        .await
    }

    async fn usage(&self, tenant: &str, since: u64) -> Result<Usage, JobError> {
        let tenant = tenant.to_string();
        self.blocking(move |s| usage_on(&*s.conn()?, &tenant, since))
            .await
    }
}
