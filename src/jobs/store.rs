//! Persistence: SQLite for jobs, per-step metrics and idempotency keys; files for mesh blobs.
//!
//! Layout under the data dir:
//! ```text
//! willow.sqlite3              jobs, frames, idempotency, uploads (WAL mode)
//! jobs/{id}/input.{obj|glb|gltf}   the upload, written atomically (temp + fsync + rename)
//! jobs/{id}/frames/{step}.f32      positions in the file's vertex order, f32 LE xyz (payload)
//! jobs/{id}/frames/{step}.f64      welded positions, f64 LE xyz (to write frame meshes)
//! jobs/{id}/result.f64             final welded positions, f64 LE xyz
//! uploads/{id}.{ext}               uploads stored ahead of a job (chunked gRPC)
//! ```
//! Frame files are renamed into place but not fsynced: a process crash keeps them (the page
//! cache survives it), and after a power loss a running job restarts from step 0 anyway. Inputs
//! and results are fsynced, since a finished job must survive anything the database survives.
//!
//! One connection behind a mutex, used only from blocking threads: the workers write one small
//! transaction per step, which SQLite in WAL mode with `synchronous=NORMAL` commits in tens of
//! microseconds, so a single connection is not the bottleneck the flow step is.

use super::{
    format_name, now_ms, parse_format, poisoned, JobError, JobId, JobSpec, JobState, JobStatus,
};
use crate::mesh::io::{Asset, Format};
use crate::mesh::Limits;
use crate::metrics::StepMetrics;
use base64::Engine as _;
use rusqlite::{params, Connection, OptionalExtension};
use sha2::{Digest, Sha256};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

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
    expired         INTEGER NOT NULL DEFAULT 0
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
    expires_at      INTEGER NOT NULL
);
";

/// A job about to be admitted.
pub struct NewJob {
    pub id: JobId,
    pub spec: JobSpec,
    pub format: Format,
    pub vertex_count: usize,
    pub face_count: usize,
    pub created_at: u64,
    /// (key, request hash)
    pub idempotency: Option<(String, String)>,
}

pub struct Store {
    conn: Mutex<Connection>,
    dir: PathBuf,
}

/// The hash an idempotency key is bound to: format, spec and mesh bytes.
pub fn request_hash(data: &[u8], format: Format, spec: &JobSpec) -> String {
    let mut h = Sha256::new();
    h.update(format_name(format).as_bytes());
    h.update([0]);
    h.update(serde_json::to_vec(&HashedSpec::from(spec)).unwrap_or_default());
    h.update([0]);
    h.update(data);
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// The spec as [`request_hash`] sees it: the fields of the first release in their order, then
/// each later field only when it differs from its default. Keys are stored with their hash, so
/// a request sent again after an upgrade must hash as before, or its retry would be refused
/// as a different request. New [`JobSpec`] fields go at the end here too, skipped at default.
#[derive(serde::Serialize)]
struct HashedSpec<'a> {
    method: crate::flow::Method,
    steps: usize,
    tau: f64,
    iterations: usize,
    frame_interval: usize,
    include_positions: bool,
    deadline_secs: Option<f64>,
    #[serde(skip_serializing_if = "is_true")]
    exactness: bool,
    #[serde(skip_serializing_if = "is_false")]
    mobius_balancing: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    filter: Option<super::spec::FilterSpec>,
    #[serde(skip_serializing_if = "is_free")]
    boundary: &'a super::spec::BoundarySpec,
    #[serde(skip_serializing_if = "is_true")]
    safeguard: bool,
}

fn is_true(b: &bool) -> bool {
    *b
}

fn is_false(b: &bool) -> bool {
    !*b
}

fn is_free(b: &&super::spec::BoundarySpec) -> bool {
    b.is_free()
}

impl<'a> From<&'a JobSpec> for HashedSpec<'a> {
    fn from(s: &'a JobSpec) -> Self {
        // Destructured, so a field added to JobSpec fails to compile until it is hashed.
        let JobSpec {
            method,
            steps,
            tau,
            iterations,
            frame_interval,
            include_positions,
            deadline_secs,
            exactness,
            mobius_balancing,
            filter,
            boundary,
            safeguard,
        } = s;
        HashedSpec {
            method: *method,
            steps: *steps,
            tau: *tau,
            iterations: *iterations,
            frame_interval: *frame_interval,
            include_positions: *include_positions,
            deadline_secs: *deadline_secs,
            exactness: *exactness,
            mobius_balancing: *mobius_balancing,
            filter: *filter,
            boundary,
            safeguard: *safeguard,
        }
    }
}

