//! UploadMesh: the chunks of the client stream assembled into one file, without the stream, so
//! the logic is testable and fuzzable on its own (`fuzzing::upload_mesh`).

use tonic::Status;

use super::convert::format_from_pb;
use super::errors::{bad_request, job_error};
use super::pb::willow::v1;
use crate::jobs::JobError;
use willow::mesh::io::Format;

/// An `UploadMesh` stream being assembled: the header's format and announced size, the bytes
/// so far, and the server's upload limit.
pub(super) struct UploadAssembly {
    format: Format,
    announced: u64,
    limit: u64,
    data: Vec<u8>,
}

impl UploadAssembly {
    /// Starts from the stream's first message (`None`: the stream was empty), which must carry
    /// the header.
    pub(super) fn start(
        first: Option<v1::UploadMeshChunk>,
        limit: u64,
    ) -> Result<UploadAssembly, Status> {
        use v1::upload_mesh_chunk::Part;
        let header = match first {
            Some(v1::UploadMeshChunk {
                part: Some(Part::Header(h)),
            }) => h,
            Some(_) => {
                return Err(bad_request(
                    "header",
                    "the first message of the stream must carry `header`",
                ))
            }
            None => return Err(bad_request("header", "the upload stream was empty")),
        };
        let format = format_from_pb("header.format", header.format)?;
        if header.size_bytes > limit {
            return Err(job_error(
                JobError::TooLarge {
                    what: "upload bytes",
                    limit,
                },
                "header.size_bytes",
            ));
        }
        // Reserve what the client announced (already checked against the limit), fallibly:
        // a client lying about its size must get an error, not abort the server.
        let mut data: Vec<u8> = Vec::new();
        let announced = usize::try_from(header.size_bytes).unwrap_or(usize::MAX);
        data.try_reserve(announced)
            .map_err(|_| Status::resource_exhausted("not enough memory for the upload"))?;
        Ok(UploadAssembly {
            format,
            announced: header.size_bytes,
            limit,
            data,
        })
    }

    /// Appends one later message of the stream.
    pub(super) fn push(&mut self, chunk: v1::UploadMeshChunk) -> Result<(), Status> {
        use v1::upload_mesh_chunk::Part;
        match chunk.part {
            Some(Part::Data(bytes)) => {
                if (self.data.len() as u64).saturating_add(bytes.len() as u64) > self.limit {
                    return Err(job_error(
                        JobError::TooLarge {
                            what: "upload bytes",
                            limit: self.limit,
                        },
                        "data",
                    ));
                }
                self.data
                    .try_reserve(bytes.len())
                    .map_err(|_| Status::resource_exhausted("not enough memory for the upload"))?;
                self.data.extend_from_slice(&bytes);
                Ok(())
            }
            Some(Part::Header(_)) => Err(bad_request(
                "header",
                "only the first message of the stream may carry `header`",
            )),
            // An empty message carries nothing; tolerate it like an empty chunk.
            None => Ok(()),
        }
    }

    /// The whole file, once the stream has ended: its size must be the announced one (when
    /// one was announced).
    pub(super) fn finish(self) -> Result<(Vec<u8>, Format), Status> {
        if self.announced != 0 && self.data.len() as u64 != self.announced {
            return Err(bad_request(
                "header.size_bytes",
                format!(
                    "announced {} bytes but the stream carried {}",
                    self.announced,
                    self.data.len()
                ),
            ));
        }
        Ok((self.data, self.format))
    }
}
