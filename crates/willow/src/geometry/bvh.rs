//! Nearest points on triangles through a bounding volume hierarchy (used by
//! [`super::distance`]).
//!
//! - [`closest_point_on_triangle`]: the exact nearest point of one triangle (Ericson,
//!   *Real-Time Collision Detection*, §5.1.5: Voronoi regions of the vertices, edges, face).
//! - [`Bvh`]: a binary tree of axis-aligned boxes over a mesh's triangles, built once
//!   (median split on the longest axis of the centroids) and *refitted* when the vertices
//!   move: connectivity never changes during a flow, so only the boxes need refilling. A tree
//!   whose refitted boxes have grown much looser than a fresh build's is rebuilt.
//! - Each node also carries a [`Disc`]: a slab along the patch's mean normal cut by a
//!   cylinder across it. A query far above a nearly flat patch (a flow moves nefertiti tens
//!   of edge lengths in a step) finds every box under its nearest point about one box size
//!   closer than the triangles in it, and opened several hundred triangles per query; the
//!   disc's bound is within the patch's thickness of the truth, and took that to ~30.
//! - Queries walk a four-wide copy of the tree ([`Wide`]: each node with its grandchildren
//!   side by side, refreshed after every refit): half the pops, four boxes tested in one pass
//!   (a query 20-35% faster on nefertiti's frames than down the binary tree, which the refit
//!   and the distance's top-down max keep using).
//!
//! Why not a crate (issue 41): parry3d-f64 0.31.1, the well-kept library with closest-point
//! queries on f64 triangle meshes, measured beside this tree on nefertiti (99,938
//! triangles) in one program (best of 5, release, 3,072 queries from vertices moved 0.3, 3
//! and 40 mean edges off the surface, no hints): building takes the same (54–67 ms both);
//! its `TriMesh::distance_to_point` took 9.1 / 10.4 / 30.8 ms where [`Bvh::nearest`] took
//! 7.2 / 8.3 / 16.3 ms (1.25–1.89× slower; the same mean distance to 1e-6). Nor does it
//! offer what the distance measure is built on: a refit that keeps the tree as the vertices
//! move (a fresh build every frame would cost more than the whole measurement's 10% of a
//! step), queries started from a hint face, a relative slack, and an early stop
//! ([`Bvh::nearest_until`]). The comparison program is not kept in the repository: it would
//! make parry and its math crates a dependency of every test build.

use super::vec3::{add, cross, dot, scale, sub};
use crate::parallel::join;

/// Closest point to `p` on the triangle `(a, b, c)` (Ericson §5.1.5). Exact in exact
/// arithmetic for any triangle; a degenerate one (a segment or a point) gives the nearest
/// point of what it degenerates to, or a vertex: never NaN for finite input.
pub fn closest_point_on_triangle(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return add(a, scale(ab, v));
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return add(a, scale(ac, w));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return add(b, scale(sub(c, b), w));
    }
    let sum = va + vb + vc;
    if sum.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        // Degenerate (zero-area) triangle whose regions above all missed: the nearest
        // vertex is within rounding of the answer.
        return [a, b, c]
            .into_iter()
            .min_by(|x, y| dist2(p, *x).total_cmp(&dist2(p, *y)))
            .unwrap_or(a);
    }
    let denom = 1.0 / sum;
    let v = vb * denom;
    let w = vc * denom;
    add(a, add(scale(ab, v), scale(ac, w)))
}

/// The squared distance from `p` to triangle `f`.
#[inline]
pub(crate) fn triangle_d2(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    p: [f64; 3],
    f: usize,
) -> f64 {
    let t = triangles[f];
    dist2(
        p,
        closest_point_on_triangle(p, positions[t[0]], positions[t[1]], positions[t[2]]),
    )
}

#[inline]
pub(crate) fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = sub(a, b);
    dot(d, d)
}

/// Triangles per leaf: a leaf's disc prunes most leaves a query reaches before their
/// triangles are tested, so a shallower tree with larger leaves opens fewer nodes (8 measured
/// ~10% faster than 4 and 30% faster than 2 on nefertiti's frames).
const LEAF_SIZE: usize = 8;
/// Deepest possible traversal stack: a median split halves the triangles at every level,
/// so depth ≤ log2(triangles) + 1, and 64 covers any mesh that fits in memory.
const STACK: usize = 64;
/// A refitted tree is rebuilt when the summed surface area of its boxes exceeds this multiple
/// of a fresh build's: refitting keeps the build's grouping, which gets loose when the surface
/// deforms a lot (spot → sphere), and a loose tree visits more boxes per query.
const REBUILD_GROWTH: f64 = 2.0;

#[derive(Clone, Copy, Debug)]
pub(crate) struct Node {
    pub(crate) min: [f64; 3],
    pub(crate) max: [f64; 3],
    /// Leaf: first index into `Bvh::order`; inner: index of the right child (the left
    /// child is the next node: the nodes are stored in depth-first pre-order).
    pub(crate) start: u32,
    /// Triangles in a leaf; 0 for an inner node.
    pub(crate) count: u32,
    /// A second bound, tighter than the box over nearly flat patches.
    disc: Disc,
}

/// A bounding volume hierarchy over the triangles of one mesh (module docs).
#[derive(Clone, Debug)]
pub struct Bvh {
    pub(crate) nodes: Vec<Node>,
    /// Triangle indices, grouped by leaf.
    pub(crate) order: Vec<u32>,
    /// Summed surface area of the boxes right after the last build.
    built_box_area: f64,
    /// Which build made this tree's nodes and order (unique per build; a clone keeps it, a
    /// rebuild on refit takes a new one): two trees with the same layout group the same
    /// triangles into the same nodes ([`Bvh::same_layout`]).
    layout: u64,
    /// What a refit reads per leaf ([`Leaves`]).
    leaves: Leaves,
    /// The same tree with four children a node, for queries ([`Wide`]).
    wide: Vec<Wide>,
}

