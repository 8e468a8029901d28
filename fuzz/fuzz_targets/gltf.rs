//! The glTF/GLB reader (`Asset::read` with `Format::Gltf`; the reader tells JSON from GLB by
//! the magic bytes, so one target covers both containers), and on success the document
//! writer (glTF and GLB) and the OBJ writer.
#![no_main]
willow_fuzz::capped_allocator!();

use libfuzzer_sys::fuzz_target;
use willow::mesh::io::{Asset, Format, Limits};

fuzz_target!(|data: &[u8]| {
    let Ok(asset) = Asset::read(data, Format::Gltf, &Limits::default()) else {
        return;
    };
    let positions = asset.surface().positions.clone();
    for format in [Format::Glb, Format::Gltf, Format::Obj] {
        let out = asset.write(&positions, format);
        assert!(out.is_ok(), "writing {format:?} back failed: {out:?}");
    }
});
