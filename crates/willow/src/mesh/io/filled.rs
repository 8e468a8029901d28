//! [`Asset::with_patches`]: the asset with hole patches appended ([`crate::mesh::holes`],
//! issue 40 item 2), its file's numbering, UVs and document kept.
//!
//! A filled asset is a refined one with zero levels plus trailing triangles
//! ([`RefinedSource::base_triangles`]), so it is written by the refined writers: a glTF keeps
//! its document (each patch joins the primitive of the surface beside its hole), an OBJ its
//! statements (the patches' faces follow the last face). Per patch:
//!
//! - **Vertices**: every new welded vertex is one new split vertex and one new file vertex,
//!   appended after the file's own, so `v` line `k` (or accessor vertex `k`) is still file
//!   vertex `k` of the frames. A loop vertex reuses the split vertex of the surface beside the
//!   hole; where the loop crosses into another block (a hole between two glTF primitives) it
//!   gets a copy in the patch's block.
//! - **UVs and other varyings** (glTF TEXCOORD_n, COLOR_n, OBJ `v` colours) are the harmonic
//!   interpolation of the loop's values over the patch (uniform weights: the patch is faired,
//!   near-isotropic), so texture stays continuous across the seam. A loop whose corners do not
//!   share one chart (a UV seam runs into the hole, or the hole spans blocks) gets no UVs on
//!   its patch, with a note.
//! - **Winding**: each patch triangle is written in the winding of the input triangle beside
//!   its hole's first edge, as the surface's own faces are.

use super::refined::RefinedSource;
use super::{normal_groups_of, Asset, Block, Source};
use crate::mesh::holes::Filled;
use crate::mesh::{Limits, Mesh, MeshError};
use std::collections::HashMap;

/// Gauss–Seidel sweeps of the harmonic interpolation; patches are a few hundred vertices and
/// start from the loop's mean, so this converges to far below a texel.
const HARMONIC_SWEEPS: usize = 400;

impl Asset {
    /// The asset with `filled`'s patches (made from this asset's surface by
    /// [`crate::mesh::holes::fill_holes`]) appended, the whole surface at `positions`
    /// (welded, `filled.mesh`'s numbering: the patches faired, the surface's own vertices
    /// where they were). The file's vertices and triangles keep their numbers (module docs).
    pub fn with_patches(
        &self,
        filled: &Filled,
        positions: Vec<[f64; 3]>,
        limits: &Limits,
    ) -> Result<Asset, MeshError> {
        let nw = self.surface.vertex_count();
        let nt = self.surface.face_count();
        if filled.original_vertices != nw
            || filled.original_triangles != nt
            || positions.len() != filled.mesh.vertex_count()
        {
            return Err(MeshError::Unsupported {
                detail: format!(
                    "fill_holes: the patches were made for another surface ({} vertices, {} \
                     triangles; this one has {nw}, {nt})",
                    filled.original_vertices, filled.original_triangles
                ),
            });
        }
        if filled.holes.is_empty() {
            return Ok(self.clone());
        }
        let mut out = match &self.source {
            Source::Refined(_) => self.clone(),
            _ => self.subdivided(0, limits)?,
        };
        append(&mut out, filled, &positions)?;
        out.surface = Mesh::with_limits(positions, filled.mesh.triangles.clone(), limits)?;
        Ok(out)
    }
}

/// One new split vertex before blocks are made contiguous again.
struct NewSplit {
    welded: usize,
    /// Input block (`RefinedSource::old_blocks` counts them).
    block: usize,
    /// A loop vertex's copy in another block: the split vertex it copies.
    copy_of: Option<usize>,
}