/// Each leaf's distinct vertices, listed once at build: a refit reads a leaf's 6-10 distinct
/// positions through one contiguous index run, instead of its triangles' 24 corners through
/// two scattered lookups each (`order`, then `triangles`), which were most of its cost.
#[derive(Clone, Debug, Default)]
struct Leaves {
    /// Per node, its run in `vertices` (`[start, end)`; empty for inner nodes).
    runs: Vec<[u32; 2]>,
    /// The leaves' distinct vertices, leaf after leaf.
    vertices: Vec<u32>,
    /// Per entry of `Bvh::order`, its triangle's corners as positions in its leaf's run.
    corners: Vec<[u8; 3]>,
    /// Scratch of a refit: the positions of `vertices`.
    positions: Vec<[f64; 3]>,
}

impl Leaves {
    fn new(nodes: &[Node], order: &[u32], triangles: &[[usize; 3]]) -> Self {
        let mut leaves = Leaves {
            runs: vec![[0, 0]; nodes.len()],
            vertices: Vec::with_capacity(order.len()),
            corners: vec![[0; 3]; order.len()],
            positions: Vec::new(),
        };
        for (node, run) in nodes.iter().zip(&mut leaves.runs) {
            if node.count == 0 {
                continue;
            }
            let first = leaves.vertices.len();
            let s = node.start as usize;
            for (k, &f) in order[s..s + node.count as usize].iter().enumerate() {
                for (c, &v) in triangles[f as usize].iter().enumerate() {
                    let at = match leaves.vertices[first..]
                        .iter()
                        .position(|&w| w as usize == v)
                    {
                        Some(at) => at,
                        None => {
                            leaves.vertices.push(v as u32);
                            leaves.vertices.len() - 1 - first
                        }
                    };
                    // At most 3 · LEAF_SIZE = 24 distinct vertices, so a u8 holds it.
                    leaves.corners[s + k][c] = at as u8;
                }
            }
            *run = [first as u32, leaves.vertices.len() as u32];
        }
        leaves
    }
}

impl Bvh {
    /// Build the tree of `triangles` at `positions` (indices must be in range: a validated
    /// [`crate::mesh::Mesh`]). An empty mesh gives an empty tree whose queries find nothing.
    pub fn new(positions: &[[f64; 3]], triangles: &[[usize; 3]]) -> Self {
        let mut bvh = Bvh {
            nodes: Vec::with_capacity(2 * triangles.len().div_ceil(LEAF_SIZE)),
            order: (0..triangles.len() as u32).collect(),
            built_box_area: 0.0,
            layout: 0,
            leaves: Leaves::default(),
            wide: Vec::new(),
        };
        bvh.build(positions, triangles);
        bvh
    }

