//! The embedded [`JobStore`]: SQLite (`willow.sqlite3` in the data dir, WAL mode) for jobs,
//! per-step metrics, idempotency keys and upload records. Blobs are files ([`super::files`]).
//!
//! One connection behind a mutex, used only from blocking threads: the workers write one small
//! transaction per step, which SQLite in WAL mode with `synchronous=NORMAL` commits in tens of
//! microseconds, so a single connection is not the bottleneck the flow step is.

use super::super::codec::{decode_metrics, encode_metrics};
use super::super::ports::{
    over_quota, Admitting, Fence, Inserted, JobStore, MinuteWindows, NewJob, Recovered, Started,
    Swept, Usage, MINUTE_MS,
};
use super::super::{
    format_name, join_err, now_ms, parse_format, poisoned, FailureCode, JobError, JobId, JobSpec,
    JobState, JobStatus,
};
use async_trait::async_trait;
use base64::Engine as _;
use rusqlite::{params, Connection, OptionalExtension};
use std::fs;
use std::path::Path;
use std::sync::{Arc, Mutex};
use willow::mesh::io::Format;
use willow::metrics::StepMetrics;

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
    input_bytes     INTEGER NOT NULL DEFAULT 0,
    received        INTEGER NOT NULL DEFAULT 1
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
const ADDED_COLUMNS: [(&str, &str, &str); 5] = [
    ("jobs", "crashes", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "tenant", "TEXT NOT NULL DEFAULT 'default'"),
    ("jobs", "input_bytes", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "received", "INTEGER NOT NULL DEFAULT 1"),
    ("uploads", "tenant", "TEXT NOT NULL DEFAULT 'default'"),
];

/// The statement a trigger runs for a mesh received (a job or an upload row `NEW`): what
/// [`MinuteWindows::receive`] does, on the tenant's `tenant_usage` row.
macro_rules! receive_into_windows {
    () => {
        "
    UPDATE tenant_usage SET
        previous_count = CASE
            WHEN NEW.created_at - NEW.created_at % 60000 <= window_start
                THEN previous_count + (NEW.created_at - NEW.created_at % 60000 = window_start - 60000)
            WHEN NEW.created_at - NEW.created_at % 60000 = window_start + 60000 THEN window_count
            ELSE 0 END,
        window_count = CASE
            WHEN NEW.created_at - NEW.created_at % 60000 = window_start THEN window_count + 1
            WHEN NEW.created_at - NEW.created_at % 60000 < window_start THEN window_count
            ELSE 1 END,
        window_start = MAX(window_start, NEW.created_at - NEW.created_at % 60000)
    WHERE tenant = NEW.tenant;
"
    };
}