fn append(asset: &mut Asset, filled: &Filled, positions: &[[f64; 3]]) -> Result<(), MeshError> {
    let Source::Refined(r) = &mut asset.source else {
        return Err(malformed("a filled asset's source"));
    };
    let old_blocks = r.old_blocks;
    let n_split = asset.to_welded.len();
    let nt = asset.surface.triangles.len();
    let input_block_of = block_lookup(&asset.file.blocks, old_blocks, n_split);

    // The surface's triangle beside each loop edge, and its corner at each loop vertex.
    let mut loop_edges: HashMap<(usize, usize), usize> = HashMap::new();
    for h in &filled.holes {
        for (i, &a) in h.boundary.iter().enumerate() {
            let b = h.boundary[(i + 1) % h.boundary.len()];
            loop_edges.insert((a.min(b), a.max(b)), usize::MAX);
        }
    }
    for (t, tri) in asset.surface.triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            if let Some(slot) = loop_edges.get_mut(&(a.min(b), a.max(b))) {
                *slot = t;
            }
        }
    }
    let corner = |t: usize, w: usize| -> Option<usize> {
        let st = asset.surface.triangles.get(t)?;
        let k = st.iter().position(|&x| x == w)?;
        asset.file.triangles.get(t).map(|ft| ft[k])
    };

    let mut news: Vec<NewSplit> = Vec::new();
    let mut triangles: Vec<[usize; 3]> = Vec::new();
    let mut roots: Vec<usize> = Vec::new();
    let mut blocks_of: Vec<usize> = Vec::new();
    let mut uvs_new: Vec<Option<[f64; 2]>> = Vec::new();
    let mut varyings_new: Vec<Vec<f64>> = vec![Vec::new(); r.varyings.len()];
    let mut colours_new: Vec<Option<[f64; 3]>> = Vec::new();
    let mut uvless = 0usize;
    for h in &filled.holes {
        let n = h.boundary.len();
        let beside = |i: usize| -> Result<usize, MeshError> {
            let (a, b) = (h.boundary[i % n], h.boundary[(i + 1) % n]);
            match loop_edges.get(&(a.min(b), a.max(b))) {
                Some(&t) if t < nt => Ok(t),
                _ => Err(malformed("a hole's loop edge without a face")),
            }
        };
        let first = beside(0)?;
        let block = corner(first, h.boundary[0])
            .and_then(|sv| input_block_of.get(sv).copied())
            .ok_or_else(|| malformed("a hole's corner"))?;
        let root = r.root(first);

        // Split vertex of each loop vertex in the patch's block, and whether the loop's
        // corners agree on one chart.
        let mut split_of: HashMap<usize, usize> = HashMap::new();
        let mut one_chart = asset.file.uvs.is_some();
        for i in 0..n {
            let w = h.boundary[i];
            let before = corner(beside(i + n - 1)?, w).ok_or_else(|| malformed("corner"))?;
            let after = corner(beside(i)?, w).ok_or_else(|| malformed("corner"))?;
            let uv = |sv: usize| {
                asset
                    .file
                    .uvs
                    .as_ref()
                    .and_then(|u| u.get(sv).copied().flatten())
            };
            if uv(before).is_none() || uv(before) != uv(after) {
                one_chart = false;
            }
            let own = [after, before]
                .into_iter()
                .find(|&sv| input_block_of.get(sv) == Some(&block));
            let sv = match own {
                Some(sv) => sv,
                None => {
                    one_chart = false;
                    news.push(NewSplit {
                        welded: w,
                        block,
                        copy_of: Some(after),
                    });
                    n_split + news.len() - 1
                }
            };
            split_of.insert(w, sv);
        }
        for k in 0..h.vertex_count {
            let w = h.first_vertex + k;
            news.push(NewSplit {
                welded: w,
                block,
                copy_of: None,
            });
            split_of.insert(w, n_split + news.len() - 1);
        }
        for t in h.first_triangle..h.first_triangle + h.triangle_count {
            let tri = filled
                .mesh
                .triangles
                .get(t)
                .ok_or_else(|| malformed("a patch triangle"))?;
            let mut st = [0; 3];
            for k in 0..3 {
                st[k] = *split_of
                    .get(&tri[k])
                    .ok_or_else(|| malformed("a patch corner"))?;
            }
            triangles.push(st);
            roots.push(root);
            blocks_of.push(block);
        }

        // Harmonic values over the patch: the loop's fixed, the new vertices free.
        let patch = Patch::new(h, &filled.mesh.triangles);
        let loop_split: Vec<usize> = h.boundary.iter().map(|w| split_of[w]).collect();
        if asset.file.uvs.is_some() {
            if one_chart {
                let fixed: Vec<f64> = loop_split
                    .iter()
                    .flat_map(|&sv| {
                        let uv = asset
                            .file
                            .uvs
                            .as_ref()
                            .and_then(|u| u.get(sv).copied().flatten());
                        uv.unwrap_or([0.0; 2])
                    })
                    .collect();
                let free = patch.harmonic(&fixed, 2);
                uvs_new.extend(free.chunks_exact(2).map(|c| Some([c[0], c[1]])));
            } else {
                uvless += 1;
                uvs_new.extend(std::iter::repeat_n(None, h.vertex_count));
            }
        }
        for (v, out) in r.varyings.iter().zip(&mut varyings_new) {
            let w = v.width;
            if v.block == block {
                let fixed: Vec<f64> = loop_split
                    .iter()
                    .flat_map(|&sv| {
                        let s = v.values.get(sv * w..(sv + 1) * w);
                        s.map(<[f64]>::to_vec).unwrap_or_else(|| vec![0.0; w])
                    })
                    .collect();
                out.extend(patch.harmonic(&fixed, w));
            } else {
                out.extend(std::iter::repeat_n(0.0, h.vertex_count * w));
            }
        }
        if let Some(colours) = &r.v_colours {
            let loop_colours: Option<Vec<f64>> = loop_split
                .iter()
                .map(|&sv| {
                    let v = r.v_of_split.get(sv).copied()?;
                    colours.get(v).copied().flatten()
                })
                .collect::<Option<Vec<[f64; 3]>>>()
                .map(|c| c.concat());
            match loop_colours {
                Some(fixed) => colours_new.extend(
                    patch
                        .harmonic(&fixed, 3)
                        .chunks_exact(3)
                        .map(|c| Some([c[0], c[1], c[2]])),
                ),
                None => colours_new.extend(std::iter::repeat_n(None, h.vertex_count)),
            }
        }
    }
    let total = n_split + news.len();

    // Per new split vertex, its values, in `news` order (copies take their source's).
    let mut uv_iter = uvs_new.into_iter();
    let mut colour_iter = colours_new.into_iter();
    let mut var_iters: Vec<_> = varyings_new.into_iter().map(Vec::into_iter).collect();
    for ns in &news {
        // The next file vertex: every new split vertex is one (module docs).
        let v_count = r.stored.len();
        asset.to_welded.push(ns.welded);
        if let Some(uvs) = asset.file.uvs.as_mut() {
            let uv = match ns.copy_of {
                Some(sv) => uvs.get(sv).copied().flatten(),
                None => uv_iter.next().flatten(),
            };
            uvs.push(uv);
        }
        if let Some(keys) = asset.file.normal_keys.as_mut() {
            let key = ns.copy_of.and_then(|sv| keys.get(sv).copied()).unwrap_or(0);
            keys.push(key);
        }
        for (v, it) in r.varyings.iter_mut().zip(&mut var_iters) {
            for k in 0..v.width {
                let x = match ns.copy_of {
                    Some(sv) => v.values.get(sv * v.width + k).copied().unwrap_or(0.0),
                    None => it.next().unwrap_or(0.0),
                };
                v.values.push(x);
            }
        }
        let source_file = ns.copy_of.and_then(|sv| r.v_of_split.get(sv).copied());
        if let Some(colours) = r.v_colours.as_mut() {
            colours.resize(v_count, None);
            let c = match source_file {
                Some(v) => colours.get(v).copied().flatten(),
                None => colour_iter.next().flatten(),
            };
            colours.push(c);
        }
        r.v_of_split.push(v_count);
        // In its block's local space, as a file stores it.
        let to_local = asset
            .file
            .blocks
            .get(old_blocks + ns.block)
            .map(|b| b.to_local)
            .ok_or_else(|| malformed("a patch's block"))?;
        let local = to_local.apply(positions.get(ns.welded).copied().unwrap_or([0.0; 3]));
        asset.file.local.push(local);
        r.stored.push(local);
    }
    asset.file.triangles.extend(&triangles);
    r.patch_roots.extend(roots);
    r.patch_blocks.extend(blocks_of);
    if let Some(faces) = asset.file.face_of_triangle.as_mut() {
        let last = faces.last().copied().unwrap_or(0);
        faces.extend(std::iter::repeat_n(last, triangles.len()));
    }

    // Blocks contiguous again: each new split vertex joins its input block's new block, after
    // the vertices that block has (refined.rs numbers them so).
    let mut order: Vec<usize> = Vec::with_capacity(total);
    let mut new_by_block: Vec<Vec<usize>> = vec![Vec::new(); asset.file.blocks.len()];
    for (i, ns) in news.iter().enumerate() {
        if let Some(list) = new_by_block.get_mut(old_blocks + ns.block) {
            list.push(n_split + i);
        }
    }
    let mut blocks: Vec<Block> = Vec::with_capacity(asset.file.blocks.len());
    for (j, b) in asset.file.blocks.iter().enumerate() {
        let start = order.len();
        order.extend(b.start..b.start + b.len);
        order.extend(&new_by_block[j]);
        blocks.push(Block {
            start,
            len: order.len() - start,
            ..*b
        });
    }
    if order.len() != total {
        return Err(malformed("a patch vertex outside every block"));
    }
    let mut renumber = vec![0usize; total];
    for (new, &old) in order.iter().enumerate() {
        renumber[old] = new;
    }
    let permute = |v: &mut Vec<usize>| *v = order.iter().map(|&o| v[o]).collect();
    permute(&mut asset.to_welded);
    permute(&mut r.v_of_split);
    asset.file.local = order.iter().map(|&o| asset.file.local[o]).collect();
    if let Some(uvs) = asset.file.uvs.as_mut() {
        *uvs = order.iter().map(|&o| uvs[o]).collect();
    }
    if let Some(keys) = asset.file.normal_keys.as_mut() {
        *keys = order.iter().map(|&o| keys[o]).collect();
    }
    for v in &mut r.varyings {
        let w = v.width;
        v.values = order
            .iter()
            .flat_map(|&o| v.values[o * w..(o + 1) * w].to_vec())
            .collect();
    }
    for t in &mut asset.file.triangles {
        *t = t.map(|sv| renumber[sv]);
    }
    asset.file.blocks = blocks;

    asset.normal_groups = asset
        .file
        .normal_keys
        .as_ref()
        .map(|keys| normal_groups_of(&asset.to_welded, keys));
    let vertices: usize = filled.holes.iter().map(|h| h.vertex_count).sum();
    r.notes.push(format!(
        "fill_holes: {} holes closed with {vertices} vertices and {} triangles, appended after \
         the file's own",
        filled.holes.len(),
        triangles.len()
    ));
    if uvless > 0 {
        r.notes.push(format!(
            "fill_holes: {uvless} patches have no UVs (a UV seam or a primitive's border runs \
             into the hole); their vertices are written with UV (0, 0)"
        ));
    }
    Ok(())
}