    fn build(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]]) {
        static BUILDS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        self.layout = BUILDS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        self.nodes.clear();
        for (k, o) in self.order.iter_mut().enumerate() {
            *o = k as u32;
        }
        if triangles.is_empty() {
            self.built_box_area = 0.0;
            return;
        }
        let centroids: Vec<[f64; 3]> = triangles
            .iter()
            .map(|t| {
                scale(
                    add(add(positions[t[0]], positions[t[1]]), positions[t[2]]),
                    1.0 / 3.0,
                )
            })
            .collect();
        // Depth-first pre-order with an explicit stack (deep trees cannot overflow the
        // thread's stack): a node is numbered when popped, so a left child, pushed last, is
        // always its parent + 1; a right child patches its index into its parent.
        let mut pending: Vec<(usize, usize, Option<usize>)> = vec![(0, triangles.len(), None)];
        while let Some((start, end, parent)) = pending.pop() {
            let index = self.nodes.len();
            if let Some(parent) = parent {
                self.nodes[parent].start = index as u32;
            }
            let (min, max) = bounds(positions, triangles, &self.order[start..end]);
            // Each node's disc fitted to all its triangles (a merge of the children's, as a
            // refit makes, is looser by the children's tilt).
            let disc = Disc::fit(positions, triangles, &self.order[start..end]);
            if end - start <= LEAF_SIZE {
                self.nodes.push(Node {
                    min,
                    max,
                    start: start as u32,
                    count: (end - start) as u32,
                    disc,
                });
                continue;
            }
            self.nodes.push(Node {
                min,
                max,
                start: 0,
                count: 0,
                disc,
            });
            let (mut cmin, mut cmax) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
            for &f in &self.order[start..end] {
                let c = centroids[f as usize];
                for k in 0..3 {
                    cmin[k] = cmin[k].min(c[k]);
                    cmax[k] = cmax[k].max(c[k]);
                }
            }
            let extent = sub(cmax, cmin);
            let axis = if extent[0] >= extent[1] && extent[0] >= extent[2] {
                0
            } else if extent[1] >= extent[2] {
                1
            } else {
                2
            };
            let mid = start + (end - start) / 2;
            self.order[start..end].select_nth_unstable_by(mid - start, |&x, &y| {
                centroids[x as usize][axis].total_cmp(&centroids[y as usize][axis])
            });
            pending.push((mid, end, Some(index)));
            pending.push((start, mid, None));
        }
        self.built_box_area = self.box_area();
        self.leaves = Leaves::new(&self.nodes, &self.order, triangles);
        // A refit's scratch, filled once here so that the first refit of a flow (its first
        // frame) does not pay for fresh pages.
        self.leaves.positions = (self.leaves.vertices.iter())
            .map(|&v| positions[v as usize])
            .collect();
        self.wide.clear();
        if !self.nodes.is_empty() {
            Wide::collapse(&self.nodes, 0, &mut self.wide);
        }
    }

    /// Refill every box and disc after the vertices moved (children before parents: reverse
    /// pre-order), and rebuild when the refitted boxes got much looser than a fresh build's
    /// (twice as loose, by their summed surface area).
    pub fn refit(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]]) {
        self.refit_with(positions, triangles, false);
    }

    /// [`Bvh::refit`], the root's two subtrees on two threads when `parallel` (the same
    /// result: each node is fitted from the same inputs either way).
    pub fn refit_with(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]], parallel: bool) {
        let Some(root) = self.nodes.first().copied() else {
            return;
        };
        let Leaves {
            runs,
            vertices,
            corners,
            positions: gathered,
        } = &mut self.leaves;
        gathered.resize(vertices.len(), [0.0; 3]);
        if root.count > 0 || !parallel {
            fit_subtree(
                &mut self.nodes,
                0,
                positions,
                runs,
                vertices,
                corners,
                gathered,
            );
        } else {
            // Pre-order: the left subtree is nodes 1..right, the right one right..; their
            // leaves' vertex runs are in the same order, so both split where the right
            // subtree's first leaf run starts.
            let right = root.start as usize;
            let split = runs[right..]
                .iter()
                .zip(&self.nodes[right..])
                .find(|(_, n)| n.count > 0)
                .map_or(vertices.len(), |(r, _)| r[0] as usize);
            let (top, rest) = self.nodes.split_at_mut(1);
            let (left_nodes, right_nodes) = rest.split_at_mut(right - 1);
            let (left_gathered, right_gathered) = gathered.split_at_mut(split);
            let (runs, vertices, corners) = (&*runs, &*vertices, &*corners);
            join(
                true,
                || {
                    fit_subtree(
                        left_nodes,
                        1,
                        positions,
                        runs,
                        vertices,
                        corners,
                        left_gathered,
                    )
                },
                || {
                    fit_subtree(
                        right_nodes,
                        right,
                        positions,
                        runs,
                        &vertices[split..],
                        corners,
                        right_gathered,
                    )
                },
            );
            let (l, r) = (&left_nodes[0], &right_nodes[0]);
            let (min, max, disc) = merged(l, r);
            (top[0].min, top[0].max, top[0].disc) = (min, max, disc);
        }
        if self.box_area() > REBUILD_GROWTH * self.built_box_area {
            self.build(positions, triangles);
        } else {
            for w in &mut self.wide {
                w.copy_bounds(&self.nodes);
            }
        }
    }

    /// Per node, the largest of `values` (one per vertex) over its triangles' corners, into
    /// `out` (children before parents, like a refit; 0 for a node whose values are all NaN).
    pub(crate) fn max_per_node(&self, values: &[f64], out: &mut Vec<f64>) {
        out.resize(self.nodes.len(), 0.0);
        for i in (0..self.nodes.len()).rev() {
            let node = &self.nodes[i];
            out[i] = if node.count > 0 {
                let [a, b] = self.leaves.runs[i].map(|x| x as usize);
                self.leaves.vertices[a..b]
                    .iter()
                    .fold(0.0, |m, &v| larger(values[v as usize], m))
            } else {
                larger(out[i + 1], out[node.start as usize])
            };
        }
    }

    /// Whether `other` groups the same triangles into the same nodes (one was cloned from the
    /// other, and neither was rebuilt since): per-node values over vertices are then the
    /// same for both.
    pub(crate) fn same_layout(&self, other: &Bvh) -> bool {
        self.layout == other.layout
    }

    fn box_area(&self) -> f64 {
        self.nodes
            .iter()
            .map(|n| {
                let e = sub(n.max, n.min);
                e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
            })
            .sum()
    }

    /// The triangle nearest to `p` and the squared distance to it, or `None` for an empty
    /// tree. `hint`, a triangle likely to be near (the same face on the other surface of a
    /// flow), starts the search with a tight bound so most boxes are never opened; the
    /// answer does not depend on it, except which of two equally near triangles is named.
    pub fn nearest(
        &self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        p: [f64; 3],
        hint: Option<usize>,
    ) -> Option<(usize, f64)> {
        self.nearest_within(positions, triangles, p, hint, 0.0)
    }

    /// [`Bvh::nearest`] up to a relative `slack` ≥ 0: a triangle whose distance is at most
    /// `(1 + slack)` times the nearest's. A box is skipped once its distance times
    /// `1 + slack` reaches the best found: far from a surface, most boxes a query must open
    /// for the exact answer lie in the thin shell just inside the nearest distance.
    pub fn nearest_within(
        &self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        p: [f64; 3],
        hint: Option<usize>,
        slack: f64,
    ) -> Option<(usize, f64)> {
        self.nearest_until(positions, triangles, p, hint, slack, -1.0)
    }

    /// [`Bvh::nearest_within`] that stops at the first triangle whose squared distance is
    /// at most `enough` (a caller that only needs to know some face is that near).
    pub(crate) fn nearest_until(
        &self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        p: [f64; 3],
        hint: Option<usize>,
        slack: f64,
        enough: f64,
    ) -> Option<(usize, f64)> {
        let start = match hint {
            Some(f) if f < triangles.len() => (f, triangle_d2(positions, triangles, p, f)),
            _ => (usize::MAX, f64::INFINITY),
        };
        self.nearest_from(positions, triangles, p, start, slack, enough)
    }

    /// [`Bvh::nearest_until`] started from a triangle and its squared distance, already known
    /// (`(usize::MAX, ∞)`: none).
    pub(crate) fn nearest_from(
        &self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        p: [f64; 3],
        start: (usize, f64),
        slack: f64,
        enough: f64,
    ) -> Option<(usize, f64)> {
        if self.wide.is_empty() {
            return None;
        }
        let grow = (1.0 + slack) * (1.0 + slack);
        let mut best = start;
        // Entries: (wide node or leaf start, leaf count or 0, bound).
        let mut stack = [(0u32, 0u32, 0.0f64); 3 * STACK];
        let mut top = 1usize;
        while top > 0 && best.1 > enough {
            top -= 1;
            let (index, count, bound) = stack[top];
            if bound >= best.1 {
                continue;
            }
            if count > 0 {
                let s = index as usize;
                for &f in &self.order[s..s + count as usize] {
                    let d2 = triangle_d2(positions, triangles, p, f as usize);
                    if d2 < best.1 {
                        best = (f as usize, d2);
                    }
                }
                continue;
            }
            let w = &self.wide[index as usize];
            let mut b = [0.0f64; 4];
            for (lane, b) in b.iter_mut().enumerate() {
                let mut d2 = 0.0;
                for k in 0..3 {
                    let d = larger(larger(w.min[k][lane] - p[k], p[k] - w.max[k][lane]), 0.0);
                    d2 += d * d;
                }
                *b = grow * d2;
            }
            let mut order = [0usize; 4];
            let mut n = 0;
            for lane in 0..4 {
                if b[lane] < best.1 {
                    b[lane] = larger(b[lane], grow * w.disc[lane].d2(p));
                    if b[lane] < best.1 {
                        // Insertion by decreasing bound: the nearest is pushed last.
                        let mut at = n;
                        while at > 0 && b[order[at - 1]] < b[lane] {
                            order[at] = order[at - 1];
                            at -= 1;
                        }
                        order[at] = lane;
                        n += 1;
                    }
                }
            }
            for &lane in &order[..n] {
                if top < stack.len() {
                    stack[top] = (w.child[lane], w.count[lane], b[lane]);
                    top += 1;
                }
            }
        }
        (best.0 != usize::MAX).then_some(best)
    }
}

