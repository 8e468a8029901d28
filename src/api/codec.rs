//! The protobuf codec of the generated gRPC services (`build.rs` names it with
//! `codec_path`): tonic-prost's own, except that a request that does not decode is
//! INVALID_ARGUMENT, not INTERNAL.
//!
//! tonic-prost maps every `prost::DecodeError` (truncated or malformed bytes, a string field
//! holding invalid UTF-8) to INTERNAL, which tells the client the server broke and invites a
//! retry of the same bad bytes. The message is the client's fault, so it gets the client-error
//! code, with the field prost names as a `BadRequest` violation. Generated clients use the same
//! codec: a response that does not decode is then reported as INVALID_ARGUMENT too, which only
//! our own tests and Rust callers see.

use super::problem::cap_detail;
use prost::Message;
use tonic::codec::{BufferSettings, Codec, DecodeBuf, Decoder};
use tonic::{Code, Status};
use tonic_prost::ProstCodec;
use tonic_types::{ErrorDetails, StatusExt};

/// [`ProstCodec`] with decode errors mapped to INVALID_ARGUMENT.
#[derive(Debug, Clone)]
pub struct ProtoCodec<T, U>(ProstCodec<T, U>);

impl<T, U> Default for ProtoCodec<T, U> {
    fn default() -> Self {
        ProtoCodec(ProstCodec::default())
    }
}

impl<T, U> Codec for ProtoCodec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = <ProstCodec<T, U> as Codec>::Encoder;
    type Decoder = ClientFaultDecoder<<ProstCodec<T, U> as Codec>::Decoder>;

    fn encoder(&mut self) -> Self::Encoder {
        self.0.encoder()
    }

    fn decoder(&mut self) -> Self::Decoder {
        ClientFaultDecoder(self.0.decoder())
    }
}

/// A decoder whose INTERNAL errors (tonic-prost's only use of it is a `DecodeError`) become
/// INVALID_ARGUMENT.
#[derive(Debug)]
pub struct ClientFaultDecoder<D>(D);

impl<D: Decoder<Error = Status>> Decoder for ClientFaultDecoder<D> {
    type Item = D::Item;
    type Error = Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Self::Item>, Status> {
        self.0.decode(src).map_err(|e| {
            if e.code() == Code::Internal {
                malformed(e.message())
            } else {
                e
            }
        })
    }

    fn buffer_settings(&self) -> BufferSettings {
        self.0.buffer_settings()
    }
}

/// INVALID_ARGUMENT for prost's message, which reads `failed to decode Protobuf message:
/// CreateJobRequest.params: JobParams.method: invalid varint`: the `Type.field` segments give
/// the field path (`params.method`) for the `BadRequest` violation.
pub(crate) fn malformed(message: &str) -> Status {
    let reason = cap_detail(message.to_string());
    let field: Vec<&str> = message
        .split(": ")
        .filter_map(|seg| {
            let (ty, field) = seg.split_once('.')?;
            let ident =
                |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
            (ident(ty) && ident(field)).then_some(field)
        })
        .collect();
    let field = field.join(".");
    Status::with_error_details(
        Code::InvalidArgument,
        format!("the request is not a valid protobuf message: {reason}"),
        ErrorDetails::with_bad_request_violation(field, reason),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_path_comes_from_prosts_message() {
        let s = malformed(
            "failed to decode Protobuf message: CreateJobRequest.params: JobParams.method: \
             invalid varint",
        );
        assert_eq!(s.code(), Code::InvalidArgument);
        let fields: Vec<String> = s
            .get_details_bad_request()
            .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
            .unwrap_or_default();
        assert_eq!(fields, vec!["params.method".to_string()]);
    }
}
