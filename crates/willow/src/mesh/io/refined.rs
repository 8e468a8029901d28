//! [`Asset::refined`]: the asset Loop-subdivided ([`crate::mesh::refine`]) before the flow,
//! with the file's UVs, normals and numbering carried over (issue 26, item 5).
//!
//! Three numberings are split at once, level by level, with the same 1-to-4 rule
//! ([`midpoint_split`]): the welded surface (positions by Loop's rules), the split vertices
//! (one per UV/normal corner) and the file's vertices. Child `4t + i` of triangle `t` is the
//! same child in all three, corner by corner, so each new split vertex learns its welded and
//! its file vertex from the children's corners. Edges are keyed by vertex pair, so a UV seam
//! (two split vertices at one welded vertex) stays split at its new midpoints.
//!
//! - **UVs** are interpolated linearly (the new corner's UV is its edge's midpoint in UV space,
//!   old corners keep theirs: OpenSubdiv's "linear face-varying" rule), so texture
//!   coordinates never leave the charts the artist drew.
//! - **Numbering**: the file's own vertices keep their numbers (a region or a frame position
//!   `k` still means the `k`-th `v` line / accessor vertex), and the new vertices are appended
//!   after them, one per edge between two file vertices (for OBJ one per `v` pair, shared
//!   across a UV seam as a `v` line is; for glTF one per accessor-vertex pair).
//! - **Other attributes** (glTF TEXCOORD_n, COLOR_n) are interpolated the same way; what
//!   cannot be (JOINTS/WEIGHTS and skins, custom attributes) is dropped with a note, and
//!   TANGENT is dropped as on every written glTF (viewers recompute it).
//! - **Writing** the input's own format keeps the input's file: a glTF its whole document
//!   (materials, textures, images, samplers, nodes and names), with each primitive's
//!   accessors rewritten (`gltf::refined`); an OBJ its statements (`g`, `o`, `usemtl`,
//!   `mtllib`, `s`, comments), each face replaced by its children (`obj::write_refined`).
//!   Other formats are written new.

use super::{Asset, Block, FileGeometry, Source, UNWELDED};
use crate::mesh::refine::{check_level, check_plan, check_vertices, loop_positions};
use crate::mesh::refine::{midpoint_split, planned_levels};
use crate::mesh::{Limits, Mesh, MeshError};

/// The file side of a refined asset: split vertex → file vertex, and each file vertex's
/// stored position (local space), for those no triangle uses; and what writing the input's
/// own format needs: the input's source, and how its triangles and blocks were split.
#[derive(Clone)]
pub(crate) struct RefinedSource {
    pub(crate) v_of_split: Vec<usize>,
    pub(crate) stored: Vec<[f64; 3]>,
    /// The input's source (its document or text), kept so a refined glTF keeps its
    /// materials, textures and nodes, and a refined OBJ its groups and materials.
    pub(crate) original: Box<Source>,
    /// 1-to-4 levels: triangle `c` descends from the input's triangle `c >> 2·levels`.
    pub(crate) levels: usize,
    /// Blocks of the input: block `i`'s new split vertices are block `old_blocks + i`.
    pub(crate) old_blocks: usize,
    /// Split vertices of the input (they keep their numbers; the new ones follow).
    pub(crate) old_split: usize,
    /// Per triangle of the input: the oriented surface reversed the file's winding (children
    /// are written back in the file's winding, as an unrefined file keeps its faces).
    pub(crate) flipped: Vec<bool>,
    /// Per-vertex attributes interpolated like the UVs (glTF TEXCOORD_n, COLOR_n).
    pub(crate) varyings: Vec<Varying>,
    /// Per file vertex its OBJ `v` line colour, interpolated along the file's edges like the
    /// UVs (`None` for a vertex, or the file, without one).
    pub(crate) v_colours: Option<Vec<Option<[f64; 3]>>>,
    /// The input's notes and what refining could not carry (`gltf::refined::dropped`).
    pub(crate) notes: Vec<String>,
    /// Triangles the subdivision made; those after them are hole patches
    /// ([`Asset::with_patches`]), each written after the input's faces.
    pub(crate) base_triangles: usize,
    /// Per patch triangle: the input triangle beside its hole, whose winding it is written in.
    pub(crate) patch_roots: Vec<usize>,
    /// Per patch triangle: the input block (glTF primitive's POSITION accessor) it joins.
    pub(crate) patch_blocks: Vec<usize>,
}

