//! The tables of the embedded store and how a database file is brought up to date: created
//! if missing, columns added since an older version, indexes, and `tenant_usage` recounted
//! from the rows at every open.

use super::super::super::ports::MINUTE_MS;
use super::super::super::{now_ms, JobError};
use super::ms;
use rusqlite::{params, Connection};

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
    received        INTEGER NOT NULL DEFAULT 1,
    callback_pending INTEGER NOT NULL DEFAULT 0,
    report          TEXT,
    checkpoint_step INTEGER,
    delivery_checkpoint INTEGER,
    stalled_deliveries INTEGER NOT NULL DEFAULT 0,
    planned_bytes   INTEGER NOT NULL DEFAULT 0
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
CREATE TABLE IF NOT EXISTS rendered (
    job_id          TEXT NOT NULL,
    name            TEXT NOT NULL,
    bytes           INTEGER NOT NULL,
    PRIMARY KEY (job_id, name)
) WITHOUT ROWID;
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
const ADDED_COLUMNS: [(&str, &str, &str); 11] = [
    ("jobs", "crashes", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "tenant", "TEXT NOT NULL DEFAULT 'default'"),
    ("jobs", "input_bytes", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "received", "INTEGER NOT NULL DEFAULT 1"),
    ("uploads", "tenant", "TEXT NOT NULL DEFAULT 'default'"),
    ("jobs", "callback_pending", "INTEGER NOT NULL DEFAULT 0"),
    ("jobs", "report", "TEXT"),
    // The delivery ledger (`JobStore::delivered`): the step of the job's checkpoint, the
    // one its last delivery saw, and deliveries in a row that found no newer one.
    ("jobs", "checkpoint_step", "INTEGER"),
    ("jobs", "delivery_checkpoint", "INTEGER"),
    ("jobs", "stalled_deliveries", "INTEGER NOT NULL DEFAULT 0"),
    // What the job may store besides its input (`jobs::stored`), counted with it.
    ("jobs", "planned_bytes", "INTEGER NOT NULL DEFAULT 0"),
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
/// - `bytes`: inputs of unexpired jobs and uploads, what those jobs may store besides
///   (`planned_bytes`: frames, checkpoint, result; `jobs::stored`), the downloads rendered and stored
///   for unexpired jobs (`rendered`, one row per stored rendering: a rendering is counted
///   once however often it is charged);
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
CREATE INDEX IF NOT EXISTS jobs_callback_pending ON jobs(seq) WHERE callback_pending != 0;
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
        bytes = bytes + (CASE WHEN NEW.expired = 0 THEN NEW.input_bytes + NEW.planned_bytes ELSE 0 END),
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
    UPDATE tenant_usage SET bytes = bytes - OLD.input_bytes - OLD.planned_bytes
    WHERE tenant = OLD.tenant;
END;
DROP TRIGGER IF EXISTS tenant_usage_job_planned;
CREATE TRIGGER tenant_usage_job_planned AFTER UPDATE OF planned_bytes ON jobs
WHEN OLD.expired = 0 AND NEW.expired = 0 AND OLD.planned_bytes != NEW.planned_bytes
BEGIN
    UPDATE tenant_usage SET bytes = bytes + NEW.planned_bytes - OLD.planned_bytes
    WHERE tenant = NEW.tenant;
END;
DROP TRIGGER IF EXISTS tenant_usage_job_out;
CREATE TRIGGER tenant_usage_job_out AFTER DELETE ON jobs
BEGIN
    UPDATE tenant_usage SET
        bytes = bytes - (CASE WHEN OLD.expired = 0 THEN OLD.input_bytes + OLD.planned_bytes ELSE 0 END),
        live = live - (OLD.state IN ('queued', 'running'))
    WHERE tenant = OLD.tenant;
END;
DROP TRIGGER IF EXISTS tenant_usage_rendered_in;
CREATE TRIGGER tenant_usage_rendered_in AFTER INSERT ON rendered
BEGIN
    UPDATE tenant_usage SET bytes = bytes + NEW.bytes
    WHERE tenant = (SELECT tenant FROM jobs WHERE id = NEW.job_id AND expired = 0);
END;
DROP TRIGGER IF EXISTS tenant_usage_rendered_out;
CREATE TRIGGER tenant_usage_rendered_out AFTER DELETE ON rendered
BEGIN
    UPDATE tenant_usage SET bytes = bytes - OLD.bytes
    WHERE tenant = (SELECT tenant FROM jobs WHERE id = OLD.job_id AND expired = 0);
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
pub(super) const RECOUNT_USAGE: &str = "
INSERT INTO tenant_usage (tenant, bytes, live, window_start, window_count, previous_count)
    SELECT tenant, SUM(b), SUM(l), ?1, SUM(c >= ?1), SUM(c >= ?1 - 60000 AND c < ?1) FROM (
        SELECT tenant, (CASE WHEN expired = 0 THEN input_bytes + planned_bytes ELSE 0 END) AS b,
               (state IN ('queued', 'running')) AS l,
               (CASE WHEN received != 0 THEN created_at ELSE 0 END) AS c FROM jobs
        UNION ALL SELECT tenant, size, 0, created_at FROM uploads
        UNION ALL SELECT j.tenant, r.bytes, 0, 0 FROM rendered r JOIN jobs j ON j.id = r.job_id
            WHERE j.expired = 0
    ) GROUP BY tenant;
";

/// Bring the database behind `conn` to this version's schema (idempotent: run at every open).
pub(super) fn prepare(conn: &Connection) -> Result<(), JobError> {
    conn.busy_timeout(BUSY_TIMEOUT)?;
    // WAL: readers never block the writer; NORMAL: a commit survives a process crash
    // (SIGKILL), and power loss can lose only the last transactions, not corrupt the file.
    conn.pragma_update(None, "journal_mode", "WAL")?;
    conn.pragma_update(None, "synchronous", "NORMAL")?;
    match upgrade(conn) {
        Ok(()) => Ok(()),
        // A full disk: the tables of the previous start serve as they are (their triggers are
        // the last release's; `tenant_usage` was kept current by them), so the server starts
        // and serves reads. A database that has no tables yet cannot.
        Err(JobError::StorageFull { detail }) if has_tables(conn)? => {
            tracing::error!(error = %detail, "storage full: schema check skipped, the database is used as it is");
            Ok(())
        }
        Err(e) => Err(e),
    }
}

/// Whether every table exists already (a database this or an earlier release created).
fn has_tables(conn: &Connection) -> Result<bool, JobError> {
    let n: i64 = conn.query_row(
        "SELECT count(*) FROM sqlite_master WHERE type = 'table'
         AND name IN ('jobs', 'frames', 'idempotency', 'uploads', 'tenant_usage')",
        [],
        |r| r.get(0),
    )?;
    Ok(n == 5)
}

/// Create, extend and recount, in one transaction: a write that fails half way (a full disk)
/// leaves the database as it was.
fn upgrade(conn: &Connection) -> Result<(), JobError> {
    conn.execute_batch("BEGIN IMMEDIATE")?;
    let done = upgrade_in_transaction(conn);
    match done {
        Ok(()) => {
            if let Err(e) = conn.execute_batch("COMMIT") {
                let _ = conn.execute_batch("ROLLBACK");
                return Err(e.into());
            }
            Ok(())
        }
        Err(e) => {
            let _ = conn.execute_batch("ROLLBACK");
            Err(e)
        }
    }
}

fn upgrade_in_transaction(conn: &Connection) -> Result<(), JobError> {
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
    Ok(())
}
