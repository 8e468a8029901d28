//! What a job gives back: its events (live and replayed), its frames' metrics, a kept
//! frame as a mesh and the result file. A mesh is rendered by re-reading the stored upload
//! (`JobSpec::read_asset`) and writing the positions into it; downloads render it once, store
//! it and stream it from storage ([`Jobs::rendered`]).
//!
//! For a job with `refine` the re-read subdivides again, once per rendering. It is
//! deterministic, and cheap by construction: the default target stops at about 16k–64k
//! triangles, and inputs already that fine are not subdivided. Measured (debug profile, which
//! optimizes; 2 shared cores): refining adds 45 ms to rendering the Duck (4k → 17k faces),
//! 52 ms for spot (6k → 23k), 74 ms for bob (500 → 32k), about what reading a file of the
//! refined size costs, and less than reading a 70k-face upload (the bunny: 300 ms).

use super::*;
use ports::BlobReader;
use render_memory::{render_estimate, DownloadMemory, RENDER_WAIT};

/// Renders that may run at once ([`Jobs::rendered`]); renders of one key share a stripe, so
/// they run one after the other and only the first renders.
pub(super) const RENDER_STRIPES: usize = 8;

/// A mesh download, as the transports send it.
pub enum MeshDownload {
    /// Streamed from its stored rendering, a chunk at a time.
    Stored(BlobReader),
    /// Held whole in memory (it could not be stored).
    Whole(bytes::Bytes),
}

impl MeshDownload {
    /// Its length in bytes.
    pub fn len(&self) -> u64 {
        match self {
            MeshDownload::Stored(r) => r.len,
            MeshDownload::Whole(b) => b.len() as u64,
        }
    }

    /// Whether it is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes `first..=last` of it (`first <= last < len`, as the caller resolved them; a
    /// `last` past the end is cut there), for a resumed download.
    ///
    /// A stored download is read from its start and the bytes before `first` dropped as they
    /// arrive: the stores hand out blobs in order only, and what a skip costs is a read, not
    /// memory (a chunk at a time). One held whole is copied, so the range does not keep the
    /// whole buffer alive while it waits for its client.
    pub fn range(self, first: u64, last: u64) -> MeshDownload {
        use futures::StreamExt;
        let last = last.min(self.len().saturating_sub(1));
        let take = (last + 1).saturating_sub(first);
        match self {
            MeshDownload::Whole(b) => {
                let (from, to) = (first as usize, (last as usize + 1).min(b.len()));
                MeshDownload::Whole(bytes::Bytes::copy_from_slice(
                    b.get(from..to).unwrap_or_default(),
                ))
            }
            MeshDownload::Stored(r) => {
                let chunks = futures::stream::unfold(
                    (r.chunks, first, take),
                    |(mut chunks, mut skip, take)| async move {
                        if take == 0 {
                            return None;
                        }
                        loop {
                            let mut c = match chunks.next().await? {
                                Ok(c) => c,
                                Err(e) => return Some((Err(e), (chunks, skip, 0))),
                            };
                            let n = c.len() as u64;
                            if skip >= n {
                                skip -= n;
                                continue;
                            }
                            c = c.slice(skip as usize..);
                            c.truncate(usize::try_from(take).unwrap_or(usize::MAX));
                            let left = take - c.len() as u64;
                            return Some((Ok(c), (chunks, 0, left)));
                        }
                    },
                )
                .boxed();
                MeshDownload::Stored(BlobReader { len: take, chunks })
            }
        }
    }
}

/// The stripe of [`Inner::renders`] a key renders under.
fn render_stripe(key: &BlobKey) -> usize {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    format!("{key:?}").hash(&mut h);
    (h.finish() % RENDER_STRIPES as u64) as usize
}

impl Jobs {
    /// Events of a job from `from_step` on: its current state, the stored frames (replay),
    /// then live frames, ending with `Done`. A watcher that falls behind the live channel
    /// resumes from the store, so it sees every step once and in order, and never slows the
    /// worker down. A client slower than the default [`watch::WatchFloor`] is cut off.
    pub async fn watch(
        &self,
        caller: &Caller,
        id: &str,
        from_step: usize,
    ) -> Result<watch::Watch, JobError> {
        self.watch_with_floor(caller, id, from_step, watch::WatchFloor::default())
            .await
    }

