//! What a job gives back: its events (live and replayed), its frames' metrics, a kept
//! frame as a mesh and the result file. Each download re-reads the stored upload
//! (`JobSpec::read_asset`) and writes the positions into it.
//!
//! For a job with `refine` that re-read subdivides again. It is deterministic, and cheap by
//! construction: the default target stops at about 16k–64k triangles, and inputs already
//! that fine are not subdivided. Measured (debug profile, which optimizes; 2 shared cores):
//! refining adds 45 ms to a download of the Duck (4k → 17k faces), 52 ms for spot (6k →
//! 23k), 74 ms for bob (500 → 32k), about what reading a file of the refined size costs,
//! and less than reading a 70k-face upload (the bunny: 300 ms). Storing the refined asset
//! instead would need a stable serialization of `Asset` in both blob stores; a written file
//! read back does not keep the refined numbering of a multi-accessor glTF.

use super::*;

impl Jobs {
    /// Events of a job from `from_step` on: its current state, the stored frames (replay),
    /// then live frames, ending with `Done`. A watcher that falls behind the live channel
    /// resumes from the store, so it sees every step once and in order, and never slows the
    /// worker down.
    pub async fn watch(
        &self,
        caller: &Caller,
        id: &str,
        from_step: usize,
    ) -> Result<impl Stream<Item = JobEvent> + Send + 'static, JobError> {
        self.read(watch::watch(
            self.clone(),
            &caller.tenant,
            id.to_string(),
            from_step,
        ))
        .await
    }

    /// Metrics of steps `from_step..` (at most `page_size`, 0 = 100, max 10 000) and the step
    /// to ask for next, if any.
    pub async fn frames(
        &self,
        caller: &Caller,
        id: &str,
        from_step: usize,
        page_size: usize,
    ) -> Result<(Vec<StepMetrics>, Option<usize>), JobError> {
        let size = match page_size {
            0 => 100,
            n => n.min(10_000),
        };
        let store = &self.inner.backend.store;
        let rows = self
            .read(async {
                store.status(id, Some(&caller.tenant)).await?;
                store.frame_rows(id, from_step, size + 1).await
            })
            .await?;
        let mut metrics: Vec<StepMetrics> = rows.into_iter().map(|(m, _)| m).collect();
        let next = if metrics.len() > size {
            metrics.truncate(size);
            metrics.last().map(|m| m.step + 1)
        } else {
            None
        };
        Ok((metrics, next))
    }

    /// The mesh after `step` in `format`, for steps that kept positions.
    pub async fn frame_mesh(
        &self,
        caller: &Caller,
        id: &str,
        step: usize,
        format: Format,
    ) -> Result<Vec<u8>, JobError> {
        let status = self.get(caller, id).await?;
        let kept = if step <= status.step {
            let rows = self
                .read(self.inner.backend.store.frame_rows(id, step, 1))
                .await?;
            rows.first().is_some_and(|(m, p)| m.step == step && *p)
        } else {
            false
        };
        let key = BlobKey::Frame {
            id: status.id.clone(),
            step,
            welded: true,
        };
        let bytes = if kept {
            self.on_request(self.inner.backend.blobs.get(key)).await?
        } else {
            None
        };
        let Some(bytes) = bytes else {
            let detail = if step > status.step
                || (step == status.step && !status.state.is_terminal() && status.latest.is_none())
            {
                format!(
                    "the job has completed {} of {} steps",
                    status.step, status.total_steps
                )
            } else if !status.spec.include_positions {
                "the job was submitted with include_positions=false".to_string()
            } else {
                format!(
                    "positions are kept at step 0, every {} steps and the last step",
                    status.spec.frame_interval
                )
            };
            return Err(JobError::FrameNotFound {
                id: id.to_string(),
                step,
                detail,
            });
        };
        self.render(&status, codec::bytes_to_f64s(&bytes)?, format)
            .await
    }

    /// The faired mesh in `format` (input UVs, materials and textures kept). `Conflict` until
    /// the job succeeded.
    pub async fn result(
        &self,
        caller: &Caller,
        id: &str,
        format: Format,
    ) -> Result<Vec<u8>, JobError> {
        let status = self.get(caller, id).await?;
        if status.state != JobState::Succeeded {
            return Err(JobError::Conflict(format!(
                "job `{id}` is {}: only a succeeded job has a result",
                status.state.as_str()
            )));
        }
        let key = BlobKey::Result {
            id: status.id.clone(),
        };
        let bytes = self
            .on_request(self.inner.backend.blobs.get(key))
            .await?
            .ok_or_else(|| JobError::Internal(format!("the result of job `{id}` is missing")))?;
        self.render(&status, codec::bytes_to_f64s(&bytes)?, format)
            .await
    }

    /// Write `positions` (welded, f64) over the job's input asset in `format`.
    async fn render(
        &self,
        status: &JobStatus,
        positions: Vec<[f64; 3]>,
        format: Format,
    ) -> Result<Vec<u8>, JobError> {
        let key = BlobKey::Input {
            id: status.id.clone(),
            format: status.input_format,
        };
        let input = self
            .on_request(self.inner.backend.blobs.get(key))
            .await?
            .ok_or_else(|| {
                JobError::Internal(format!("the input of job `{}` is missing", status.id))
            })?;
        let (input_format, limits) = (status.input_format, self.inner.config.limits.mesh_limits());
        let spec = status.spec.clone();
        tokio::task::spawn_blocking(move || {
            let asset = spec
                .read_asset(&input, input_format, &limits)
                .map_err(JobError::InvalidMesh)?;
            asset
                .write(&positions, format)
                .map_err(|e| JobError::Internal(format!("writing {}: {e}", format_name(format))))
        })
        .await
        .map_err(join_err)?
    }

    /// Wait until the job is terminal or `timeout` passed; returns the status either way.
    pub async fn wait(
        &self,
        caller: &Caller,
        id: &str,
        timeout: std::time::Duration,
    ) -> Result<JobStatus, JobError> {
        use futures::StreamExt;
        let status = self.get(caller, id).await?;
        if status.state.is_terminal() {
            return Ok(status);
        }
        let mut events = Box::pin(self.watch(caller, id, usize::MAX).await?);
        let waited = tokio::time::timeout(timeout, async {
            while let Some(ev) = events.next().await {
                if let JobEvent::Done(s) = ev {
                    return Some(s);
                }
            }
            None
        })
        .await;
        match waited {
            Ok(Some(s)) => Ok(s),
            _ => self.get(caller, id).await,
        }
    }
}
