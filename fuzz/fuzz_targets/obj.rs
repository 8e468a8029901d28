//! The OBJ reader (`Asset::read` with `Format::Obj`: parse, weld, validate), and on success
//! the writers: OBJ (the kept-text path) and GLB (the new-document path).
#![no_main]
willow_fuzz::capped_allocator!();

use libfuzzer_sys::fuzz_target;
use willow::mesh::io::{Asset, Format, Limits};

fuzz_target!(|data: &[u8]| {
    let Ok(asset) = Asset::read(data, Format::Obj, &Limits::default()) else {
        return;
    };
    let positions = asset.surface().positions.clone();
    // Writing back what was read must succeed: the positions are the asset's own.
    let obj = asset.write(&positions, Format::Obj);
    assert!(obj.is_ok(), "writing OBJ back failed: {obj:?}");
    let glb = asset.write(&positions, Format::Glb);
    assert!(glb.is_ok(), "writing GLB failed: {glb:?}");
});