/// Input block of every split vertex (a refined block `old_blocks + i` is input block `i`).
fn block_lookup(blocks: &[Block], old_blocks: usize, n: usize) -> Vec<usize> {
    let mut of = vec![0usize; n];
    for (j, b) in blocks.iter().enumerate() {
        let input = if j >= old_blocks { j - old_blocks } else { j };
        for slot in of.iter_mut().skip(b.start).take(b.len) {
            *slot = input;
        }
    }
    of
}

/// A hole's patch as a graph: its loop's vertices (fixed, local `0..n`) then its new ones
/// (free, local `n..`), each with its patch neighbours.
struct Patch {
    fixed: usize,
    neighbours: Vec<Vec<usize>>,
}

impl Patch {
    fn new(h: &crate::mesh::holes::FilledHole, triangles: &[[usize; 3]]) -> Patch {
        let n = h.boundary.len();
        let mut local: HashMap<usize, usize> = HashMap::new();
        for (i, &w) in h.boundary.iter().enumerate() {
            local.insert(w, i);
        }
        for k in 0..h.vertex_count {
            local.insert(h.first_vertex + k, n + k);
        }
        let mut neighbours = vec![Vec::new(); n + h.vertex_count];
        let tris = triangles
            .iter()
            .skip(h.first_triangle)
            .take(h.triangle_count);
        for t in tris {
            let l = t.map(|w| local.get(&w).copied());
            for k in 0..3 {
                if let (Some(a), Some(b)) = (l[k], l[(k + 1) % 3]) {
                    if !neighbours[a].contains(&b) {
                        neighbours[a].push(b);
                        neighbours[b].push(a);
                    }
                }
            }
        }
        Patch {
            fixed: n,
            neighbours,
        }
    }

