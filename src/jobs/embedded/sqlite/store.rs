//! [`SqliteStore`] behind the [`JobStore`] port: each call one blocking closure over the
//! connection (the `*_now` helpers of the store, or a transaction of its own).

use super::super::super::codec::encode_metrics;
use super::super::super::ports::{
    over_quota, Admitting, Fence, Inserted, JobStore, NewJob, OverQuota, Recovered, Started, Swept,
    Usage,
};
use super::super::super::{
    format_name, now_ms, parse_format, FailureCode, JobError, JobId, JobState, JobStatus,
    TenantQuotas,
};
use super::{ms, row_to_status, usage_on, SqliteStore, STATUS_COLUMNS};
use async_trait::async_trait;
use rusqlite::{params, OptionalExtension};
use willow::mesh::io::Format;
use willow::metrics::StepMetrics;

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
        fence.renewed(now_ms());
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
                // A job that never started stored nothing but its input: its plan goes
                // (`tenant_usage_job_planned` gives the bytes back).
                "UPDATE jobs SET state = ?2, error_code = ?3, error = ?4, finished_at = ?5, expires_at = ?6,
                                 planned_bytes = CASE WHEN started_at IS NULL THEN 0 ELSE planned_bytes END
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
                "UPDATE jobs SET state = 'queued', stalled_deliveries = 0
                 WHERE id = ?1 AND state = 'running'",
                params![id],
            )?;
            Ok(())
        })
        .await
    }

    async fn checkpointed(&self, id: &str, step: usize, _fence: &Fence) -> Result<(), JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            s.conn()?.execute(
                "UPDATE jobs SET checkpoint_step = ?2 WHERE id = ?1 AND state = 'running'",
                params![id, i64::try_from(step).unwrap_or(i64::MAX)],
            )?;
            Ok(())
        })
        .await
    }

    async fn settle_planned(&self, id: &str, bytes: u64, _fence: &Fence) -> Result<(), JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            // `tenant_usage_job_planned` moves the tenant's bytes with it.
            s.conn()?.execute(
                "UPDATE jobs SET planned_bytes = ?2
                 WHERE id = ?1 AND state = 'running' AND planned_bytes > ?2",
                params![id, ms(bytes)],
            )?;
            Ok(())
        })
        .await
    }

    async fn delivered(&self, id: &str, _fence: &Fence) -> Result<u32, JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            // `IS` compares NULLs too: no checkpoint then and none now is no progress.
            let stalled: Option<i64> = s
                .conn()?
                .query_row(
                    "UPDATE jobs SET
                       stalled_deliveries = CASE WHEN checkpoint_step IS delivery_checkpoint
                                            THEN stalled_deliveries + 1 ELSE 1 END,
                       delivery_checkpoint = checkpoint_step
                     WHERE id = ?1 RETURNING stalled_deliveries",
                    params![id],
                    |r| r.get(0),
                )
                .optional()?;
            let stalled = stalled.ok_or_else(|| JobError::NotFound(id.clone()))?;
            Ok(u32::try_from(stalled).unwrap_or(u32::MAX))
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
            forget_rendered(&tx, &id)?;
            tx.execute("DELETE FROM idempotency WHERE job_id = ?1", params![id])?;
            tx.execute("DELETE FROM jobs WHERE id = ?1", params![id])?;
            tx.commit()?;
            Ok(())
        })
        .await
    }

    async fn charge_rendered(
        &self,
        id: &str,
        name: &str,
        bytes: u64,
        quotas: &TenantQuotas,
    ) -> Result<Option<OverQuota>, JobError> {
        let (id, name, quotas) = (id.to_string(), name.to_string(), quotas.clone());
        self.blocking(move |s| {
            let row = s.row(&id)?;
            if row.expired {
                return Err(JobError::Gone(id));
            }
            let mut conn = s.conn()?;
            // One transaction: concurrent charges of one tenant cannot both take the last
            // bytes of its quota.
            let tx = conn.transaction()?;
            let counted = tx
                .prepare_cached("SELECT 1 FROM rendered WHERE job_id = ?1 AND name = ?2")?
                .exists(params![id, name])?;
            if counted {
                return Ok(None);
            }
            if quotas.any() {
                let usage = usage_on(&tx, &row.status.tenant, now_ms())?;
                if let Some(over) = over_quota(&quotas, &usage, bytes, Admitting::Rendered) {
                    return Ok(Some(over));
                }
            }
            tx.prepare_cached("INSERT INTO rendered (job_id, name, bytes) VALUES (?1, ?2, ?3)")?
                .execute(params![id, name, ms(bytes)])?;
            tx.commit()?;
            Ok(None)
        })
        .await
    }

    async fn refund_rendered(&self, id: &str, name: &str) -> Result<(), JobError> {
        let (id, name) = (id.to_string(), name.to_string());
        self.blocking(move |s| {
            s.conn()?.execute(
                "DELETE FROM rendered WHERE job_id = ?1 AND name = ?2",
                params![id, name],
            )?;
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
                forget_rendered(&tx, id)?;
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

    async fn pending_callbacks(&self, limit: usize) -> Result<Vec<JobStatus>, JobError> {
        self.blocking(move |s| {
            let conn = s.conn()?;
            // The partial index holds only the pending rows: this stays cheap however many
            // jobs the store keeps.
            let mut st = conn.prepare_cached(&format!(
                "SELECT {STATUS_COLUMNS} FROM jobs WHERE callback_pending != 0
                   AND state IN ('succeeded', 'failed', 'cancelled') AND expired = 0
                 ORDER BY seq LIMIT ?1"
            ))?;
            let rows = st.query_map(params![ms(limit as u64)], row_to_status)?;
            let mut out = Vec::new();
            for row in rows {
                out.push(row??.status);
            }
            Ok(out)
        })
        .await
    }

    async fn settle_callback(&self, id: &str) -> Result<(), JobError> {
        let id = id.to_string();
        self.blocking(move |s| {
            s.conn()?.execute(
                "UPDATE jobs SET callback_pending = 0 WHERE id = ?1",
                params![id],
            )?;
            Ok(())
        })
        .await
    }

    async fn server_stored_bytes(&self) -> Result<u64, JobError> {
        self.blocking(move |s| Ok(usage_on(&*s.conn()?, "", 0)?.server_stored_bytes))
            .await
    }

    async fn usage(&self, tenant: &str, now: u64) -> Result<Usage, JobError> {
        let tenant = tenant.to_string();
        self.blocking(move |s| usage_on(&*s.conn()?, &tenant, now))
            .await
    }
}

/// Forget the stored renderings of job `id` (their count leaves its tenant's bytes while the
/// job is unexpired: call before it expires or goes). A database from before `rendered` that
/// could not be upgraded (a full disk at start) has none to forget, and a delete must work
/// there.
fn forget_rendered(conn: &rusqlite::Connection, id: &str) -> Result<(), JobError> {
    match conn.execute("DELETE FROM rendered WHERE job_id = ?1", params![id]) {
        Ok(_) => Ok(()),
        Err(e) if e.to_string().contains("no such table") => Ok(()),
        Err(e) => Err(e.into()),
    }
}