/// Created after the columns they index exist.
///
/// `tenant_usage` is what each tenant's quotas check, one row per tenant so that an
/// admission reads one row however many jobs the tenant keeps (`cargo bench --bench
/// service_load`, part 8: counting the rows cost 5–10% of a submission at 8 clients):
/// - `bytes`: inputs of unexpired jobs and uploads;
/// - `live`: queued and running jobs;
/// - `window_start`, `window_count`, `previous_count`: meshes received (uploads, and jobs
///   that brought their mesh: `received`; a stored upload's job does not count again) in
///   the fixed minute starting at `window_start` and in the minute before it, from which
///   [`MinuteWindows`] estimates the sliding minute (the triggers do what
///   [`MinuteWindows::receive`] does).
///
/// A mesh received moves its tenant's windows on to the minute of its `created_at`: the
/// current window becomes the previous one when the next minute starts, both reset after a
/// quiet minute, and a row committed late with the previous minute's time counts there. (Each
/// trigger creates its tenant's row before it updates it: SQLite promises no order between
/// the triggers of one insert.)
///
/// The triggers are recreated at every open, so their bodies are always this release's.
/// Triggers keep it on every path that adds, finishes, expires or removes a row, and it is
/// recomputed at every open ([`RECOUNT_USAGE`]), so it also heals from anything older. It
/// replaces `tenant_bytes`, which kept the bytes alone.
const INDEXES: &str = concat!(
    "
CREATE INDEX IF NOT EXISTS jobs_by_tenant ON jobs(tenant, seq);
CREATE INDEX IF NOT EXISTS jobs_by_tenant_state ON jobs(tenant, state);
CREATE INDEX IF NOT EXISTS jobs_by_tenant_created ON jobs(tenant, created_at);
CREATE INDEX IF NOT EXISTS uploads_by_tenant ON uploads(tenant, created_at);
DROP TRIGGER IF EXISTS tenant_bytes_job_in;
DROP TRIGGER IF EXISTS tenant_bytes_job_expired;
DROP TRIGGER IF EXISTS tenant_bytes_job_out;
DROP TRIGGER IF EXISTS tenant_bytes_upload_in;
DROP TRIGGER IF EXISTS tenant_bytes_upload_out;
DROP TABLE IF EXISTS tenant_bytes;
CREATE TABLE IF NOT EXISTS tenant_usage (
    tenant          TEXT PRIMARY KEY,
    bytes           INTEGER NOT NULL DEFAULT 0,
    live            INTEGER NOT NULL DEFAULT 0,
    window_start    INTEGER NOT NULL DEFAULT 0,
    window_count    INTEGER NOT NULL DEFAULT 0,
    previous_count  INTEGER NOT NULL DEFAULT 0
) WITHOUT ROWID;
DROP TRIGGER IF EXISTS tenant_usage_job_in;
CREATE TRIGGER tenant_usage_job_in AFTER INSERT ON jobs
BEGIN
    INSERT INTO tenant_usage (tenant) VALUES (NEW.tenant) ON CONFLICT (tenant) DO NOTHING;
    UPDATE tenant_usage SET
        bytes = bytes + (CASE WHEN NEW.expired = 0 THEN NEW.input_bytes ELSE 0 END),
        live = live + (NEW.state IN ('queued', 'running'))
    WHERE tenant = NEW.tenant;
END;
DROP TRIGGER IF EXISTS tenant_usage_job_received;
CREATE TRIGGER tenant_usage_job_received AFTER INSERT ON jobs WHEN NEW.received != 0
BEGIN
    INSERT INTO tenant_usage (tenant) VALUES (NEW.tenant) ON CONFLICT (tenant) DO NOTHING;
",
    receive_into_windows!(),
    "END;
DROP TRIGGER IF EXISTS tenant_usage_job_state;
CREATE TRIGGER tenant_usage_job_state AFTER UPDATE OF state ON jobs
WHEN (OLD.state IN ('queued', 'running')) != (NEW.state IN ('queued', 'running'))
BEGIN
    UPDATE tenant_usage
    SET live = live + (CASE WHEN NEW.state IN ('queued', 'running') THEN 1 ELSE -1 END)
    WHERE tenant = NEW.tenant;
END;
DROP TRIGGER IF EXISTS tenant_usage_job_expired;
CREATE TRIGGER tenant_usage_job_expired AFTER UPDATE OF expired ON jobs
WHEN OLD.expired = 0 AND NEW.expired != 0
BEGIN
    UPDATE tenant_usage SET bytes = bytes - OLD.input_bytes WHERE tenant = OLD.tenant;
END;
DROP TRIGGER IF EXISTS tenant_usage_job_out;
CREATE TRIGGER tenant_usage_job_out AFTER DELETE ON jobs
BEGIN
    UPDATE tenant_usage SET
        bytes = bytes - (CASE WHEN OLD.expired = 0 THEN OLD.input_bytes ELSE 0 END),
        live = live - (OLD.state IN ('queued', 'running'))
    WHERE tenant = OLD.tenant;
END;
DROP TRIGGER IF EXISTS tenant_usage_upload_in;
CREATE TRIGGER tenant_usage_upload_in AFTER INSERT ON uploads
BEGIN
    INSERT INTO tenant_usage (tenant) VALUES (NEW.tenant) ON CONFLICT (tenant) DO NOTHING;
    UPDATE tenant_usage SET bytes = bytes + NEW.size WHERE tenant = NEW.tenant;
",
    receive_into_windows!(),
    "END;
DROP TRIGGER IF EXISTS tenant_usage_upload_out;
CREATE TRIGGER tenant_usage_upload_out AFTER DELETE ON uploads
BEGIN
    UPDATE tenant_usage SET bytes = bytes - OLD.size WHERE tenant = OLD.tenant;
END;
"
);