/// Bytes of a metrics row as the first release wrote it: step as u64, then nine f64
/// (`willmore_energy` … `step_ms`), all little-endian.
const METRICS_V1_BYTES: usize = 80;
/// Bytes of a metrics row now: the first release's 80, then `tau` (f64) and `rejected` (u32),
/// little-endian. Rows are only ever appended to, so an old row is a prefix of a new one.
const METRICS_BYTES: usize = METRICS_V1_BYTES + 8 + 4;

/// The binary form of [`StepMetrics`] ([`METRICS_BYTES`]). Binary and not JSON because a
/// metric may legitimately be NaN or infinite, which JSON cannot carry.
fn encode_metrics(m: &StepMetrics) -> Vec<u8> {
    let mut out = Vec::with_capacity(METRICS_BYTES);
    out.extend_from_slice(&(m.step as u64).to_le_bytes());
    for v in [
        m.willmore_energy,
        m.q_mean,
        m.q_area_mean,
        m.q_p95,
        m.q_max,
        m.closure_residual,
        m.eigen_residual,
        m.area,
        m.step_ms,
        m.tau,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&m.rejected.to_le_bytes());
    out
}

/// Reads a row of either length: one written before the safeguard existed
/// ([`METRICS_V1_BYTES`]) has `tau = 0` and `rejected = 0`, as [`StepMetrics`] documents.
fn decode_metrics(b: &[u8]) -> Result<StepMetrics, JobError> {
    if b.len() != METRICS_BYTES && b.len() != METRICS_V1_BYTES {
        return Err(JobError::Internal(format!(
            "stored metrics have {} bytes, expected {METRICS_BYTES} (or {METRICS_V1_BYTES} for \
             rows written before the safeguard)",
            b.len()
        )));
    }
    let u = |i: usize| {
        let mut a = [0u8; 8];
        a.copy_from_slice(&b[i * 8..i * 8 + 8]);
        a
    };
    let f = |i: usize| f64::from_le_bytes(u(i));
    let (tau, rejected) = if b.len() == METRICS_BYTES {
        let mut r = [0u8; 4];
        r.copy_from_slice(&b[METRICS_V1_BYTES + 8..]);
        (f(10), u32::from_le_bytes(r))
    } else {
        (0.0, 0)
    };
    Ok(StepMetrics {
        step: u64::from_le_bytes(u(0)) as usize,
        willmore_energy: f(1),
        q_mean: f(2),
        q_area_mean: f(3),
        q_p95: f(4),
        q_max: f(5),
        closure_residual: f(6),
        eigen_residual: f(7),
        area: f(8),
        step_ms: f(9),
        tau,
        rejected,
    })
}