/// A per-vertex attribute interpolated linearly like the UVs: `width` numbers per split
/// vertex (zeros outside `block`, the input block whose accessor it is).
#[derive(Clone, Debug)]
pub(crate) struct Varying {
    pub(crate) accessor: usize,
    pub(crate) block: usize,
    pub(crate) width: usize,
    pub(crate) values: Vec<f64>,
}

impl RefinedSource {
    /// The input triangle `c` (a refined triangle) descends from.
    pub(crate) fn root(&self, c: usize) -> usize {
        match c.checked_sub(self.base_triangles) {
            Some(k) => self.patch_roots.get(k).copied().unwrap_or(0),
            None => c >> (2 * self.levels),
        }
    }
}

/// What [`Asset::refined`] did: the number of 1-to-4 levels (0: the mesh was already fine).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Refinement {
    pub levels: usize,
    pub vertices_before: usize,
    pub faces_before: usize,
}

impl Asset {
    /// The asset Loop-subdivided [`planned_levels`] times: until the surface's mean edge
    /// length is about `target`, or by default to 16k–64k triangles, with UVs, normals and the
    /// file's numbering carried over (module docs). With no level needed, the asset itself.
    ///
    /// The plan is checked against `limits` and [`MAX_REFINED_FACES`](crate::mesh::refine::MAX_REFINED_FACES)
    /// before any level is built; past them, a [`MeshError::TooLarge`] naming `refine`.
    pub fn refined(
        &self,
        target: Option<f64>,
        limits: &Limits,
    ) -> Result<(Asset, Refinement), MeshError> {
        let planned = planned_levels(&self.surface, target)?;
        check_plan(self.surface.face_count(), planned, limits)?;
        let before = Refinement {
            levels: 0,
            vertices_before: self.file_vertex_count(),
            faces_before: self.surface.face_count(),
        };
        if planned == 0 {
            return Ok((self.clone(), before));
        }
        let asset = self.subdivided(planned, limits)?;
        Ok((
            asset,
            Refinement {
                levels: planned,
                ..before
            },
        ))
    }