/// Four children of the binary tree's nodes side by side (a node and its grandchildren
/// collapsed): a query tests four boxes in one pass of straight-line arithmetic and pops half
/// as many nodes. Lanes hold a copy of their binary node's box and disc.
#[derive(Clone, Debug)]
struct Wide {
    min: [[f64; 4]; 3],
    max: [[f64; 4]; 3],
    disc: [Disc; 4],
    /// Per lane: a leaf's first index into `order` (count > 0), an inner lane's wide node, or
    /// nothing (count 0 and `child == u32::MAX`).
    child: [u32; 4],
    count: [u32; 4],
    /// Per lane, the binary node it copies (`u32::MAX`: empty lane).
    node: [u32; 4],
}

impl Wide {
    /// Collapse the binary subtree at `root` (an inner node) into `wide`; its index.
    fn collapse(nodes: &[Node], root: usize, wide: &mut Vec<Wide>) -> u32 {
        let index = wide.len();
        wide.push(Wide {
            min: [[f64::INFINITY; 4]; 3],
            max: [[f64::NEG_INFINITY; 4]; 3],
            disc: [Disc::NONE; 4],
            child: [u32::MAX; 4],
            count: [0; 4],
            node: [u32::MAX; 4],
        });
        let mut lanes: Vec<usize> = if nodes[root].count > 0 {
            vec![root]
        } else {
            vec![root + 1, nodes[root].start as usize]
        };
        // Open the largest inner lane while there is room.
        while lanes.len() < 4 {
            let area = |i: usize| {
                let e = sub(nodes[i].max, nodes[i].min);
                e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
            };
            let Some((k, _)) = lanes
                .iter()
                .enumerate()
                .filter(|(_, &i)| nodes[i].count == 0)
                .max_by(|a, b| area(*a.1).total_cmp(&area(*b.1)))
            else {
                break;
            };
            let i = lanes.swap_remove(k);
            lanes.push(i + 1);
            lanes.push(nodes[i].start as usize);
        }
        for (lane, &i) in lanes.iter().enumerate() {
            wide[index].node[lane] = i as u32;
            if nodes[i].count > 0 {
                wide[index].child[lane] = nodes[i].start;
                wide[index].count[lane] = nodes[i].count;
            } else {
                let child = Wide::collapse(nodes, i, wide);
                wide[index].child[lane] = child;
            }
        }
        wide[index].copy_bounds(nodes);
        index as u32
    }

    fn copy_bounds(&mut self, nodes: &[Node]) {
        for lane in 0..4 {
            let Some(n) = nodes.get(self.node[lane] as usize) else {
                continue;
            };
            for k in 0..3 {
                self.min[k][lane] = n.min[k];
                self.max[k][lane] = n.max[k];
            }
            self.disc[lane] = n.disc;
        }
    }
}

/// A lower bound of the distance to a few triangles that hugs a nearly flat patch: the
/// triangles lie in the slab `lo ≤ n·(x − c) ≤ hi` and within `radius` of `c` across `n`, so
/// a point's distance to them is at least the hypotenuse of its distances to the slab and to
/// that cylinder (the two are orthogonal). A box is looser by up to its own size along the
/// patch's normal, which is what a query far from the surface pays for.
#[derive(Clone, Copy, Debug)]
struct Disc {
    centre: [f64; 3],
    normal: [f64; 3],
    lo: f64,
    hi: f64,
    radius: f64,
}

impl Disc {
    /// No bound (every point at distance 0).
    const NONE: Disc = Disc {
        centre: [0.0; 3],
        normal: [0.0; 3],
        lo: f64::NEG_INFINITY,
        hi: f64::INFINITY,
        radius: f64::INFINITY,
    };

