//! The opt-in `repair` ([`Asset::read_repaired`](super::Asset::read_repaired)): drops
//! degenerate faces and splits non-manifold vertices and edges, and says what it changed.
//!
//! Splitting is welding by corners without joining a file vertex's own corners
//! (`weld::by_corners`): each surface vertex is then one fan of triangles, so a bowtie vertex
//! becomes one vertex per fan and an edge with three or more faces is cut into separate
//! boundary edges. A split file vertex gets extra split vertices (copies with its UV and
//! normal), so the surface and new-format outputs keep the split; files written back in their
//! own format keep their own vertex sharing (a `v` line, a PLY record, a glTF index), and give
//! the shared vertex the position of its first fan.

use super::weld::Weld;
use super::{Block, FileGeometry};
use crate::mesh::error::Offenders;
use std::collections::{HashMap, HashSet};
use std::fmt;

/// What [`Asset::read_repaired`](super::Asset::read_repaired) changed, in file numbering
/// (see [`Asset::file_vertex_count`](super::Asset::file_vertex_count)).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Repairs {
    /// Faces dropped as degenerate (two corners at one position, or exactly zero area).
    pub dropped_faces: Offenders<usize>,
    /// File vertices split because their faces formed several fans (a bowtie, or the ends of
    /// an edge with three or more faces).
    pub split_vertices: Offenders<usize>,
    /// Surface vertices the splits added.
    pub added_vertices: usize,
}

impl Repairs {
    /// True when nothing was changed.
    pub fn is_empty(&self) -> bool {
        self.dropped_faces.is_empty() && self.split_vertices.is_empty()
    }
}

impl fmt::Display for Repairs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.is_empty() {
            return write!(f, "nothing to repair");
        }
        let mut parts = Vec::new();
        if !self.dropped_faces.is_empty() {
            parts.push(format!(
                "dropped {} degenerate faces (first: {})",
                self.dropped_faces.count, self.dropped_faces
            ));
        }
        if !self.split_vertices.is_empty() {
            parts.push(format!(
                "split {} non-manifold vertices into {} more (first: {})",
                self.split_vertices.count, self.added_vertices, self.split_vertices
            ));
        }
        write!(f, "{}", parts.join("; "))
    }
}

fn key(p: [f64; 3]) -> [u64; 3] {
    p.map(|x| (x + 0.0).to_bits())
}

/// Drops the triangles with two corners at one position or exactly zero area (the
/// validator's rule), recording their file faces; keeps `face_of_triangle` pointing at the
/// file's faces.
pub(crate) fn drop_degenerate(file: &mut FileGeometry, world: &[[f64; 3]], repairs: &mut Repairs) {
    let at = |sv: usize| world.get(sv).copied().unwrap_or([0.0; 3]);
    let degenerate = |t: &[usize; 3]| {
        let [a, b, c] = t.map(at);
        let (ka, kb, kc) = (key(a), key(b), key(c));
        ka == kb || kb == kc || kc == ka || {
            let n = super::cross(super::sub(b, a), super::sub(c, a));
            n == [0.0; 3]
        }
    };
    if !file.triangles.iter().any(degenerate) {
        return;
    }
    let face = |t: usize| -> usize {
        file.face_of_triangle
            .as_ref()
            .and_then(|f| f.get(t))
            .map_or(t, |&f| f as usize)
    };
    let mut triangles = Vec::with_capacity(file.triangles.len());
    let mut faces = Vec::with_capacity(file.triangles.len());
    let mut dropped_faces = HashSet::new();
    for (t, tri) in file.triangles.iter().enumerate() {
        if degenerate(tri) {
            // A polygon fanned into several triangles counts once.
            if dropped_faces.insert(face(t)) {
                repairs.dropped_faces.push(face(t));
            }
        } else {
            triangles.push(*tri);
            faces.push(face(t) as u32);
        }
    }
    file.triangles = triangles;
    file.face_of_triangle = Some(faces);
}

/// Gives each split vertex whose corners `w` put in several surface vertices one copy per
/// extra surface vertex, repoints those corners at the copies, and records the split file
/// vertices.
pub(crate) fn split_copies(
    file: &mut FileGeometry,
    w: &mut Weld,
    file_of_split: &dyn Fn(usize) -> usize,
    repairs: &mut Repairs,
) {
    let mut classes_of_file: HashMap<usize, HashSet<usize>> = HashMap::new();
    let mut copies: HashMap<(usize, usize), usize> = HashMap::new();
    for (t, st) in w.triangles.iter().enumerate() {
        for (k, &class) in st.iter().enumerate() {
            let Some(&sv) = file.triangles.get(t).and_then(|tri| tri.get(k)) else {
                continue;
            };
            classes_of_file
                .entry(file_of_split(sv))
                .or_default()
                .insert(class);
            if w.to_welded.get(sv) == Some(&class) {
                continue;
            }
            let id = *copies.entry((sv, class)).or_insert_with(|| {
                let id = file.local.len();
                let p = file.local.get(sv).copied().unwrap_or([0.0; 3]);
                file.local.push(p);
                if let Some(uvs) = &mut file.uvs {
                    let uv = uvs.get(sv).copied().flatten();
                    uvs.push(uv);
                }
                if let Some(keys) = &mut file.normal_keys {
                    let key = keys.get(sv).copied().unwrap_or(u64::MAX);
                    keys.push(key);
                }
                let block = file
                    .blocks
                    .iter()
                    .find(|b| (b.start..b.start + b.len).contains(&sv))
                    .cloned();
                if let Some(b) = block {
                    file.blocks.push(Block {
                        start: id,
                        len: 1,
                        ..b
                    });
                }
                file.copies.push(sv);
                w.to_welded.push(class);
                id
            });
            if let Some(slot) = file.triangles.get_mut(t).and_then(|tri| tri.get_mut(k)) {
                *slot = id;
            }
        }
    }
    let mut split: Vec<(usize, usize)> = classes_of_file
        .into_iter()
        .filter(|(_, c)| c.len() > 1)
        .map(|(f, c)| (f, c.len()))
        .collect();
    split.sort_unstable();
    for (f, n) in split {
        repairs.split_vertices.push(f);
        repairs.added_vertices += n - 1;
    }
}
