//! Joining the file's split vertices into the surface's vertices, without ever making the
//! surface non-manifold (issue 27, item 3).
//!
//! The fast path joins every split vertex at the same exact world position ([`by_position`]):
//! it closes UV and normal seams, joins glTF primitives and STL's triangle soup, and for almost
//! every file is the whole story. When the result is refused (a bowtie or an edge with three
//! faces), coincident vertices may have been joined that the file keeps apart: pymeshlab's
//! `cow.obj` has `v` lines 45 and 2904 at one position, each with its own closed fan. Then
//! [`by_corners`] joins triangle corners only where the file says they are one vertex (the same
//! file vertex, e.g. one OBJ `v` line) or where two triangles meet along an edge that exactly
//! those two triangles share (a seam: both edges' ends coincide). Two fans that touch only at a
//! point stay two vertices; a file vertex whose own faces form two fans is still refused.

use super::UNWELDED;
use std::collections::HashMap;

/// The surface's vertices and triangles, and the surface vertex of each split vertex.
pub(crate) struct Weld {
    pub(crate) positions: Vec<[f64; 3]>,
    pub(crate) triangles: Vec<[usize; 3]>,
    /// Split vertex → surface vertex (`UNWELDED` when no triangle uses it).
    pub(crate) to_welded: Vec<usize>,
}

/// The key of an exact position: `+ 0.0` turns -0.0 into +0.0 so the two are one position.
fn key(p: [f64; 3]) -> [u64; 3] {
    p.map(|x| (x + 0.0).to_bits())
}

/// Joins split vertices at the same exact position, numbered in order of first use by a
/// triangle corner (so re-reading a written file gives the same numbering). `None` when a
/// triangle names a split vertex that does not exist.
pub(crate) fn by_position(world: &[[f64; 3]], triangles: &[[usize; 3]]) -> Option<Weld> {
    let mut to_welded = vec![UNWELDED; world.len()];
    let mut ids: HashMap<[u64; 3], usize> = HashMap::new();
    let mut positions = Vec::new();
    let mut out = Vec::with_capacity(triangles.len());
    for t in triangles {
        let mut w = [0usize; 3];
        for (k, &sv) in t.iter().enumerate() {
            let p = *world.get(sv)?;
            let id = *ids.entry(key(p)).or_insert_with(|| {
                positions.push(p);
                positions.len() - 1
            });
            to_welded[sv] = id;
            w[k] = id;
        }
        out.push(w);
    }
    Some(Weld {
        positions,
        triangles: out,
        to_welded,
    })
}

fn find(parent: &mut [u32], mut x: u32) -> u32 {
    while parent[x as usize] != x {
        parent[x as usize] = parent[parent[x as usize] as usize]; // path halving
        x = parent[x as usize];
    }
    x
}

fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    if ra != rb {
        parent[ra.max(rb) as usize] = ra.min(rb);
    }
}

/// Joins triangle corners into surface vertices (see the module docs): corners of the same
/// file vertex (`file_of[split]`) when `join_file_vertices`, and the corners at both ends of
/// an edge shared by exactly two triangles, at the position level or, where more triangles meet
/// at a position-level edge, at the file-vertex level.
///
/// Without `join_file_vertices` (repair), every surface vertex is one fan of triangles: a file
/// vertex whose faces form two fans becomes two vertices, and an edge with three or more faces
/// is cut apart. A split vertex whose corners end in several surface vertices is reported in
/// `to_welded` by the first; [`Weld::triangles`] is what counts.
///
/// Callers have checked every triangle's split vertices exist (via [`by_position`]).
pub(crate) fn by_corners(
    world: &[[f64; 3]],
    triangles: &[[usize; 3]],
    file_of: &dyn Fn(usize) -> usize,
    join_file_vertices: bool,
) -> Weld {
    let mut pos_ids: HashMap<[u64; 3], u32> = HashMap::new();
    let pos: Vec<u32> = world
        .iter()
        .map(|p| {
            let n = pos_ids.len() as u32;
            *pos_ids.entry(key(*p)).or_insert(n)
        })
        .collect();
    let corners = triangles.len() * 3;
    let mut parent: Vec<u32> = (0..corners as u32).collect();
    let corner = |t: usize, k: usize| (3 * t + k) as u32;
    if join_file_vertices {
        let mut first: HashMap<usize, u32> = HashMap::new();
        for (t, tri) in triangles.iter().enumerate() {
            for (k, &sv) in tri.iter().enumerate() {
                let c = corner(t, k);
                let f = *first.entry(file_of(sv)).or_insert(c);
                union(&mut parent, f, c);
            }
        }
    }
    // Edges at the position level: (low position, high position) → corner of the edge's start.
    let mut edges: Vec<(u64, u32)> = Vec::with_capacity(corners);
    for (t, tri) in triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (pos[tri[k]], pos[tri[(k + 1) % 3]]);
            if a != b {
                let key = (u64::from(a.min(b)) << 32) | u64::from(a.max(b));
                edges.push((key, corner(t, k)));
            }
        }
    }
    edges.sort_unstable();
    // The corners of triangle `c / 3` at both ends of its edge starting at corner `c`,
    // ordered (low position end, high position end).
    let ends = |c: u32| -> [u32; 2] {
        let (t, k) = (c / 3, c % 3);
        let next = 3 * t + (k + 1) % 3;
        let tri = triangles[t as usize];
        if pos[tri[k as usize]] < pos[tri[((k + 1) % 3) as usize]] {
            [c, next]
        } else {
            [next, c]
        }
    };
    let file_at = |c: u32| file_of(triangles[(c / 3) as usize][(c % 3) as usize]);
    let join_pair = |parent: &mut [u32], a: u32, b: u32| {
        let (ea, eb) = (ends(a), ends(b));
        union(parent, ea[0], eb[0]);
        union(parent, ea[1], eb[1]);
    };
    let mut i = 0;
    while i < edges.len() {
        let mut j = i + 1;
        while j < edges.len() && edges[j].0 == edges[i].0 {
            j += 1;
        }
        let group = &edges[i..j];
        if group.len() == 2 {
            join_pair(&mut parent, group[0].1, group[1].1);
        } else if group.len() > 2 {
            // Several surfaces touch along this edge: pair triangles only along the file's
            // own edges (same file vertices at both ends) that have exactly two triangles.
            let mut by_file: HashMap<[usize; 2], Vec<u32>> = HashMap::new();
            for &(_, c) in group {
                let [lo, hi] = ends(c);
                by_file
                    .entry([file_at(lo), file_at(hi)])
                    .or_default()
                    .push(c);
            }
            for cs in by_file.values() {
                if let [a, b] = cs.as_slice() {
                    join_pair(&mut parent, *a, *b);
                }
            }
        }
        i = j;
    }
    // Surface vertices in order of first use by a corner.
    let mut id_of_root: HashMap<u32, usize> = HashMap::new();
    let mut positions = Vec::new();
    let mut to_welded = vec![UNWELDED; world.len()];
    let mut out = Vec::with_capacity(triangles.len());
    for (t, tri) in triangles.iter().enumerate() {
        let mut w = [0usize; 3];
        for (k, &sv) in tri.iter().enumerate() {
            let root = find(&mut parent, corner(t, k));
            let id = *id_of_root.entry(root).or_insert_with(|| {
                positions.push(world[sv]);
                positions.len() - 1
            });
            if to_welded[sv] == UNWELDED {
                to_welded[sv] = id;
            }
            w[k] = id;
        }
        out.push(w);
    }
    Weld {
        positions,
        triangles: out,
        to_welded,
    }
}