    /// The disc of the listed triangles: their area-weighted normal, their vertices' mean as
    /// centre. Degenerate patches (no area, NaN) give [`Disc::NONE`].
    fn fit(positions: &[[f64; 3]], triangles: &[[usize; 3]], faces: &[u32]) -> Disc {
        let (mut normal, mut centre, mut corners) = ([0.0; 3], [0.0; 3], 0.0);
        for &f in faces {
            let [a, b, c] = triangles[f as usize].map(|v| positions[v]);
            normal = add(normal, cross(sub(b, a), sub(c, a)));
            centre = add(add(centre, a), add(b, c));
            corners += 3.0;
        }
        let length = dot(normal, normal).sqrt();
        if !(length > 0.0 && length.is_finite()) {
            return Disc::NONE;
        }
        let (normal, centre) = (scale(normal, 1.0 / length), scale(centre, 1.0 / corners));
        let (mut lo, mut hi, mut r2) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
        for &f in faces {
            for v in triangles[f as usize] {
                let x = sub(positions[v], centre);
                let h = dot(x, normal);
                lo = lo.min(h);
                hi = hi.max(h);
                r2 = r2.max(dot(x, x) - h * h);
            }
        }
        Disc::padded(centre, normal, lo, hi, r2.max(0.0).sqrt())
    }

    /// A disc widened by a relative hair, so rounding in its fit or in [`Disc::d2`] cannot
    /// lift the bound above a true distance.
    fn padded(centre: [f64; 3], normal: [f64; 3], lo: f64, hi: f64, radius: f64) -> Disc {
        let pad = 1e-12 * (radius + hi.abs() + lo.abs() + centre.map(f64::abs).iter().sum::<f64>());
        Disc {
            centre,
            normal,
            lo: lo - pad,
            hi: hi + pad,
            radius: radius + pad,
        }
    }

    /// A disc holding both `a` and `b` (each child's cylinder mapped into a frame between
    /// their normals; [`Disc::NONE`] if either is, or the normals cancel). A child's point is
    /// `c + h·n + u` with `h ∈ [lo, hi]`, `u ⊥ n`, `|u| ≤ radius`; against the new normal `N`
    /// (the angle θ to `n`), `h·n` adds `h·cos θ` along `N` and `|h|·sin θ` across, and `u` at
    /// most `radius·sin θ` along and `radius` across.
    fn merge(a: &Disc, b: &Disc) -> Disc {
        if !(a.radius.is_finite() && b.radius.is_finite()) {
            return Disc::NONE;
        }
        // Weighted by the children's size, a proxy for their area.
        let (wa, wb) = (a.radius * a.radius + 1e-300, b.radius * b.radius + 1e-300);
        let normal = add(scale(a.normal, wa), scale(b.normal, wb));
        let length = dot(normal, normal).sqrt();
        if !(length > 1e-9 * (wa + wb) && length.is_finite()) {
            return Disc::NONE;
        }
        let normal = scale(normal, 1.0 / length);
        let centre = scale(add(a.centre, b.centre), 0.5);
        let (mut lo, mut hi, mut radius) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
        for d in [a, b] {
            let cos = dot(normal, d.normal).clamp(-1.0, 1.0);
            let sin = larger(1.0 - cos * cos, 0.0).sqrt();
            let x = sub(d.centre, centre);
            let base = dot(x, normal);
            let (h0, h1) = (d.lo * cos, d.hi * cos);
            lo = smaller(base + smaller(h0, h1) - d.radius * sin, lo);
            hi = larger(base + larger(h0, h1) + d.radius * sin, hi);
            let across = larger(dot(x, x) - base * base, 0.0).sqrt();
            radius = larger(
                across + larger(d.lo.abs(), d.hi.abs()) * sin + d.radius,
                radius,
            );
        }
        Disc::padded(centre, normal, lo, hi, radius)
    }

    /// Squared lower bound of the distance from `p` to the patch.
    #[inline]
    fn d2(&self, p: [f64; 3]) -> f64 {
        let x = sub(p, self.centre);
        let h = dot(x, self.normal);
        let across2 = dot(x, x) - h * h;
        let up = larger(larger(h - self.hi, self.lo - h), 0.0);
        if across2 <= self.radius * self.radius {
            return up * up;
        }
        let out = across2.sqrt() - self.radius;
        up * up + out * out
    }
}

/// Fit the subtree whose nodes are `nodes` (the tree's nodes from index `offset` on, a whole
/// subtree in pre-order), children before parents. `gathered` receives the positions of
/// `vertices` (the subtree's leaves' vertex runs, from where its first run starts): the
/// scattered reads first, in one loop whose iterations do not wait on each other (the
/// processor keeps many loads in flight), then the fits over contiguous copies: fitting
/// while gathering left each leaf's arithmetic waiting on its loads.
fn fit_subtree(
    nodes: &mut [Node],
    offset: usize,
    positions: &[[f64; 3]],
    runs: &[[u32; 2]],
    vertices: &[u32],
    corners: &[[u8; 3]],
    gathered: &mut [[f64; 3]],
) {
    for (g, &v) in gathered.iter_mut().zip(vertices) {
        *g = positions[v as usize];
    }
    let gathered = &*gathered;
    // Where this subtree's gathered copy starts among all the leaves' runs.
    let first = (offset..offset + nodes.len())
        .find(|&i| nodes[i - offset].count > 0)
        .map_or(0, |i| runs[i][0] as usize);
    for i in (0..nodes.len()).rev() {
        let node = nodes[i];
        let (min, max, disc) = if node.count > 0 {
            let s = node.start as usize;
            let [a, b] = runs[offset + i].map(|x| x as usize - first);
            leaf_fit(&gathered[a..b], &corners[s..s + node.count as usize])
        } else {
            merged(&nodes[i + 1], &nodes[node.start as usize - offset])
        };
        let n = &mut nodes[i];
        (n.min, n.max, n.disc) = (min, max, disc);
    }
}