    /// The asset split `planned` times (0: the same surface, with a refined asset's
    /// bookkeeping, which is what [`Asset::with_patches`] appends to).
    pub(crate) fn subdivided(&self, planned: usize, limits: &Limits) -> Result<Asset, MeshError> {
        let before = Refinement {
            levels: 0,
            vertices_before: self.file_vertex_count(),
            faces_before: self.surface.face_count(),
        };
        let mut welded = self.surface.clone();
        let mut split_tris = self.oriented_split_triangles();
        let mut to_welded = self.to_welded.clone();
        let file_of = |sv: usize| self.source.file_vertex_of_split(self.file.original(sv));
        let mut v_of_split: Vec<usize> = (0..to_welded.len()).map(file_of).collect();
        let mut v_count = self.file_vertex_count();
        let mut uvs = self.file.uvs.clone();
        let mut keys = self.file.normal_keys.clone();
        let mut block_of: Vec<usize> = vec![0; to_welded.len()];
        for (i, b) in self.file.blocks.iter().enumerate() {
            for slot in block_of.iter_mut().skip(b.start).take(b.len) {
                *slot = i;
            }
        }
        let mut varyings = self.varyings();
        let mut v_colours = match &self.source {
            Source::Obj(src) => src.v_colours(),
            _ => None,
        };
        let mut levels = 0;
        while levels < planned {
            check_level(welded.face_count(), limits)?;
            let w = midpoint_split(&welded.triangles, welded.vertex_count());
            check_vertices(welded.vertex_count() + w.edges.len(), limits)?;
            let s = midpoint_split(&split_tris, to_welded.len());
            check_vertices(to_welded.len() + s.edges.len(), limits)?;
            let file_tris: Vec<[usize; 3]> = split_tris
                .iter()
                .map(|t| t.map(|sv| v_of_split[sv]))
                .collect();
            let f = midpoint_split(&file_tris, v_count);
            if let Some(colours) = v_colours.as_mut() {
                colours.resize(v_count, None);
                for &[a, b] in &f.edges {
                    let mid = match (colours[a], colours[b]) {
                        (Some(p), Some(q)) => Some([0, 1, 2].map(|k| 0.5 * (p[k] + q[k]))),
                        _ => None,
                    };
                    colours.push(mid);
                }
            }
            // New split vertices learn their welded and file vertices from the children's
            // corners (child 4t + i is the same child in all three numberings).
            let n_split = to_welded.len();
            to_welded.resize(n_split + s.edges.len(), UNWELDED);
            v_of_split.resize(n_split + s.edges.len(), 0);
            for ((st, wt), ft) in s.triangles.iter().zip(&w.triangles).zip(&f.triangles) {
                for k in 0..3 {
                    if st[k] >= n_split {
                        to_welded[st[k]] = wt[k];
                        v_of_split[st[k]] = ft[k];
                    }
                }
            }
            for v in &mut varyings {
                for &[a, b] in &s.edges {
                    for k in 0..v.width {
                        let mid = 0.5 * (v.values[a * v.width + k] + v.values[b * v.width + k]);
                        v.values.push(mid);
                    }
                }
            }
            for &[a, b] in &s.edges {
                block_of.push(block_of[a]);
                if let Some(uvs) = uvs.as_mut() {
                    let uv = match (uvs[a], uvs[b]) {
                        (Some(p), Some(q)) => Some([0.5 * (p[0] + q[0]), 0.5 * (p[1] + q[1])]),
                        _ => None,
                    };
                    uvs.push(uv);
                }
                if let Some(keys) = keys.as_mut() {
                    // Symmetric in the edge's welded ends, so both sides of a UV seam with one
                    // stored normal stay one normal group (smooth), and a crease stays one.
                    let (ka, kb) = if to_welded[a] <= to_welded[b] {
                        (keys[a], keys[b])
                    } else {
                        (keys[b], keys[a])
                    };
                    keys.push(ka.wrapping_mul(0x9E37_79B9_7F4A_7C15).rotate_left(17) ^ kb);
                }
            }
            v_count += f.edges.len();
            welded = Mesh {
                positions: loop_positions(&welded.positions, &w),
                triangles: w.triangles,
            };
            split_tris = s.triangles;
            levels += 1;
        }
        let parent_face = |c: usize| {
            let t = c >> (2 * levels);
            match &self.file.face_of_triangle {
                Some(faces) => faces.get(t).copied().unwrap_or(t as u32),
                None => t as u32,
            }
        };
        let face_of_triangle = (0..split_tris.len()).map(parent_face).collect();

        // Blocks must be contiguous: new split vertices are renumbered by block (stable), after
        // every old one.
        let n_old = self.file.local.len();
        let mut order: Vec<usize> = (n_old..to_welded.len()).collect();
        order.sort_by_key(|&sv| block_of[sv]);
        let mut renumber: Vec<usize> = (0..to_welded.len()).collect();
        for (i, &sv) in order.iter().enumerate() {
            renumber[sv] = n_old + i;
        }
        let permute = |v: &[usize]| -> Vec<usize> {
            let mut out = v.to_vec();
            for (i, &sv) in order.iter().enumerate() {
                out[n_old + i] = v[sv];
            }
            out
        };
        let to_welded = permute(&to_welded);
        let v_of_split = permute(&v_of_split);
        let uvs = uvs.map(|u| {
            let mut out = u.clone();
            for (i, &sv) in order.iter().enumerate() {
                out[n_old + i] = u[sv];
            }
            out
        });
        let normal_keys = keys.map(|k| {
            let mut out = k.clone();
            for (i, &sv) in order.iter().enumerate() {
                out[n_old + i] = k[sv];
            }
            out
        });
        for v in &mut varyings {
            let w = v.width;
            let mut out = v.values.clone();
            for (i, &sv) in order.iter().enumerate() {
                out[(n_old + i) * w..(n_old + i + 1) * w]
                    .copy_from_slice(&v.values[sv * w..(sv + 1) * w]);
            }
            v.values = out;
        }
        let split_tris_len = split_tris.len();
        let triangles: Vec<[usize; 3]> = split_tris
            .iter()
            .map(|t| t.map(|sv| renumber[sv]))
            .collect();
        let mut blocks = self.file.blocks.clone();
        let mut local = self.file.local.clone();
        let mut start = n_old;
        for (i, b) in self.file.blocks.iter().enumerate() {
            let len = order.iter().filter(|&&sv| block_of[sv] == i).count();
            blocks.push(Block {
                start,
                len,
                to_world: b.to_world,
                to_local: b.to_local,
            });
            start += len;
        }
        local.resize(to_welded.len(), [0.0; 3]);
        for b in &blocks {
            for sv in b.start..b.start + b.len {
                if let Some(p) = to_welded.get(sv).and_then(|&w| welded.positions.get(w)) {
                    local[sv] = b.to_local.apply(*p);
                }
            }
        }
        let mut stored = self.file_positions_f64(&self.surface.positions);
        stored.resize(v_count, [0.0; 3]);
        for (sv, &v) in v_of_split.iter().enumerate() {
            if v >= before.vertices_before {
                stored[v] = local[sv];
            }
        }
        let surface = Mesh::with_limits(welded.positions, welded.triangles, limits)?;
        let file = FileGeometry {
            local,
            blocks,
            triangles,
            uvs,
            normal_keys,
            face_of_triangle: Some(face_of_triangle),
            copies: Vec::new(),
        };
        let normal_groups = file
            .normal_keys
            .as_ref()
            .map(|keys| super::normal_groups_of(&to_welded, keys));
        let asset = Asset {
            format: self.format,
            surface,
            file,
            to_welded,
            normal_groups,
            source: Source::Refined(RefinedSource {
                v_of_split,
                stored,
                original: Box::new(self.source.clone()),
                levels,
                old_blocks: self.file.blocks.len(),
                old_split: n_old,
                flipped: self
                    .file
                    .triangles
                    .iter()
                    .zip(self.oriented_split_triangles())
                    .map(|(f, o)| *f != o)
                    .collect(),
                varyings,
                v_colours,
                notes: self.refined_notes(),
                base_triangles: split_tris_len,
                patch_roots: Vec::new(),
                patch_blocks: Vec::new(),
            }),
            repairs: self.repairs.clone(),
        };
        Ok(asset)
    }
}