    /// The discrete harmonic extension (uniform weights) of `fixed` (`width` numbers per
    /// loop vertex) to the new vertices, `width` numbers each.
    fn harmonic(&self, fixed: &[f64], width: usize) -> Vec<f64> {
        let n = self.fixed;
        let total = self.neighbours.len();
        let mut x = vec![0.0; total * width];
        x[..n * width].copy_from_slice(&fixed[..n * width]);
        let mut mean = vec![0.0; width];
        for i in 0..n {
            for k in 0..width {
                mean[k] += fixed[i * width + k] / n.max(1) as f64;
            }
        }
        for i in n..total {
            x[i * width..(i + 1) * width].copy_from_slice(&mean);
        }
        let scale = fixed.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1.0);
        for _ in 0..HARMONIC_SWEEPS {
            let mut change = 0.0f64;
            for i in n..total {
                let nb = &self.neighbours[i];
                if nb.is_empty() {
                    continue;
                }
                for k in 0..width {
                    let avg = nb.iter().map(|&j| x[j * width + k]).sum::<f64>() / nb.len() as f64;
                    change = change.max((avg - x[i * width + k]).abs());
                    x[i * width + k] = avg;
                }
            }
            if change < 1e-12 * scale {
                break;
            }
        }
        x.split_off(n * width)
    }
}

fn malformed(what: &str) -> MeshError {
    MeshError::Unsupported {
        detail: format!("fill_holes: internal bookkeeping failed ({what})"),
    }
}

impl RefinedSource {
    /// Patch triangles of input block `block`, as indices into the asset's triangles.
    pub(crate) fn patch_triangles(&self, block: usize) -> impl Iterator<Item = usize> + '_ {
        self.patch_blocks
            .iter()
            .enumerate()
            .filter(move |(_, &b)| b == block)
            .map(move |(k, _)| self.base_triangles + k)
    }
}