/// `tenant_usage` from the rows themselves, with the minute windows of `?1` (unix ms, the
/// start of the current minute): run at every open, on an emptied table.
const RECOUNT_USAGE: &str = "
INSERT INTO tenant_usage (tenant, bytes, live, window_start, window_count, previous_count)
    SELECT tenant, SUM(b), SUM(l), ?1, SUM(c >= ?1), SUM(c >= ?1 - 60000 AND c < ?1) FROM (
        SELECT tenant, (CASE WHEN expired = 0 THEN input_bytes ELSE 0 END) AS b,
               (state IN ('queued', 'running')) AS l,
               (CASE WHEN received != 0 THEN created_at ELSE 0 END) AS c FROM jobs
        UNION ALL SELECT tenant, size, 0, created_at FROM uploads
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
        let now = now_ms();
        conn.execute("DELETE FROM tenant_usage", [])?;
        conn.execute(RECOUNT_USAGE, params![ms(now - now % MINUTE_MS)])?;
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
                if let Some(over) = over_quota(&job.quotas, &usage, job.input_bytes, admitting) {
                    return Ok(Inserted::OverQuota(over));
                }
            }
            tx.prepare_cached(
                "INSERT INTO jobs (id, state, spec, input_format, vertex_count, face_count, created_at,
                                   tenant, input_bytes, received)
                 VALUES (?1, 'queued', ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
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
                    job.received
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
    let Some((bytes, live, window_start, current, previous)) = row else {
        return Ok(Usage::default());
    };
    let n = |v: i64| u64::try_from(v).unwrap_or(0);
    Ok(Usage {
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

    /// One process, one in-process queue that never hands out a running job: no fencing.
    async fn start(&self, id: &str, _fence: &Fence, at: u64) -> Result<Started, JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            // `started_at` keeps the first start: a resumed job has been running since then.
            let n = s.conn()?.execute(
                "UPDATE jobs SET state = 'running', started_at = COALESCE(started_at, ?2)
                 WHERE id = ?1 AND state IN ('queued', 'running') AND expired = 0",
                params![id, ms(at)],
            )?;
            if n == 0 {
                return Ok(Started::Gone);
            }
            s.status_now(&id, None).map(|s| Started::Run(Box::new(s)))
        })
        .await
    }

    async fn renew(&self, _id: &str, fence: &Fence) -> Result<(), JobError> {
        fence.renewed(super::super::now_ms());
        Ok(())
    }

    async fn record_frame(
        &self,
        id: &str,
        m: StepMetrics,
        has_positions: bool,
        _fence: &Fence,
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

    async fn rewind(&self, id: &str, step: usize, _fence: &Fence) -> Result<(), JobError> {
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
        error: Option<(FailureCode, String)>,
        at: u64,
        expires_at: u64,
        _fence: Option<&Fence>,
    ) -> Result<Option<JobStatus>, JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            let (code, msg) = error.unzip();
            let code = code.map(FailureCode::as_str);
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

    async fn requeue(&self, id: &str, _fence: &Fence) -> Result<(), JobError> {
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
            let jobs: Vec<JobId> = {
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

    async fn usage(&self, tenant: &str, now: u64) -> Result<Usage, JobError> {
        let tenant = tenant.to_string();
        self.blocking(move |s| usage_on(&*s.conn()?, &tenant, now))
            .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::{JobSpec, JobState, TenantQuotas};

    const MIN: u64 = MINUTE_MS;

    fn job(tenant: &str, bytes: u64, at: u64) -> NewJob {
        NewJob {
            id: JobId::random(),
            tenant: tenant.to_string(),
            spec: JobSpec::default(),
            format: Format::Obj,
            vertex_count: 3,
            face_count: 1,
            input_bytes: bytes,
            received: true,
            created_at: at,
            quotas: TenantQuotas {
                max_live_jobs: 0,
                max_stored_bytes: 0,
                uploads_per_minute: 0,
            },
            idempotency: None,
        }
    }

    fn usage_rows(store: &SqliteStore) -> Vec<(String, i64, i64, i64, i64, i64)> {
        let conn = store.conn().expect("conn");
        let mut st = conn
            .prepare(
                "SELECT tenant, bytes, live, window_start, window_count, previous_count
                 FROM tenant_usage ORDER BY tenant",
            )
            .expect("prepare");
        st.query_map([], |r| {
            Ok((
                r.get(0)?,
                r.get(1)?,
                r.get(2)?,
                r.get(3)?,
                r.get(4)?,
                r.get(5)?,
            ))
        })
        .expect("query")
        .collect::<Result<_, _>>()
        .expect("rows")
    }

    /// After every kind of change (jobs queued, started, finished, requeued, expired and
    /// deleted, uploads stored and swept, over three minutes), the bytes and live jobs the
    /// triggers keep equal a recount from the rows themselves, the minute windows count every
    /// mesh received, and what `usage` reports follows from them.
    #[tokio::test]
    async fn triggers_keep_tenant_usage_equal_to_a_recount() {
        let dir = tempfile::tempdir().expect("dir");
        let store = SqliteStore::open(dir.path()).expect("open");
        let now = now_ms();
        let this_minute = now - now % MIN;
        let (earlier, previous) = (this_minute - 2 * MIN + 5, this_minute - MIN + 5);
        let id = |i: &Inserted| match i {
            Inserted::New(s) => s.id.clone(),
            other => panic!("not inserted: {other:?}"),
        };
        let mut a = Vec::new();
        for (bytes, at) in [(100, earlier), (200, previous), (300, previous), (400, now)] {
            a.push(id(&store
                .insert(job("a", bytes, at))
                .await
                .expect("insert")));
        }
        let b = id(&store.insert(job("b", 50, now)).await.expect("insert"));
        // c's job is made from a stored upload: it holds its bytes and a live job, but
        // received no mesh.
        let stored = NewJob {
            received: false,
            ..job("c", 25, now)
        };
        store.insert(stored).await.expect("insert");
        let fence = Fence::new(std::time::Duration::from_secs(30));
        store.start(&a[0], &fence, now).await.expect("start");
        store.start(&a[1], &fence, now).await.expect("start");
        store.requeue(&a[1], &fence).await.expect("requeue");
        store
            .finish(&a[0], JobState::Succeeded, None, now, now + 1, None)
            .await
            .expect("finish");
        store
            .finish(&a[2], JobState::Failed, None, now, now + 10 * MIN, None)
            .await
            .expect("finish");
        store
            .finish(&b, JobState::Cancelled, None, now, now + 10 * MIN, None)
            .await
            .expect("finish");
        store
            .put_upload("b", "u1", Format::Obj, 70, now + 1)
            .await
            .expect("upload");
        store
            .put_upload("b", "u2", Format::Obj, 80, now + 10 * MIN)
            .await
            .expect("upload");
        // a[0] and u1 expire; a[2] is deleted.
        store.sweep_expired(now + 2).await.expect("sweep");
        store.delete("a", &a[2]).await.expect("delete");

        let kept = usage_rows(&store);
        let usage = store.usage("a", now).await.expect("usage");
        assert_eq!(usage.live_jobs, 2);
        assert_eq!(usage.stored_bytes, 600);
        assert_eq!(
            usage.uploads_last_minute,
            MinuteWindows {
                start: this_minute,
                current: 1,
                previous: 2
            }
            .last_minute(now)
        );
        {
            let conn = store.conn().expect("conn");
            conn.execute("DELETE FROM tenant_usage", []).expect("empty");
            conn.execute(RECOUNT_USAGE, params![ms(this_minute)])
                .expect("recount");
        }
        let recounted = usage_rows(&store);
        // Bytes and live jobs equal the recount.
        let held = |rows: &[(String, i64, i64, i64, i64, i64)]| -> Vec<(String, i64, i64)> {
            rows.iter().map(|r| (r.0.clone(), r.1, r.2)).collect()
        };
        assert_eq!(held(&kept), held(&recounted));
        // By hand: a keeps a[1] (queued, 200) and a[3] (queued, 400); b keeps its cancelled
        // job (50) and u2 (80).
        assert_eq!(
            held(&kept),
            [
                ("a".into(), 600, 2),
                ("b".into(), 130, 0),
                ("c".into(), 25, 1)
            ]
        );
        // Nothing received: c's windows stay empty, in the triggers' rows and the recount's.
        assert_eq!((kept[2].4, kept[2].5), (0, 0));
        assert_eq!((recounted[2].4, recounted[2].5), (0, 0));
        let usage = store.usage("c", now).await.expect("usage");
        assert_eq!((usage.live_jobs, usage.uploads_last_minute), (1, 0));
        // The windows count every mesh received, also those deleted or swept since (deleting
        // jobs frees no rate): a got 2 in the previous minute and 1 in this one, b 3 in this
        // one. A recount sees only the rows still there (a[2] deleted, u1 swept).
        assert_eq!((kept[0].3, kept[0].4, kept[0].5), (ms(this_minute), 1, 2));
        // The triggers move the windows as `MinuteWindows::receive` does (the NATS store's).
        let mut expected = MinuteWindows::default();
        for at in [earlier, previous, previous, now] {
            expected.receive(at);
        }
        let as_row = |w: MinuteWindows| (ms(w.start), ms(w.current), ms(w.previous));
        assert_eq!((kept[0].3, kept[0].4, kept[0].5), as_row(expected));
        // (b's uploads take the clock's time: if a minute started during the test, b's windows
        // moved on and its 3 are split over them.)
        let b_received = match kept[1].3 - ms(this_minute) {
            0 => {
                assert_eq!(kept[1].5, 0, "b received nothing before this minute");
                kept[1].4
            }
            d if d == ms(MIN) => kept[1].4 + kept[1].5,
            other => panic!("b's windows start {other} ms after the test's minute"),
        };
        assert_eq!(b_received, 3);
        assert_eq!((recounted[0].4, recounted[0].5), (1, 1));
        assert_eq!((recounted[1].4, recounted[1].5), (2, 0));

        let unknown = store.usage("nobody", now).await.expect("usage");
        assert_eq!(unknown, Usage::default());
    }
}
