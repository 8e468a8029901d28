//! The NATS [`BlobStore`]: the object store `willow-blobs`, objects named like the embedded
//! backend's files (`jobs/{id}/input.obj`, `jobs/{id}/frames/3.f32`, …). The object store
//! chunks large blobs (a 1M-vertex frame is 12 MB) under the server's message size limit.

use super::super::ports::{BlobKey, BlobStore};
use super::super::{format_name, JobError};
use super::{nats_err, retry};
use crate::jobs::embedded::sqlite::check_id;
use async_nats::jetstream::object_store::{GetErrorKind, ObjectStore};
use async_trait::async_trait;
use futures::StreamExt;
use tokio::io::AsyncReadExt;

pub(crate) struct ObjectBlobs {
    store: ObjectStore,
}

impl ObjectBlobs {
    pub fn new(store: ObjectStore) -> ObjectBlobs {
        ObjectBlobs { store }
    }
}

fn name(key: &BlobKey) -> Result<String, JobError> {
    if let Some(id) = key.job() {
        check_id(id)?;
    }
    Ok(match key {
        BlobKey::Input { id, format } => format!("jobs/{id}/input.{}", format_name(*format)),
        BlobKey::Frame { id, step, welded } => {
            format!(
                "jobs/{id}/frames/{step}.{}",
                if *welded { "f64" } else { "f32" }
            )
        }
        BlobKey::Result { id } => format!("jobs/{id}/result.f64"),
        BlobKey::Checkpoint { id } => format!("jobs/{id}/checkpoint"),
        BlobKey::Upload { id, format } => {
            check_id(id).map_err(|_| JobError::UploadNotFound(id.clone()))?;
            format!("uploads/{id}.{}", format_name(*format))
        }
    })
}

#[async_trait]
impl BlobStore for ObjectBlobs {
    async fn put(&self, key: BlobKey, data: bytes::Bytes) -> Result<(), JobError> {
        let name = name(&key)?;
        // A put replaces the object whole once its last chunk is in: readers see the old
        // blob or the new one.
        retry(|| async {
            self.store
                .put(name.as_str(), &mut data.as_ref())
                .await
                .map_err(|e| nats_err("storing a blob", e))
        })
        .await?;
        Ok(())
    }

    async fn get(&self, key: BlobKey) -> Result<Option<bytes::Bytes>, JobError> {
        let name = name(&key)?;
        retry(|| self.get_once(&name)).await
    }

    async fn delete(&self, key: BlobKey) -> Result<(), JobError> {
        let name = name(&key)?;
        match self.store.delete(name.as_str()).await {
            Ok(()) => Ok(()),
            Err(e) if e.to_string().contains("not found") => Ok(()),
            Err(e) => Err(nats_err("deleting a blob", e)),
        }
    }

    async fn delete_job(&self, id: &str) -> Result<(), JobError> {
        self.delete_job_blobs(id).await
    }
}

impl ObjectBlobs {
    async fn get_once(&self, name: &str) -> Result<Option<bytes::Bytes>, JobError> {
        let mut object = match self.store.get(name).await {
            Ok(o) => o,
            Err(e) if e.kind() == GetErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(nats_err("reading a blob", e)),
        };
        let mut out = Vec::with_capacity(object.info().size);
        object
            .read_to_end(&mut out)
            .await
            .map_err(|e| nats_err("reading a blob", e))?;
        Ok(Some(out.into()))
    }

    async fn delete_job_blobs(&self, id: &str) -> Result<(), JobError> {
        check_id(id)?;
        let prefix = format!("jobs/{id}/");
        let mut list = self
            .store
            .list()
            .await
            .map_err(|e| nats_err("listing blobs", e))?;
        let mut names = Vec::new();
        while let Some(info) = list.next().await {
            let info = info.map_err(|e| nats_err("listing blobs", e))?;
            if info.name.starts_with(&prefix) && !info.deleted {
                names.push(info.name);
            }
        }
        for n in names {
            if let Err(e) = self.store.delete(n.as_str()).await {
                tracing::warn!(blob = %n, error = %e, "could not delete a blob");
            }
        }
        Ok(())
    }
}