/// Write `data` to `path` atomically: a reader sees the old file or the whole new one.
fn write_atomic(path: &Path, data: &[u8], durable: bool) -> Result<(), JobError> {
    let dir = path
        .parent()
        .ok_or_else(|| JobError::Internal(format!("{} has no parent", path.display())))?;
    fs::create_dir_all(dir)?;
    let tmp = dir.join(format!(
        ".{}.tmp-{}",
        path.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        uuid::Uuid::new_v4().simple()
    ));
    let result = (|| {
        let mut f = fs::File::create(&tmp)?;
        f.write_all(data)?;
        if durable {
            f.sync_all()?;
        }
        drop(f);
        fs::rename(&tmp, path)?;
        if durable {
            // The rename itself is durable only once the directory entry is.
            fs::File::open(dir)?.sync_all()?;
        }
        Ok::<_, std::io::Error>(())
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result.map_err(JobError::from)
}

fn f64s_to_bytes(p: &[[f64; 3]]) -> Vec<u8> {
    let mut out = Vec::with_capacity(p.len() * 24);
    for v in p {
        for c in v {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

fn bytes_to_f64s(b: &[u8]) -> Result<Vec<[f64; 3]>, JobError> {
    if !b.len().is_multiple_of(24) {
        return Err(JobError::Internal("truncated f64 position blob".into()));
    }
    Ok(b.chunks_exact(24)
        .map(|c| {
            let g = |i: usize| {
                let mut a = [0u8; 8];
                a.copy_from_slice(&c[i * 8..i * 8 + 8]);
                f64::from_le_bytes(a)
            };
            [g(0), g(1), g(2)]
        })
        .collect())
}

/// Little-endian f32 xyz, the frame payload format.
pub fn f32s_to_bytes(p: &[[f32; 3]]) -> Vec<u8> {
    let mut out = Vec::with_capacity(p.len() * 12);
    for v in p {
        for c in v {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

fn bytes_to_f32s(b: &[u8]) -> Result<Vec<[f32; 3]>, JobError> {
    if !b.len().is_multiple_of(12) {
        return Err(JobError::Internal("truncated f32 position blob".into()));
    }
    Ok(b.chunks_exact(12)
        .map(|c| {
            let g =
                |i: usize| f32::from_le_bytes([c[i * 4], c[i * 4 + 1], c[i * 4 + 2], c[i * 4 + 3]]);
            [g(0), g(1), g(2)]
        })
        .collect())
}

const STATUS_COLUMNS: &str =
    "id, state, spec, input_format, vertex_count, face_count, step, latest, \
     error, error_code, created_at, started_at, finished_at, expires_at, expired, seq";

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
                state,
                step: step.max(0) as usize,
                total_steps: spec.steps,
                spec,
                input_format,
                vertex_count: vertex_count.max(0) as usize,
                face_count: face_count.max(0) as usize,
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

impl Store {
    /// Open (creating if needed) the store in `dir`.
    pub fn open(dir: &Path) -> Result<Store, JobError> {
        fs::create_dir_all(dir.join("jobs"))?;
        fs::create_dir_all(dir.join("uploads"))?;
        let conn = Connection::open(dir.join("willow.sqlite3"))?;
        conn.busy_timeout(BUSY_TIMEOUT)?;
        // WAL: readers never block the writer; NORMAL: a commit survives a process crash
        // (SIGKILL), and power loss can lose only the last transactions, not corrupt the file.
        conn.pragma_update(None, "journal_mode", "WAL")?;
        conn.pragma_update(None, "synchronous", "NORMAL")?;
        conn.execute_batch(SCHEMA)?;
        Ok(Store {
            conn: Mutex::new(conn),
            dir: dir.to_path_buf(),
        })
    }

    fn conn(&self) -> Result<std::sync::MutexGuard<'_, Connection>, JobError> {
        self.conn.lock().map_err(poisoned)
    }

    fn job_dir(&self, id: &str) -> Result<PathBuf, JobError> {
        // Ids come from URLs: only our own UUID text may become a path.
        if id.is_empty() || id.len() > 64 || !id.bytes().all(|b| b.is_ascii_hexdigit() || b == b'-')
        {
            return Err(JobError::NotFound(id.to_string()));
        }
        Ok(self.dir.join("jobs").join(id))
    }

    fn frame_path(&self, id: &str, step: usize, ext: &str) -> Result<PathBuf, JobError> {
        Ok(self
            .job_dir(id)?
            .join("frames")
            .join(format!("{step}.{ext}")))
    }

    /// Make the store consistent after a previous process: running jobs go back to queued
    /// (their frames are dropped, they restart from step 0). Returns the queued jobs in order.
    pub fn recover(&self) -> Result<Vec<JobId>, JobError> {
        let mut conn = self.conn()?;
        let tx = conn.transaction()?;
        let running: Vec<String> = {
            let mut st = tx.prepare("SELECT id FROM jobs WHERE state = 'running'")?;
            let rows = st.query_map([], |r| r.get(0))?;
            rows.collect::<Result<_, _>>()?
        };
        for id in &running {
            tx.execute("DELETE FROM frames WHERE job_id = ?1", params![id])?;
            tx.execute(
                "UPDATE jobs SET state = 'queued', step = 0, latest = NULL, started_at = NULL WHERE id = ?1",
                params![id],
            )?;
        }
        let queued: Vec<String> = {
            let mut st = tx.prepare("SELECT id FROM jobs WHERE state = 'queued' ORDER BY seq")?;
            let rows = st.query_map([], |r| r.get(0))?;
            rows.collect::<Result<_, _>>()?
        };
        tx.commit()?;
        drop(conn);
        for id in &running {
            if let Ok(d) = self.job_dir(id) {
                let _ = fs::remove_dir_all(d.join("frames"));
            }
            tracing::warn!(job_id = %id, "job was running when the previous process stopped: re-queued from step 0");
        }
        Ok(queued)
    }

    pub fn write_input(&self, id: &str, format: Format, data: &[u8]) -> Result<(), JobError> {
        let path = self
            .job_dir(id)?
            .join(format!("input.{}", format_name(format)));
        write_atomic(&path, data, true)
    }

    pub fn remove_job_files(&self, id: &str) -> Result<(), JobError> {
        match fs::remove_dir_all(self.job_dir(id)?) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    pub fn read_asset(&self, id: &str, limits: &Limits) -> Result<Asset, JobError> {
        let format: String = self
            .conn()?
            .query_row(
                "SELECT input_format FROM jobs WHERE id = ?1",
                params![id],
                |r| r.get(0),
            )
            .optional()?
            .ok_or_else(|| JobError::NotFound(id.to_string()))?;
        let format = parse_format(&format)
            .ok_or_else(|| JobError::Internal(format!("unknown stored format `{format}`")))?;
        let bytes = fs::read(
            self.job_dir(id)?
                .join(format!("input.{}", format_name(format))),
        )?;
        Asset::read(&bytes, format, limits).map_err(JobError::InvalidMesh)
    }

    /// Insert an admitted job (and its idempotency key) in one transaction.
    pub fn insert_job(&self, job: &NewJob) -> Result<JobStatus, JobError> {
        let spec = serde_json::to_string(&job.spec)
            .map_err(|e| JobError::Internal(format!("spec: {e}")))?;
        {
            let mut conn = self.conn()?;
            let tx = conn.transaction()?;
            tx.execute(
                "INSERT INTO jobs (id, state, spec, input_format, vertex_count, face_count, created_at)
                 VALUES (?1, 'queued', ?2, ?3, ?4, ?5, ?6)",
                params![
                    job.id,
                    spec,
                    format_name(job.format),
                    job.vertex_count as i64,
                    job.face_count as i64,
                    job.created_at as i64
                ],
            )?;
            if let Some((key, hash)) = &job.idempotency {
                tx.execute(
                    "INSERT INTO idempotency (key, request_hash, job_id) VALUES (?1, ?2, ?3)",
                    params![key, hash, job.id],
                )?;
            }
            tx.commit()?;
        }
        self.status(&job.id)
    }

    /// The job an idempotency key created, if the key is known and bound to the same request.
    pub fn idempotent_job(&self, key: &str, hash: &str) -> Result<Option<JobStatus>, JobError> {
        let found: Option<(String, String)> = self
            .conn()?
            .query_row(
                "SELECT request_hash, job_id FROM idempotency WHERE key = ?1",
                params![key],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .optional()?;
        match found {
            None => Ok(None),
            Some((stored, _)) if stored != hash => Err(JobError::IdempotencyMismatch(format!(
                "key `{key}` was first used with a different mesh or parameters"
            ))),
            Some((_, job_id)) => self.status(&job_id).map(Some),
        }
    }

    fn row(&self, id: &str) -> Result<Row, JobError> {
        self.job_dir(id)?;
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

    /// The status of a live job: `NotFound` if unknown, `Gone` once expired (even before the
    /// sweeper deleted its files).
    pub fn status(&self, id: &str) -> Result<JobStatus, JobError> {
        let row = self.row(id)?;
        let expired_now = row.status.expires_at.is_some_and(|t| t <= now_ms());
        if row.expired || expired_now {
            return Err(JobError::Gone(id.to_string()));
        }
        Ok(row.status)
    }

    pub fn list(
        &self,
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
        let now = now_ms() as i64;
        let conn = self.conn()?;
        let sql = format!(
            "SELECT {STATUS_COLUMNS} FROM jobs
             WHERE seq < ?1 AND expired = 0 AND (expires_at IS NULL OR expires_at > ?2)
               AND (?3 IS NULL OR state = ?3)
             ORDER BY seq DESC LIMIT ?4"
        );
        let mut st = conn.prepare(&sql)?;
        let rows = st.query_map(
            params![before, now, state.map(|s| s.as_str()), (size + 1) as i64],
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

    /// Mark a queued job running; `None` if it is no longer queued (cancelled meanwhile).
    pub fn set_running(&self, id: &str, at: u64) -> Result<Option<JobStatus>, JobError> {
        let n = self.conn()?.execute(
            "UPDATE jobs SET state = 'running', started_at = ?2, step = 0 WHERE id = ?1 AND state = 'queued'",
            params![id, at as i64],
        )?;
        if n == 0 {
            return Ok(None);
        }
        self.status(id).map(Some)
    }

    /// Keep a frame's positions: the payload (file order, f32) and the welded f64 positions.
    pub fn write_frame_positions(
        &self,
        id: &str,
        step: usize,
        file_order: &[[f32; 3]],
        welded: &[[f64; 3]],
    ) -> Result<(), JobError> {
        write_atomic(
            &self.frame_path(id, step, "f32")?,
            &f32s_to_bytes(file_order),
            false,
        )?;
        write_atomic(
            &self.frame_path(id, step, "f64")?,
            &f64s_to_bytes(welded),
            false,
        )
    }

    /// Record a step's metrics and advance the job's progress, in one transaction.
    pub fn record_frame(
        &self,
        id: &str,
        m: &StepMetrics,
        has_positions: bool,
    ) -> Result<(), JobError> {
        let blob = encode_metrics(m);
        let mut conn = self.conn()?;
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
    }

    pub fn write_result(&self, id: &str, welded: &[[f64; 3]]) -> Result<(), JobError> {
        write_atomic(
            &self.job_dir(id)?.join("result.f64"),
            &f64s_to_bytes(welded),
            true,
        )
    }

    pub fn read_result(&self, id: &str) -> Result<Vec<[f64; 3]>, JobError> {
        bytes_to_f64s(&fs::read(self.job_dir(id)?.join("result.f64"))?)
    }

    /// Move a job to a terminal state. Returns `None` if it already was terminal.
    pub fn finish(
        &self,
        id: &str,
        state: JobState,
        error: Option<(&str, String)>,
        at: u64,
        expires_at: u64,
    ) -> Result<Option<JobStatus>, JobError> {
        let (code, msg) = match error {
            Some((c, m)) => (Some(c.to_string()), Some(m)),
            None => (None, None),
        };
        let n = self.conn()?.execute(
            "UPDATE jobs SET state = ?2, error_code = ?3, error = ?4, finished_at = ?5, expires_at = ?6
             WHERE id = ?1 AND state IN ('queued', 'running')",
            params![id, state.as_str(), code, msg, at as i64, expires_at as i64],
        )?;
        if n == 0 {
            return Ok(None);
        }
        self.row(id).map(|r| Some(r.status))
    }

    /// Put a running job back in the queue from step 0 (graceful shutdown).
    pub fn requeue(&self, id: &str) -> Result<(), JobError> {
        {
            let mut conn = self.conn()?;
            let tx = conn.transaction()?;
            tx.execute("DELETE FROM frames WHERE job_id = ?1", params![id])?;
            tx.execute(
                "UPDATE jobs SET state = 'queued', step = 0, latest = NULL, started_at = NULL
                 WHERE id = ?1 AND state = 'running'",
                params![id],
            )?;
            tx.commit()?;
        }
        let _ = fs::remove_dir_all(self.job_dir(id)?.join("frames"));
        Ok(())
    }

    /// Metrics of steps `from..` (at most `size`) and the next step to ask for.
    pub fn frame_metrics(
        &self,
        id: &str,
        from: usize,
        size: usize,
    ) -> Result<(Vec<StepMetrics>, Option<usize>), JobError> {
        let rows = self.frame_rows(id, from, size + 1)?;
        let mut metrics: Vec<StepMetrics> = rows.into_iter().map(|(m, _)| m).collect();
        let next = if metrics.len() > size {
            metrics.truncate(size);
            metrics.last().map(|m| m.step + 1)
        } else {
            None
        };
        Ok((metrics, next))
    }

    /// Stored frames `from..` (at most `limit`), with whether each kept positions.
    pub fn frame_rows(
        &self,
        id: &str,
        from: usize,
        limit: usize,
    ) -> Result<Vec<(StepMetrics, bool)>, JobError> {
        let from = i64::try_from(from).unwrap_or(i64::MAX);
        let conn = self.conn()?;
        let mut st = conn.prepare(
            "SELECT metrics, has_positions FROM frames WHERE job_id = ?1 AND step >= ?2 ORDER BY step LIMIT ?3",
        )?;
        let rows = st.query_map(params![id, from, limit as i64], |r| {
            Ok((r.get::<_, Vec<u8>>(0)?, r.get::<_, i64>(1)?))
        })?;
        let mut out = Vec::new();
        for r in rows {
            let (b, p) = r?;
            out.push((decode_metrics(&b)?, p != 0));
        }
        Ok(out)
    }

    pub fn read_frame_positions(&self, id: &str, step: usize) -> Result<Vec<[f32; 3]>, JobError> {
        bytes_to_f32s(&fs::read(self.frame_path(id, step, "f32")?)?)
    }

    pub fn read_frame_welded(&self, id: &str, step: usize) -> Result<Vec<[f64; 3]>, JobError> {
        bytes_to_f64s(&fs::read(self.frame_path(id, step, "f64")?)?)
    }

    /// Delete a terminal (or expired) job and everything it owns.
    pub fn delete(&self, id: &str) -> Result<(), JobError> {
        let row = self.row(id)?;
        if !row.expired && !row.status.state.is_terminal() {
            return Err(JobError::Conflict(format!(
                "job `{id}` is {}: cancel it first, only finished jobs can be deleted",
                row.status.state.as_str()
            )));
        }
        {
            let mut conn = self.conn()?;
            let tx = conn.transaction()?;
            tx.execute("DELETE FROM frames WHERE job_id = ?1", params![id])?;
            tx.execute("DELETE FROM idempotency WHERE job_id = ?1", params![id])?;
            tx.execute("DELETE FROM jobs WHERE id = ?1", params![id])?;
            tx.commit()?;
        }
        self.remove_job_files(id)
    }

    /// Delete the files and frames of jobs past `expires_at`, keeping a tombstone row so they
    /// answer `Gone` rather than `NotFound`. Also drops expired uploads.
    pub fn sweep_expired(&self, now: u64) -> Result<usize, JobError> {
        let ids: Vec<String> = {
            let conn = self.conn()?;
            let mut st = conn.prepare(
                "SELECT id FROM jobs WHERE expired = 0 AND expires_at IS NOT NULL AND expires_at <= ?1",
            )?;
            let rows = st.query_map(params![now as i64], |r| r.get(0))?;
            rows.collect::<Result<_, _>>()?
        };
        for id in &ids {
            {
                let mut conn = self.conn()?;
                let tx = conn.transaction()?;
                tx.execute("DELETE FROM frames WHERE job_id = ?1", params![id])?;
                tx.execute("UPDATE jobs SET expired = 1 WHERE id = ?1", params![id])?;
                tx.commit()?;
            }
            self.remove_job_files(id)?;
        }
        let uploads: Vec<(String, String)> = {
            let conn = self.conn()?;
            let mut st = conn.prepare("SELECT id, format FROM uploads WHERE expires_at <= ?1")?;
            let rows = st.query_map(params![now as i64], |r| Ok((r.get(0)?, r.get(1)?)))?;
            rows.collect::<Result<_, _>>()?
        };
        for (id, format) in &uploads {
            let _ = fs::remove_file(self.dir.join("uploads").join(format!("{id}.{format}")));
            self.conn()?
                .execute("DELETE FROM uploads WHERE id = ?1", params![id])?;
        }
        Ok(ids.len())
    }

    pub fn write_upload(
        &self,
        id: &str,
        format: Format,
        data: &[u8],
        expires_at: u64,
    ) -> Result<(), JobError> {
        let path = self
            .dir
            .join("uploads")
            .join(format!("{id}.{}", format_name(format)));
        write_atomic(&path, data, true)?;
        self.conn()?.execute(
            "INSERT INTO uploads (id, format, size, created_at, expires_at) VALUES (?1, ?2, ?3, ?4, ?5)",
            params![id, format_name(format), data.len() as i64, now_ms() as i64, expires_at as i64],
        )?;
        Ok(())
    }

    pub fn read_upload(&self, upload_id: &str) -> Result<(bytes::Bytes, Format), JobError> {
        let found: Option<(String, i64)> = self
            .conn()?
            .query_row(
                "SELECT format, expires_at FROM uploads WHERE id = ?1",
                params![upload_id],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .optional()?;
        let (format, expires_at) =
            found.ok_or_else(|| JobError::UploadNotFound(upload_id.to_string()))?;
        if expires_at <= now_ms() as i64 {
            return Err(JobError::UploadNotFound(upload_id.to_string()));
        }
        let fmt = parse_format(&format)
            .ok_or_else(|| JobError::Internal(format!("unknown stored format `{format}`")))?;
        let data = fs::read(
            self.dir
                .join("uploads")
                .join(format!("{upload_id}.{format}")),
        )?;
        Ok((bytes::Bytes::from(data), fmt))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spec with the later fields at their defaults hashes exactly as the first release
    /// hashed it (its JSON then), so stored idempotency keys survive the upgrade; a spec that
    /// sets one hashes differently.
    #[test]
    fn request_hash_is_stable_across_new_spec_fields() {
        let first_release = br#"{"method":"conformal","steps":20,"tau":0.5,"iterations":1,"frame_interval":1,"include_positions":true,"deadline_secs":null}"#;
        let mut h = Sha256::new();
        h.update(b"obj");
        h.update([0]);
        h.update(first_release);
        h.update([0]);
        h.update(b"mesh");
        let old: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
        let spec = JobSpec::default();
        assert_eq!(request_hash(b"mesh", Format::Obj, &spec), old);
        let cmc = JobSpec {
            boundary: crate::jobs::spec::BoundarySpec::Cmc,
            ..JobSpec::default()
        };
        assert_ne!(request_hash(b"mesh", Format::Obj, &cmc), old);
        let unguarded = JobSpec {
            safeguard: false,
            ..JobSpec::default()
        };
        assert_ne!(request_hash(b"mesh", Format::Obj, &unguarded), old);
        // And an old stored spec (without the new fields) still loads, with their defaults.
        let stored: JobSpec =
            serde_json::from_slice(first_release).expect("a first-release spec loads");
        assert_eq!(stored, spec);
    }

    #[test]
    fn metrics_round_trip_including_nan() {
        let m = StepMetrics {
            step: 7,
            willmore_energy: 12.5,
            q_mean: 1.0,
            q_area_mean: 1.01,
            q_p95: f64::NAN,
            q_max: f64::INFINITY,
            closure_residual: 1e-9,
            eigen_residual: 0.0,
            area: 4.0,
            step_ms: 3.25,
            tau: 0.125,
            rejected: 3,
        };
        let blob = encode_metrics(&m);
        assert_eq!(blob.len(), METRICS_BYTES);
        let back = decode_metrics(&blob).expect("a new row decodes");
        assert_eq!(back.step, 7);
        assert_eq!(back.willmore_energy, 12.5);
        assert!(back.q_p95.is_nan());
        assert_eq!(back.q_max, f64::INFINITY);
        assert_eq!(back.step_ms, 3.25);
        assert_eq!(back.tau, 0.125);
        assert_eq!(back.rejected, 3);
    }

    /// A row as the first release stored it (80 bytes, built here by hand, not by
    /// `encode_metrics`) still decodes, with `tau = 0` and `rejected = 0`.
    #[test]
    fn metrics_stored_before_the_safeguard_decode_with_tau_zero() {
        let mut old = Vec::new();
        old.extend_from_slice(&5u64.to_le_bytes());
        for v in [14.0, 1.1, 1.05, 1.2, 1.5, 1e-8, 1e-10, 12.0, 4.5] {
            old.extend_from_slice(&f64::to_le_bytes(v));
        }
        assert_eq!(old.len(), 80);
        let m = decode_metrics(&old).expect("an old row decodes");
        assert_eq!(m.step, 5);
        assert_eq!(m.willmore_energy, 14.0);
        assert_eq!(m.area, 12.0);
        assert_eq!(m.step_ms, 4.5);
        assert_eq!(m.tau, 0.0);
        assert_eq!(m.rejected, 0);
        // The new form is the old one with tau and rejected appended.
        assert_eq!(encode_metrics(&m)[..80], old[..]);
        for bad in [79, 81, 91, 93] {
            assert!(
                decode_metrics(&vec![0; bad]).is_err(),
                "{bad} bytes accepted"
            );
        }
    }

    #[test]
    fn rfc3339_known_instants() {
        assert_eq!(super::super::rfc3339(0), "1970-01-01T00:00:00.000Z");
        // 2000-02-29T12:34:56.789Z (a leap day)
        assert_eq!(
            super::super::rfc3339(951_827_696_789),
            "2000-02-29T12:34:56.789Z"
        );
    }
}