/// An inner node's box and disc from its children's.
#[inline(always)]
fn merged(l: &Node, r: &Node) -> ([f64; 3], [f64; 3], Disc) {
    (
        [
            smaller(r.min[0], l.min[0]),
            smaller(r.min[1], l.min[1]),
            smaller(r.min[2], l.min[2]),
        ],
        [
            larger(r.max[0], l.max[0]),
            larger(r.max[1], l.max[1]),
            larger(r.max[2], l.max[2]),
        ],
        Disc::merge(&l.disc, &r.disc),
    )
}

/// A leaf's box and disc from the positions of its distinct vertices ([`Leaves`]):
/// the box and the disc's slab and radius are extremes over the vertices, the disc's normal
/// and centre the same area-weighted normal and corner mean as [`Disc::fit`]'s.
fn leaf_fit(local: &[[f64; 3]], corners: &[[u8; 3]]) -> ([f64; 3], [f64; 3], Disc) {
    let (mut min, mut max) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in local {
        for k in 0..3 {
            min[k] = smaller(p[k], min[k]);
            max[k] = larger(p[k], max[k]);
        }
    }
    let (mut normal, mut centre) = ([0.0; 3], [0.0; 3]);
    for c in corners {
        let [a, b, c] = c.map(|k| local.get(usize::from(k)).copied().unwrap_or([f64::NAN; 3]));
        normal = add(normal, cross(sub(b, a), sub(c, a)));
        centre = add(add(centre, a), add(b, c));
    }
    let length = dot(normal, normal).sqrt();
    if !(length > 0.0 && length.is_finite()) {
        return (min, max, Disc::NONE);
    }
    let (normal, centre) = (
        scale(normal, 1.0 / length),
        scale(centre, 1.0 / (3 * corners.len()) as f64),
    );
    let (mut lo, mut hi, mut r2) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
    for p in local {
        let x = sub(*p, centre);
        let h = dot(x, normal);
        lo = smaller(h, lo);
        hi = larger(h, hi);
        r2 = larger(dot(x, x) - h * h, r2);
    }
    (
        min,
        max,
        Disc::padded(centre, normal, lo, hi, larger(r2, 0.0).sqrt()),
    )
}

/// Box of the listed triangles' vertices.
fn bounds(positions: &[[f64; 3]], triangles: &[[usize; 3]], faces: &[u32]) -> ([f64; 3], [f64; 3]) {
    let (mut min, mut max) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for &f in faces {
        for &v in &triangles[f as usize] {
            let p = positions[v];
            for k in 0..3 {
                min[k] = min[k].min(p[k]);
                max[k] = max[k].max(p[k]);
            }
        }
    }
    (min, max)
}

