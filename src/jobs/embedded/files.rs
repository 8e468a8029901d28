//! The embedded [`BlobStore`]: files under the data dir.
//!
//! ```text
//! jobs/{id}/input.{obj|glb|gltf}   the upload, as received
//! jobs/{id}/frames/{step}.f32      positions in the file's vertex order, f32 LE xyz (payload)
//! jobs/{id}/frames/{step}.f64      welded positions, f64 LE xyz (to write frame meshes)
//! jobs/{id}/result.f64             final welded positions, f64 LE xyz
//! jobs/{id}/checkpoint             the flow's latest checkpoint (codec::encode_checkpoint)
//! jobs/{id}/rendered/result.{ext}  the result as downloaded, rendered once (streamed from here)
//! jobs/{id}/rendered/{step}-{source}.{ext}  a kept frame's mesh as downloaded, likewise;
//!                                  `source` names the positions it was rendered from
//! uploads/{id}.{ext}               uploads stored ahead of a job (chunked gRPC)
//! ```
//! Every file is written to a temporary name and renamed into place, so a reader sees the old
//! blob or the whole new one. Frames are not fsynced: a process crash keeps them (the page
//! cache survives it), and after a power loss a job resumes from its checkpoint and writes
//! them again. Everything else is ([`BlobKey::durable`]).

use super::super::ids::well_formed;
use super::super::ports::{rendered_name, BlobKey, BlobReader, BlobStore};
use super::super::{format_name, join_err, JobError, JobId};
use async_trait::async_trait;
use std::fs;
use std::io::Write;
use tokio::io::AsyncReadExt;

/// What an open blob reads at a time ([`BlobStore::open`]): what a download holds per
/// client while it waits to be taken.
const READ_CHUNK_BYTES: usize = 64 << 10;
use std::path::{Path, PathBuf};

#[derive(Clone)]
pub struct FileBlobs {
    dir: PathBuf,
}

impl FileBlobs {
    pub fn open(dir: &Path) -> Result<FileBlobs, JobError> {
        fs::create_dir_all(dir.join("jobs"))?;
        fs::create_dir_all(dir.join("uploads"))?;
        Ok(FileBlobs {
            dir: dir.to_path_buf(),
        })
    }

    fn job_dir(&self, id: &str) -> Result<PathBuf, JobError> {
        JobId::parse(id)?;
        Ok(self.dir.join("jobs").join(id))
    }

    fn path(&self, key: &BlobKey) -> Result<PathBuf, JobError> {
        Ok(match key {
            BlobKey::Input { id, format } => self
                .job_dir(id)?
                .join(format!("input.{}", format_name(*format))),
            BlobKey::Frame { id, step, welded } => self
                .job_dir(id)?
                .join("frames")
                .join(format!("{step}.{}", if *welded { "f64" } else { "f32" })),
            BlobKey::Result { id } => self.job_dir(id)?.join("result.f64"),
            BlobKey::Checkpoint { id } => self.job_dir(id)?.join("checkpoint"),
            BlobKey::Rendered {
                id,
                step,
                format,
                source,
            } => self.job_dir(id)?.join("rendered").join(rendered_name(
                *step,
                *format,
                source.as_deref(),
            )),
            BlobKey::Upload { id, format } => {
                if !well_formed(id) {
                    return Err(JobError::UploadNotFound(id.clone()));
                }
                self.dir
                    .join("uploads")
                    .join(format!("{id}.{}", format_name(*format)))
            }
        })
    }
}

#[async_trait]
impl BlobStore for FileBlobs {
    async fn put(&self, key: BlobKey, data: bytes::Bytes) -> Result<(), JobError> {
        let path = self.path(&key)?;
        let durable = key.durable();
        tokio::task::spawn_blocking(move || write_atomic(&path, &data, durable))
            .await
            .map_err(join_err)?
    }

    async fn get(&self, key: BlobKey) -> Result<Option<bytes::Bytes>, JobError> {
        let path = self.path(&key)?;
        tokio::task::spawn_blocking(move || match fs::read(&path) {
            Ok(b) => Ok(Some(bytes::Bytes::from(b))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        })
        .await
        .map_err(join_err)?
    }

    async fn open(&self, key: BlobKey) -> Result<Option<BlobReader>, JobError> {
        let path = self.path(&key)?;
        // The open handle keeps reading the file it opened even if a put renames a new one
        // over it or the job is deleted: a reader sees one whole blob.
        let file = match tokio::fs::File::open(&path).await {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e.into()),
        };
        let len = file.metadata().await?.len();
        let chunks = futures::stream::try_unfold((file, len), |(mut file, left)| async move {
            if left == 0 {
                return Ok(None);
            }
            let want = left.min(READ_CHUNK_BYTES as u64) as usize;
            let mut buf = vec![0u8; want];
            file.read_exact(&mut buf).await?;
            Ok(Some((bytes::Bytes::from(buf), (file, left - want as u64))))
        });
        Ok(Some(BlobReader {
            len,
            chunks: Box::pin(chunks),
        }))
    }

    /// The file's inode, modification time (ns) and length: a put renames a new file into
    /// place, so a rewrite has a new inode (the old one is in use until the rename) and a new
    /// time; no read of the content.
    async fn version(&self, key: BlobKey) -> Result<Option<String>, JobError> {
        let path = self.path(&key)?;
        let meta = match tokio::fs::metadata(&path).await {
            Ok(m) => m,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e.into()),
        };
        let modified = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos());
        #[cfg(unix)]
        let inode = std::os::unix::fs::MetadataExt::ino(&meta);
        #[cfg(not(unix))]
        let inode = 0u64;
        Ok(Some(format!("{inode:x}-{modified:x}-{:x}", meta.len())))
    }

    async fn delete(&self, key: BlobKey) -> Result<(), JobError> {
        let path = self.path(&key)?;
        tokio::task::spawn_blocking(move || match fs::remove_file(&path) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e.into()),
        })
        .await
        .map_err(join_err)?
    }

    async fn delete_job(&self, id: &str) -> Result<(), JobError> {
        let dir = self.job_dir(id)?;
        tokio::task::spawn_blocking(move || match fs::remove_dir_all(&dir) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e.into()),
        })
        .await
        .map_err(join_err)?
    }
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
