//! Entry points for the fuzz targets in `fuzz/` (not an API: hidden from the docs, may change
//! at any time). They run the same code the handlers run, minus the network and the job core.

use super::convert::{format_from_pb, request_id, spec_from_pb};
use super::errors::job_error;
use super::pb::willow::v1;
use super::upload::UploadAssembly;
use crate::api::codec;
use crate::jobs::{Config, JobSpec};
use tonic::Status;
use willow::mesh::io::Format;

/// An `UploadMesh` stream whose messages arrive as the protobuf encodings in `messages`,
/// decoded as the server's codec decodes them and assembled under an upload limit of
/// `limit` bytes: the assembled file's size and format, or the status the client gets.
pub fn upload_mesh(messages: &[&[u8]], limit: u64) -> Result<(usize, Format), Status> {
    let mut decoded = messages.iter().map(|m| decode::<v1::UploadMeshChunk>(m));
    let first = decoded.next().transpose()?;
    let mut upload = UploadAssembly::start(first, limit)?;
    for chunk in decoded {
        upload.push(chunk?)?;
    }
    let (data, format) = upload.finish()?;
    Ok((data.len(), format))
}

/// A `CreateJob` request's protobuf encoding, decoded as the server's codec decodes it,
/// its parameters translated to a [`JobSpec`] and validated as `submit` validates them
/// (default server configuration).
pub fn create_job(bytes: &[u8]) -> Result<JobSpec, Status> {
    let request = decode::<v1::CreateJobRequest>(bytes)?;
    request_id(&request.request_id)?;
    if let Some(v1::create_job_request::Mesh::InlineMesh(mesh)) = &request.mesh {
        format_from_pb("inline_mesh.format", mesh.format)?;
    }
    let spec = spec_from_pb(request.params)?;
    spec.validate(default_config())
        .map_err(|e| job_error(e, "inline_mesh.data"))?;
    Ok(spec)
}

/// The default server configuration (built once: it asks the OS for the core count).
pub(crate) fn default_config() -> &'static Config {
    static CONFIG: std::sync::OnceLock<Config> = std::sync::OnceLock::new();
    CONFIG.get_or_init(|| Config::new("willow-data"))
}

/// prost's decode, its error mapped as the codec maps it.
fn decode<M: prost::Message + Default>(bytes: &[u8]) -> Result<M, Status> {
    M::decode(bytes)
        .map_err(|e| codec::malformed(&format!("failed to decode Protobuf message: {e}")))
}
