//! File I/O: round trips keep UVs, faces, indices and images; seams never open; transforms
//! are applied for the surface and undone for the file; output passes the Khronos validator.
//!
//! One file a theme: `obj`, `gltf_io` (GLB/glTF round trips, tangents, quantized input),
//! `layouts` (several primitives, buffers, interleaving, strips), `formats` (every format in
//! and out). The shared readers and the glTF inspection helpers live here.

#[path = "../mesh_support/mod.rs"]
mod mesh_support;

mod formats;
mod gltf_io;
mod layouts;
mod obj;

use mesh_support::*;
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::Topology;

const TETRA: &str = include_str!("../data/tetra_seams.obj");

fn read(bytes: &[u8], format: Format) -> Asset {
    Asset::read(bytes, format, &Limits::default()).unwrap()
}

/// Per corner of each file triangle: the UV, in surface face order.
fn corner_uvs(a: &Asset) -> Vec<[[f32; 2]; 3]> {
    a.corner_uvs().expect("file has UVs")
}

/// Moves every welded vertex differently (so a seam that opened would show).
fn wobble(p: &[[f64; 3]]) -> Vec<[f64; 3]> {
    p.iter()
        .enumerate()
        .map(|(i, q)| {
            let s = 1.0 + 0.01 * (i % 7) as f64;
            [q[0] * s + 0.25, q[1] * s - 0.5, q[2] * s + 0.125]
        })
        .collect()
}

/// Every split copy of a welded vertex carries exactly the welded vertex's new position.
fn assert_seams_closed(a: &Asset, moved: &[[f64; 3]]) {
    let file = a.file_positions(moved);
    assert_eq!(file.len(), a.file_vertex_count());
    let map = a.file_to_welded();
    let mut first: Vec<Option<[f32; 3]>> = vec![None; moved.len()];
    for (fv, w) in map.iter().enumerate() {
        if let Some(w) = *w {
            match first[w] {
                None => first[w] = Some(file[fv]),
                Some(p) => assert_eq!(p, file[fv], "split copies of vertex {w} differ"),
            }
        }
    }
}

// ---------------------------------------------------------------------------------------
// glTF inspection helpers (for well-formed outputs only)

struct Glb {
    doc: gltf::Document,
    blob: Vec<u8>,
}

fn open_glb(bytes: &[u8]) -> Glb {
    let g = gltf::Gltf::from_slice(bytes).unwrap();
    Glb {
        doc: g.document,
        blob: g.blob.unwrap(),
    }
}

impl Glb {
    fn image_bytes(&self) -> Vec<Vec<u8>> {
        self.doc
            .images()
            .map(|im| match im.source() {
                gltf::image::Source::View { view, .. } => {
                    self.blob[view.offset()..view.offset() + view.length()].to_vec()
                }
                gltf::image::Source::Uri { uri, .. } => uri.as_bytes().to_vec(),
            })
            .collect()
    }

    /// (indices, uv0, positions, normals) of every primitive, in order.
    #[allow(clippy::type_complexity)]
    fn primitives(&self) -> Vec<(Vec<u32>, Vec<[f32; 2]>, Vec<[f32; 3]>, Vec<[f32; 3]>)> {
        let blob = &self.blob;
        self.doc
            .meshes()
            .flat_map(|m| m.primitives())
            .map(|p| {
                let r = p.reader(|_| Some(&blob[..]));
                (
                    r.read_indices()
                        .map(|i| i.into_u32().collect())
                        .unwrap_or_default(),
                    r.read_tex_coords(0)
                        .map(|t| t.into_f32().collect())
                        .unwrap_or_default(),
                    r.read_positions().map(|p| p.collect()).unwrap_or_default(),
                    r.read_normals().map(|n| n.collect()).unwrap_or_default(),
                )
            })
            .collect()
    }
}