impl Asset {
    /// The glTF attributes interpolated like the UVs (TEXCOORD_n, COLOR_n), per split vertex.
    fn varyings(&self) -> Vec<Varying> {
        let Source::Gltf(src) = &self.source else {
            return Vec::new();
        };
        let n = self.to_welded.len();
        src.varyings
            .iter()
            .filter_map(|v| {
                let b = self.file.blocks.get(v.block)?;
                let mut values = vec![0.0; n * v.width];
                for sv in 0..n {
                    let k = self.file.original(sv);
                    if (b.start..b.start + b.len).contains(&k) {
                        let from = (k - b.start) * v.width;
                        let slot = &mut values[sv * v.width..(sv + 1) * v.width];
                        slot.copy_from_slice(v.values.get(from..from + v.width)?);
                    }
                }
                Some(Varying {
                    accessor: v.accessor,
                    block: v.block,
                    width: v.width,
                    values,
                })
            })
            .collect()
    }

    /// The notes of a refined asset: the input's, and what refining drops.
    fn refined_notes(&self) -> Vec<String> {
        let mut notes = self.notes();
        if let Source::Gltf(src) = &self.source {
            notes.extend(super::gltf::refined::dropped(src));
        }
        notes
    }

    /// For a refined asset, the vertices a format with shared vertices (OBJ, OFF) writes: the
    /// file's, in its numbering then the new ones (module docs), in world space (unused ones
    /// at their stored position), and each split vertex's index among them. `None` for any
    /// other asset, which writes its welded vertices.
    pub(crate) fn refined_vertices(
        &self,
        positions: &[[f64; 3]],
    ) -> Option<(Vec<[f64; 3]>, &[usize])> {
        let Source::Refined(src) = &self.source else {
            return None;
        };
        let mut out = src.stored.clone();
        for (&v, &w) in src.v_of_split.iter().zip(&self.to_welded) {
            if let (Some(slot), Some(p)) = (out.get_mut(v), positions.get(w)) {
                *slot = *p;
            }
        }
        Some((out, &src.v_of_split))
    }
}

#[cfg(test)]
#[path = "refined_tests.rs"]
mod tests;