/// The smaller of `a` and `b`, `b` where either is NaN: one compare and select, without
/// `f64::min`'s care for NaN (the bounds of a query and the fits of a refit cost mostly
/// these). Accumulators pass the new value as `a`, so a NaN value leaves them as they were.
#[inline(always)]
fn smaller(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// The larger of `a` and `b`, `b` where either is NaN (as [`smaller`]).
#[inline(always)]
fn larger(a: f64, b: f64) -> f64 {
    if a > b {
        a
    } else {
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::bumpy_sphere;

    /// Squared distance from `p` to the node's box (0 inside).
    fn box_d2(node: &Node, p: [f64; 3]) -> f64 {
        (0..3)
            .map(|k| {
                (node.min[k] - p[k])
                    .max(p[k] - node.max[k])
                    .max(0.0)
                    .powi(2)
            })
            .sum()
    }

    /// The four-wide copy a query walks holds every triangle exactly once, each lane the box
    /// and disc of the binary node it stands for, after a build and after a refit (a lane
    /// left stale or a leaf left out would answer queries wrongly only sometimes).
    #[test]
    fn the_wide_tree_mirrors_the_binary_one() {
        let mesh = bumpy_sphere(3, 0.1);
        let mut bvh = Bvh::new(&mesh.positions, &mesh.triangles);
        let check = |bvh: &Bvh| {
            let mut seen = vec![0u32; mesh.triangles.len()];
            let mut pending = vec![0u32];
            let mut wide_nodes = 0;
            while let Some(w) = pending.pop() {
                wide_nodes += 1;
                let w = &bvh.wide[w as usize];
                for lane in 0..4 {
                    let Some(node) = bvh.nodes.get(w.node[lane] as usize) else {
                        assert_eq!((w.child[lane], w.count[lane]), (u32::MAX, 0));
                        continue;
                    };
                    for k in 0..3 {
                        assert_eq!(w.min[k][lane], node.min[k]);
                        assert_eq!(w.max[k][lane], node.max[k]);
                    }
                    assert_eq!(w.disc[lane].centre, node.disc.centre);
                    assert_eq!(w.disc[lane].radius, node.disc.radius);
                    if w.count[lane] > 0 {
                        assert_eq!((w.child[lane], w.count[lane]), (node.start, node.count));
                        let s = node.start as usize;
                        for &f in &bvh.order[s..s + node.count as usize] {
                            seen[f as usize] += 1;
                        }
                    } else {
                        pending.push(w.child[lane]);
                    }
                }
            }
            assert!(seen.iter().all(|&n| n == 1), "every triangle once");
            assert_eq!(wide_nodes, bvh.wide.len());
            // Four lanes a node: about a third of the binary tree's inner nodes.
            assert!(3 * bvh.wide.len() <= bvh.nodes.len() / 2 + 3);
        };
        check(&bvh);
        bvh.refit(&twisted(&mesh.positions), &mesh.triangles);
        check(&bvh);
    }

    /// A twist about z that grows with height, and a stretch: a smooth deformation for a
    /// tree to be refitted to.
    fn twisted(positions: &[[f64; 3]]) -> Vec<[f64; 3]> {
        positions
            .iter()
            .map(|p| {
                let (s, c) = (0.8 * p[2]).sin_cos();
                [c * p[0] - s * p[1], s * p[0] + c * p[1], 1.3 * p[2]]
            })
            .collect()
    }

    /// The root's two subtrees refitted on two threads give bitwise the tree one thread
    /// gives: every node's box and disc, and the wide copy's lanes.
    #[test]
    fn a_parallel_refit_is_the_sequential_one() {
        let mesh = bumpy_sphere(3, 0.2);
        let mut one = Bvh::new(&mesh.positions, &mesh.triangles);
        let mut two = one.clone();
        let moved = twisted(&mesh.positions);
        one.refit_with(&moved, &mesh.triangles, false);
        two.refit_with(&moved, &mesh.triangles, true);
        assert!(one.nodes.len() > 100);
        let bits = |b: &Bvh| -> Vec<u64> {
            b.nodes
                .iter()
                .flat_map(|n| {
                    let d = &n.disc;
                    n.min
                        .into_iter()
                        .chain(n.max)
                        .chain(d.centre)
                        .chain(d.normal)
                        .chain([d.lo, d.hi, d.radius])
                })
                .chain(
                    b.wide
                        .iter()
                        .flat_map(|w| w.min.into_iter().chain(w.max).flatten()),
                )
                .map(f64::to_bits)
                .collect()
        };
        assert_eq!(bits(&one), bits(&two));
        // And the refit did move the boxes (the comparison is not of two untouched trees).
        let fresh = Bvh::new(&mesh.positions, &mesh.triangles);
        assert_ne!(bits(&one), bits(&fresh));
    }

    /// The three Voronoi regions of each kind give the expected nearest point.
    #[test]
    fn closest_points_on_a_right_triangle() {
        let (a, b, c) = ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        let cases = [
            ([0.25, 0.25, 2.0], [0.25, 0.25, 0.0]), // face
            ([-1.0, -1.0, 0.5], a),                 // vertex a
            ([2.0, -0.5, 0.0], b),                  // vertex b
            ([-0.5, 3.0, 1.0], c),                  // vertex c
            ([0.5, -1.0, 0.0], [0.5, 0.0, 0.0]),    // edge ab
            ([-1.0, 0.5, 0.0], [0.0, 0.5, 0.0]),    // edge ac
            ([1.0, 1.0, -1.0], [0.5, 0.5, 0.0]),    // edge bc
        ];
        for (p, expected) in cases {
            let q = closest_point_on_triangle(p, a, b, c);
            assert!(dist2(q, expected) < 1e-24, "{p:?}: {q:?} vs {expected:?}");
        }
        // Degenerate: all three corners on a line still give a point of the segment.
        let q = closest_point_on_triangle([0.5, 1.0, 0.0], a, b, [2.0, 0.0, 0.0]);
        assert!(dist2(q, [0.5, 0.0, 0.0]) < 1e-24, "{q:?}");
    }

    /// The tree's nearest triangle is the brute-force nearest, with and without a hint, and
    /// after a refit of a deformed surface (and a rebuild for a large one).
    #[test]
    fn nearest_matches_a_linear_scan() {
        let mesh = bumpy_sphere(3, 0.2);
        let mut bvh = Bvh::new(&mesh.positions, &mesh.triangles);
        let scan = |positions: &[[f64; 3]], p: [f64; 3]| {
            mesh.triangles
                .iter()
                .map(|t| {
                    dist2(
                        p,
                        closest_point_on_triangle(
                            p,
                            positions[t[0]],
                            positions[t[1]],
                            positions[t[2]],
                        ),
                    )
                })
                .fold(f64::INFINITY, f64::min)
        };
        let probes: Vec<[f64; 3]> = (0..200)
            .map(|i| {
                let t = i as f64 * 0.37;
                let r = 0.3 + 1.5 * ((i * 7919) % 100) as f64 / 100.0;
                [
                    r * t.cos() * (0.5 * t).sin(),
                    r * t.sin() * (0.5 * t).sin(),
                    r * (0.5 * t).cos(),
                ]
            })
            .collect();
        let check = |bvh: &Bvh, positions: &[[f64; 3]]| {
            for (i, &p) in probes.iter().enumerate() {
                let want = scan(positions, p);
                for hint in [None, Some(i % mesh.triangles.len())] {
                    let (_, got) = bvh
                        .nearest(positions, &mesh.triangles, p, hint)
                        .expect("non-empty");
                    assert!(
                        (got - want).abs() <= 1e-12 * want.max(1e-12),
                        "{p:?}: {got} vs {want}"
                    );
                }
            }
        };
        check(&bvh, &mesh.positions);
        let twisted = twisted(&mesh.positions);
        bvh.refit(&twisted, &mesh.triangles);
        check(&bvh, &twisted);
    }

    /// A clone shares its tree's layout, and with it every per-node value over vertices,
    /// through refits that keep the grouping; a refit that rebuilds (the vertices scrambled,
    /// every box as big as the mesh) takes a layout of its own, as any other build does.
    #[test]
    fn a_tree_keeps_its_layout_until_it_is_rebuilt() {
        let mesh = bumpy_sphere(3, 0.2);
        let input = Bvh::new(&mesh.positions, &mesh.triangles);
        let mut current = input.clone();
        let twisted = twisted(&mesh.positions);
        current.refit(&twisted, &mesh.triangles);
        assert!(current.same_layout(&input));
        let values: Vec<f64> = (0..mesh.positions.len())
            .map(|v| ((v * 7919) % 101) as f64)
            .collect();
        let (mut a, mut b) = (Vec::new(), Vec::new());
        input.max_per_node(&values, &mut a);
        current.max_per_node(&values, &mut b);
        assert_eq!(a, b);
        assert!(!Bvh::new(&mesh.positions, &mesh.triangles).same_layout(&input));
        let n = mesh.positions.len();
        let scrambled: Vec<[f64; 3]> = (0..n).map(|v| mesh.positions[(v * 7919) % n]).collect();
        current.refit(&scrambled, &mesh.triangles);
        assert!(
            !current.same_layout(&input),
            "a scrambled surface is rebuilt"
        );
    }

    /// Every node's disc bounds the distance to its triangles from below, on the built tree
    /// (each disc fitted to its triangles) and after a refit of a deformed surface (inner
    /// discs merged from their children's), for probes on, near and far from the surface.
    #[test]
    fn discs_never_exceed_the_distance_to_their_triangles() {
        let mesh = bumpy_sphere(3, 0.2);
        let mut bvh = Bvh::new(&mesh.positions, &mesh.triangles);
        let probes: Vec<[f64; 3]> = (0..60)
            .map(|i| {
                let t = i as f64 * 0.53;
                let r = 0.8 + 3.0 * ((i * 7919) % 100) as f64 / 100.0;
                [
                    r * t.cos() * (0.4 * t).sin(),
                    r * t.sin() * (0.4 * t).sin(),
                    r * (0.4 * t).cos(),
                ]
            })
            // On the surface and just off it, where a disc's slab is thinnest.
            .chain(mesh.positions.iter().step_by(7).copied())
            .chain(mesh.positions.iter().step_by(5).map(|&p| scale(p, 1.03)))
            .chain(mesh.positions.iter().step_by(5).map(|&p| scale(p, 0.97)))
            .collect();
        let check = |bvh: &Bvh, positions: &[[f64; 3]]| {
            let mut pruning = 0;
            // Each node's triangles: a leaf's own, an inner node's its children's (children
            // follow their parent in pre-order, so walk back to front).
            let mut below: Vec<Vec<u32>> = vec![Vec::new(); bvh.nodes.len()];
            for i in (0..bvh.nodes.len()).rev() {
                let node = bvh.nodes[i];
                below[i] = if node.count > 0 {
                    let s = node.start as usize;
                    bvh.order[s..s + node.count as usize].to_vec()
                } else {
                    [below[i + 1].clone(), below[node.start as usize].clone()].concat()
                };
            }
            for (i, faces) in below.iter().enumerate() {
                let disc = bvh.nodes[i].disc;
                for &p in &probes {
                    let truth = faces
                        .iter()
                        .map(|&f| {
                            let [a, b, c] = mesh.triangles[f as usize].map(|v| positions[v]);
                            dist2(p, closest_point_on_triangle(p, a, b, c))
                        })
                        .fold(f64::INFINITY, f64::min);
                    let bound = disc.d2(p);
                    assert!(
                        bound <= truth * (1.0 + 1e-12),
                        "node {i}: {bound} > {truth}"
                    );
                    if bound > box_d2(&bvh.nodes[i], p) {
                        pruning += 1;
                    }
                }
            }
            // And it is tighter than the box somewhere (else it would prune nothing).
            assert!(
                pruning > probes.len(),
                "discs tighter than boxes {pruning} times"
            );
        };
        check(&bvh, &mesh.positions);
        let twisted = twisted(&mesh.positions);
        bvh.refit(&twisted, &mesh.triangles);
        check(&bvh, &twisted);
    }

    /// Within a slack, the face found is never nearer than the nearest (it is a real face)
    /// and never further than `1 + slack` times it, from every hint, for probes near and far;
    /// asked to stop at a distance, the face found is within it.
    #[test]
    fn nearest_within_a_slack_stays_within_it() {
        let mesh = bumpy_sphere(3, 0.2);
        let bvh = Bvh::new(&mesh.positions, &mesh.triangles);
        for i in 0..300 {
            let t = i as f64 * 0.61;
            let r = 0.1 + 4.0 * ((i * 7919) % 100) as f64 / 100.0;
            let p = [
                r * t.cos() * (0.3 * t).sin(),
                r * t.sin() * (0.3 * t).sin(),
                r * (0.3 * t).cos(),
            ];
            let want = mesh
                .triangles
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|v| mesh.positions[v]);
                    dist2(p, closest_point_on_triangle(p, a, b, c))
                })
                .fold(f64::INFINITY, f64::min)
                .sqrt();
            for slack in [0.005, 0.05] {
                for hint in [None, Some((i * 37) % mesh.triangles.len())] {
                    let (f, d2) = bvh
                        .nearest_within(&mesh.positions, &mesh.triangles, p, hint, slack)
                        .expect("non-empty");
                    let [a, b, c] = mesh.triangles[f].map(|v| mesh.positions[v]);
                    let d = dist2(p, closest_point_on_triangle(p, a, b, c)).sqrt();
                    assert!(
                        (d * d - d2).abs() <= 1e-12 * d2.max(1e-12),
                        "{p:?}: face {f}"
                    );
                    assert!(d >= want * (1.0 - 1e-12), "{p:?}: {d} below {want}");
                    assert!(d <= want * (1.0 + slack) + 1e-12, "{p:?}: {d} vs {want}");
                    // Asked only for some face within 1.5 times the nearest distance: one
                    // that is, named with its own distance.
                    let enough = (1.5 * want).powi(2);
                    let (f, d2) = bvh
                        .nearest_until(&mesh.positions, &mesh.triangles, p, hint, slack, enough)
                        .expect("non-empty");
                    let [a, b, c] = mesh.triangles[f].map(|v| mesh.positions[v]);
                    let e2 = dist2(p, closest_point_on_triangle(p, a, b, c));
                    assert!((e2 - d2).abs() <= 1e-12 * d2.max(1e-12), "{p:?}: face {f}");
                    assert!(d2 <= enough, "{p:?}: {d2} above {enough}");
                }
            }
        }
    }
}
