use super::*;
use crate::mesh::io::{Format, MeshError};

#[test]
fn glb_header_lies_are_errors_not_panics() {
    // Length smaller than the header (the gltf crate underflows on this one).
    let mut b = b"glTF".to_vec();
    b.extend_from_slice(&2u32.to_le_bytes());
    b.extend_from_slice(&4u32.to_le_bytes());
    assert!(split_container(&b, Format::Glb).is_err());
    // A chunk claiming more bytes than there are.
    let mut b = b"glTF".to_vec();
    b.extend_from_slice(&2u32.to_le_bytes());
    b.extend_from_slice(&28u32.to_le_bytes());
    b.extend_from_slice(&u32::MAX.to_le_bytes());
    b.extend_from_slice(b"JSON");
    b.extend_from_slice(b"{}  ");
    let e = split_container(&b, Format::Glb).unwrap_err();
    assert_eq!(e.code(), "truncated_buffer");
    assert!(split_container(b"glTF", Format::Glb).is_err());
}

#[test]
fn only_base64_data_uris_are_decoded() {
    assert_eq!(
        decode_data_uri("data:application/octet-stream;base64,AAEC").unwrap(),
        [0, 1, 2]
    );
    for uri in [
        "/etc/passwd",
        "http://example.com/a.bin",
        "file:///etc/passwd",
        "a.bin",
    ] {
        assert!(
            matches!(decode_data_uri(uri), Err(MeshError::ExternalUri { .. })),
            "{uri}"
        );
    }
}