    /// [`Jobs::watch`] for a client that must keep up with `floor` (the transports pass their
    /// connection's write deadline and minimum rate).
    pub async fn watch_with_floor(
        &self,
        caller: &Caller,
        id: &str,
        from_step: usize,
        floor: watch::WatchFloor,
    ) -> Result<watch::Watch, JobError> {
        self.read(watch::watch(
            self.clone(),
            &caller.tenant,
            id.to_string(),
            from_step,
            floor,
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
        let positions = self.frame_positions(&status, step).await?;
        self.render(&status, positions, format).await
    }

    /// [`Jobs::frame_mesh`] as a download: rendered once, stored, and streamed from storage
    /// (see [`Jobs::rendered`]).
    ///
    /// The rendering is named after the version of the positions it is rendered from
    /// ([`BlobKey::Rendered::source`]): a job resumed from a checkpoint before `step` writes
    /// the step's positions again, and the next download renders those, not the stored
    /// rendering of the first run.
    pub async fn frame_download(
        &self,
        caller: &Caller,
        id: &str,
        step: usize,
        format: Format,
        memory: Option<&DownloadMemory>,
    ) -> Result<MeshDownload, JobError> {
        let status = self.get(caller, id).await?;
        self.kept_frame(&status, step).await?;
        let positions = BlobKey::Frame {
            id: status.id.clone(),
            step,
            welded: true,
        };
        let source = self
            .on_request(self.inner.backend.blobs.version(positions))
            .await?
            .ok_or_else(|| self.frame_not_found(&status, step))?;
        let key = BlobKey::Rendered {
            id: status.id.clone(),
            step: Some(step),
            format,
            source: Some(ports::rendered_source(&source)),
        };
        let positions = self.frame_positions(&status, step);
        self.rendered(key, &status, memory, positions).await
    }

    /// Whether the job's progress has reached `step` and the step kept positions; the
    /// reason why not ([`JobError::FrameNotFound`]) otherwise.
    async fn kept_frame(&self, status: &JobStatus, step: usize) -> Result<(), JobError> {
        let kept = if step <= status.step {
            let rows = self
                .read(self.inner.backend.store.frame_rows(&status.id, step, 1))
                .await?;
            rows.first().is_some_and(|(m, p)| m.step == step && *p)
        } else {
            false
        };
        if kept {
            Ok(())
        } else {
            Err(self.frame_not_found(status, step))
        }
    }

    /// The stored welded positions of `step`, or why there are none.
    async fn frame_positions(
        &self,
        status: &JobStatus,
        step: usize,
    ) -> Result<Vec<[f64; 3]>, JobError> {
        self.kept_frame(status, step).await?;
        let key = BlobKey::Frame {
            id: status.id.clone(),
            step,
            welded: true,
        };
        let bytes = self
            .on_request(self.inner.backend.blobs.get(key))
            .await?
            .ok_or_else(|| self.frame_not_found(status, step))?;
        codec::bytes_to_f64s(&bytes)
    }

    /// Why `status`'s job has no mesh for `step`.
    fn frame_not_found(&self, status: &JobStatus, step: usize) -> JobError {
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
        JobError::FrameNotFound {
            id: status.id.to_string(),
            step,
            detail,
        }
    }

    /// The faired mesh in `format` (input UVs, materials and textures kept). `Conflict` until
    /// the job succeeded.
    pub async fn result(
        &self,
        caller: &Caller,
        id: &str,
        format: Format,
    ) -> Result<Vec<u8>, JobError> {
        let status = self.succeeded(caller, id).await?;
        let positions = self.result_positions(&status).await?;
        self.render(&status, positions, format).await
    }

    /// [`Jobs::result`] as a download: rendered once, stored, and streamed from storage (see
    /// [`Jobs::rendered`]). A first render holds its memory from `memory`, the server's
    /// download budget (`None`: uncounted, for callers without one).
    pub async fn result_download(
        &self,
        caller: &Caller,
        id: &str,
        format: Format,
        memory: Option<&DownloadMemory>,
    ) -> Result<MeshDownload, JobError> {
        let status = self.succeeded(caller, id).await?;
        let key = BlobKey::Rendered {
            id: status.id.clone(),
            step: None,
            format,
            source: None,
        };
        let positions = self.result_positions(&status);
        self.rendered(key, &status, memory, positions).await
    }

    /// The job's status if it succeeded; `Conflict` otherwise.
    async fn succeeded(&self, caller: &Caller, id: &str) -> Result<JobStatus, JobError> {
        let status = self.get(caller, id).await?;
        if status.state != JobState::Succeeded {
            return Err(JobError::Conflict(format!(
                "job `{id}` is {}: only a succeeded job has a result",
                status.state.as_str()
            )));
        }
        Ok(status)
    }

    async fn result_positions(&self, status: &JobStatus) -> Result<Vec<[f64; 3]>, JobError> {
        let key = BlobKey::Result {
            id: status.id.clone(),
        };
        let bytes = self
            .on_request(self.inner.backend.blobs.get(key))
            .await?
            .ok_or_else(|| {
                JobError::Internal(format!("the result of job `{}` is missing", status.id))
            })?;
        codec::bytes_to_f64s(&bytes)
    }

    /// The download stored under `key`, rendered by `render` and stored first if it is not
    /// there yet.
    ///
    /// Why store it rather than stream the writer's output: the mesh writers need the whole
    /// asset and positions in memory (a glTF's buffer offsets and an OBJ's groups are known
    /// only at the end), so a writer feeding a slow client would pin the asset, its output
    /// and a blocking thread for as long as the client dawdles (issue 25 item 6: ~12 MB a
    /// client). Rendered once and stored, a download is read from storage a chunk at a time
    /// as its client takes it, so a client that never reads pins one chunk; and a repeat
    /// download (a page reload, many viewers of one result) renders nothing.
    ///
    /// Renders of the same key wait for each other (the second finds the first's blob), and
    /// at most [`RENDER_STRIPES`] run at once. The memory a render takes is held from the
    /// server's download budget (`memory`), so renders and the downloads waiting for their
    /// clients together stay within it: the render's estimate ([`render_estimate`]) before it
    /// starts, more if the positions are more than the job recorded (a refined mesh), then the
    /// output's real length while it is stored; a render that finds no room within
    /// [`RENDER_WAIT`] is refused with [`JobError::DownloadsBusy`].
    ///
    /// A stored rendering counts in its tenant's `stored_bytes` quota until the job is
    /// deleted or expires ([`ports::JobStore::charge_rendered`]). When it cannot be stored
    /// (storage full, or the tenant's quota has no room for it) it is handed out whole from
    /// memory, uncounted: a download is a read of a job the tenant already has, and the
    /// stored copy is the server's cache, so a tenant at its quota still gets its result (as
    /// it can still read its job and its frames); the download budget bounds that memory, and
    /// the price is a render per download until the tenant frees room.
    async fn rendered(
        &self,
        key: BlobKey,
        status: &JobStatus,
        memory: Option<&DownloadMemory>,
        positions: impl std::future::Future<Output = Result<Vec<[f64; 3]>, JobError>>,
    ) -> Result<MeshDownload, JobError> {
        let blobs = &self.inner.backend.blobs;
        if let Some(r) = self.on_request(blobs.open(key.clone())).await? {
            return Ok(MeshDownload::Stored(r));
        }
        let _one_at_a_time = self.inner.renders[render_stripe(&key)].lock().await;
        if let Some(r) = self.on_request(blobs.open(key.clone())).await? {
            return Ok(MeshDownload::Stored(r));
        }
        let BlobKey::Rendered {
            id,
            step,
            format,
            source,
        } = &key
        else {
            return Err(JobError::Internal(format!("{key:?} is not a rendering")));
        };
        let estimate =
            |vertices: usize, faces: usize| render_estimate(status.input_bytes, vertices, faces);
        let mut hold = match memory {
            Some(m) => {
                let bytes = estimate(status.vertex_count, status.face_count);
                Some(m.hold(bytes, RENDER_WAIT).await?)
            }
            None => None,
        };
        let positions = positions.await?;
        if let Some(h) = &mut hold {
            // A refined job's positions are more than its upload's vertices; its faces about
            // twice its vertices (a closed surface: F = 2V − 2χ).
            let vertices = positions.len().max(status.vertex_count);
            let faces = status.face_count.max(2 * positions.len());
            h.fit(estimate(vertices, faces).max(h.bytes()), RENDER_WAIT)
                .await?;
        }
        let data = bytes::Bytes::from(self.render(status, positions, *format).await?);
        if let Some(h) = &mut hold {
            // What is left is the output: hold its length while it is stored.
            h.fit(data.len() as u64, RENDER_WAIT).await?;
        }
        if self.inner.storage.is_full() {
            return Ok(MeshDownload::Whole(data));
        }
        let name = ports::rendered_name(*step, *format, source.as_deref());
        let store = &self.inner.backend.store;
        let quotas = &self.inner.config.quotas;
        let charged = self.on_request(store.charge_rendered(id, &name, data.len() as u64, quotas));
        match charged.await {
            Ok(None) => {}
            Ok(Some(over)) => {
                tracing::info!(
                    job = %id, quota = over.quota, limit = over.limit, used = over.used,
                    "a rendered download is over its tenant's quota; served from memory, not stored"
                );
                return Ok(MeshDownload::Whole(data));
            }
            Err(e) => {
                tracing::warn!(job = %id, error = %e, "a rendered download could not be counted; serving it from memory");
                return Ok(MeshDownload::Whole(data));
            }
        }
        match self.on_request(blobs.put(key.clone(), data.clone())).await {
            Ok(()) => Ok(match self.on_request(blobs.open(key)).await? {
                Some(r) => MeshDownload::Stored(r),
                // Deleted in between (the job expired): this request still gets its bytes.
                None => MeshDownload::Whole(data),
            }),
            Err(e) => {
                let e = self.inner.storage.noted(e);
                tracing::warn!(error = %e, "a rendered download could not be stored; serving it from memory");
                if let Err(e) = self.on_request(store.refund_rendered(id, &name)).await {
                    tracing::warn!(job = %id, error = %e, "the count of an unstored rendering stays until its job goes");
                }
                Ok(MeshDownload::Whole(data))
            }
        }
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
            let asset = spec.read_asset(&input, input_format, &limits)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use futures::StreamExt;

    async fn collect(d: MeshDownload) -> Vec<u8> {
        match d {
            MeshDownload::Whole(b) => b.to_vec(),
            MeshDownload::Stored(r) => {
                let len = r.len;
                let chunks: Vec<_> = r.chunks.collect().await;
                let out: Vec<u8> = chunks
                    .into_iter()
                    .flat_map(|c| c.expect("chunk").to_vec())
                    .collect();
                assert_eq!(out.len() as u64, len, "the announced length");
                out
            }
        }
    }

    /// A range of a stored download (in chunks of every size, the range starting and ending
    /// inside, on and across chunk borders) and of one held whole gives those bytes.
    #[tokio::test]
    async fn a_range_gives_its_bytes_from_stored_and_whole_downloads() {
        let data: Vec<u8> = (0..100u8).collect();
        for chunk in [1, 7, 10, 64, 100] {
            for (first, last) in [
                (0, 99),
                (0, 0),
                (9, 10),
                (10, 19),
                (33, 77),
                (99, 99),
                (95, 500),
            ] {
                let pieces: Vec<Result<bytes::Bytes, JobError>> = data
                    .chunks(chunk)
                    .map(|c| Ok(bytes::Bytes::copy_from_slice(c)))
                    .collect();
                let stored = MeshDownload::Stored(BlobReader {
                    len: 100,
                    chunks: futures::stream::iter(pieces).boxed(),
                });
                let want = &data[first..=last.min(99)];
                let got = collect(stored.range(first as u64, last as u64)).await;
                assert_eq!(got, want, "chunks of {chunk}, {first}-{last}");
                let whole = MeshDownload::Whole(bytes::Bytes::from(data.clone()));
                let got = collect(whole.range(first as u64, last as u64)).await;
                assert_eq!(got, want, "whole, {first}-{last}");
            }
        }
    }
}
