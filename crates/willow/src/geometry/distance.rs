//! How far a surface moved from the input: nearest points on triangles through a bounding
//! volume hierarchy, and the two-sided sampled distance the flows report
//! (`StepMetrics::deviation_max`, `deviation_mean`).
//!
//! - [`closest_point_on_triangle`]: the exact nearest point of one triangle (Ericson,
//!   *Real-Time Collision Detection*, §5.1.5: Voronoi regions of the vertices, edges, face).
//! - [`Bvh`]: a binary tree of axis-aligned boxes over a mesh's triangles, built once
//!   (median split on the longest axis of the centroids) and *refitted* when the vertices
//!   move: connectivity never changes during a flow, so only the boxes need refilling. A tree
//!   whose refitted boxes have grown much looser than a fresh build's is rebuilt.
//! - [`Deviation`]: samples on each surface (every vertex, edge midpoint and face centroid)
//!   and their distance to the other surface's triangles.
//!
//! What is measured: with `S_A` the samples of surface A, `d(x, B)` the distance from x to
//! the nearest point of B's triangles, `deviation_max = max(max_{x∈S_cur} d(x, input),
//! max_{x∈S_in} d(x, current))` (a sampled symmetric Hausdorff distance, exact over every
//! sample), and `deviation_mean` the mean of the two one-sided area-weighted means (over
//! every sample up to [`MEAN_SAMPLES`] per side, a strided subset above: see [`Deviation`]). The weights are the 7-point triangle
//! rule (vertices 1/20, edge midpoints 2/15, centroid 9/20 of each incident face's area;
//! exact for cubic integrands), so a one-sided mean approximates `∫ d(x, B) dA / A`.

use super::vec3::{add, dot, scale, sub};
use crate::mesh::topology::Topology;

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

#[inline]
fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = sub(a, b);
    dot(d, d)
}

/// Triangles per leaf: a leaf test costs ~4 box tests, so small leaves keep the tree shallow
/// without making the box tests dominate.
const LEAF_SIZE: usize = 4;
/// Deepest possible traversal stack: a median split halves the triangles at every level,
/// so depth ≤ log2(triangles) + 1, and 64 covers any mesh that fits in memory.
const STACK: usize = 64;
/// A refitted tree is rebuilt when the summed surface area of its boxes exceeds this multiple
/// of a fresh build's: refitting keeps the build's grouping, which gets loose when the surface
/// deforms a lot (spot → sphere), and a loose tree visits more boxes per query.
const REBUILD_GROWTH: f64 = 2.0;

#[derive(Clone, Copy, Debug)]
struct Node {
    min: [f64; 3],
    max: [f64; 3],
    /// Leaf: first index into `Bvh::order`; inner: index of the right child (the left
    /// child is the next node: the nodes are stored in depth-first pre-order).
    start: u32,
    /// Triangles in a leaf; 0 for an inner node.
    count: u32,
}

/// A bounding volume hierarchy over the triangles of one mesh (module docs).
#[derive(Clone, Debug)]
pub struct Bvh {
    nodes: Vec<Node>,
    /// Triangle indices, grouped by leaf.
    order: Vec<u32>,
    /// Summed surface area of the boxes right after the last build.
    built_box_area: f64,
}

impl Bvh {
    /// Build the tree of `triangles` at `positions` (indices must be in range: a validated
    /// [`crate::mesh::Mesh`]). An empty mesh gives an empty tree whose queries find nothing.
    pub fn new(positions: &[[f64; 3]], triangles: &[[usize; 3]]) -> Self {
        let mut bvh = Bvh {
            nodes: Vec::with_capacity(2 * triangles.len().div_ceil(LEAF_SIZE)),
            order: (0..triangles.len() as u32).collect(),
            built_box_area: 0.0,
        };
        bvh.build(positions, triangles);
        bvh
    }

    fn build(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]]) {
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
            if end - start <= LEAF_SIZE {
                self.nodes.push(Node {
                    min,
                    max,
                    start: start as u32,
                    count: (end - start) as u32,
                });
                continue;
            }
            self.nodes.push(Node {
                min,
                max,
                start: 0,
                count: 0,
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
    }

    /// Refill every box after the vertices moved (children before parents: reverse
    /// pre-order), and rebuild when the refitted boxes got much looser than a fresh build's
    /// (twice as loose, by their summed surface area).
    pub fn refit(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]]) {
        for i in (0..self.nodes.len()).rev() {
            let node = self.nodes[i];
            let (min, max) = if node.count > 0 {
                let s = node.start as usize;
                bounds(
                    positions,
                    triangles,
                    &self.order[s..s + node.count as usize],
                )
            } else {
                let (l, r) = (self.nodes[i + 1], self.nodes[node.start as usize]);
                (
                    [
                        l.min[0].min(r.min[0]),
                        l.min[1].min(r.min[1]),
                        l.min[2].min(r.min[2]),
                    ],
                    [
                        l.max[0].max(r.max[0]),
                        l.max[1].max(r.max[1]),
                        l.max[2].max(r.max[2]),
                    ],
                )
            };
            self.nodes[i].min = min;
            self.nodes[i].max = max;
        }
        if self.box_area() > REBUILD_GROWTH * self.built_box_area {
            self.build(positions, triangles);
        }
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
        let root = self.nodes.first()?;
        let triangle_d2 = |f: usize| {
            let t = triangles[f];
            dist2(
                p,
                closest_point_on_triangle(p, positions[t[0]], positions[t[1]], positions[t[2]]),
            )
        };
        let mut best = match hint {
            Some(f) if f < triangles.len() => (f, triangle_d2(f)),
            _ => (usize::MAX, f64::INFINITY),
        };
        let mut stack = [0u32; STACK];
        let mut top = 0usize;
        if box_d2(root, p) < best.1 {
            stack[0] = 0;
            top = 1;
        }
        while top > 0 {
            top -= 1;
            let node = self.nodes[stack[top] as usize];
            if box_d2(&node, p) >= best.1 {
                continue;
            }
            if node.count > 0 {
                let s = node.start as usize;
                for &f in &self.order[s..s + node.count as usize] {
                    let d2 = triangle_d2(f as usize);
                    if d2 < best.1 {
                        best = (f as usize, d2);
                    }
                }
                continue;
            }
            let (l, r) = (stack[top] + 1, node.start);
            let (dl, dr) = (
                box_d2(&self.nodes[l as usize], p),
                box_d2(&self.nodes[r as usize], p),
            );
            // Nearer child on top, so it is opened first and tightens the bound.
            let (near, dn, far, df) = if dl <= dr {
                (l, dl, r, dr)
            } else {
                (r, dr, l, dl)
            };
            if df < best.1 && top < STACK {
                stack[top] = far;
                top += 1;
            }
            if dn < best.1 && top < STACK {
                stack[top] = near;
                top += 1;
            }
        }
        (best.0 != usize::MAX).then_some(best)
    }
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

/// Squared distance from `p` to the node's box (0 inside).
#[inline]
fn box_d2(node: &Node, p: [f64; 3]) -> f64 {
    let mut d2 = 0.0;
    for k in 0..3 {
        let d = (node.min[k] - p[k]).max(p[k] - node.max[k]).max(0.0);
        d2 += d * d;
    }
    d2
}

/// 7-point rule weights (module docs), as fractions of a face's area: each of its corners,
/// each of its edge midpoints, its centroid. 3/20 + 6/15 + 9/20 = 1.
pub const VERTEX_WEIGHT: f64 = 1.0 / 20.0;
pub const EDGE_WEIGHT: f64 = 2.0 / 15.0;
pub const CENTROID_WEIGHT: f64 = 9.0 / 20.0;

/// The sample points of a surface, in this order: every vertex, every edge midpoint (edges
/// in the order of `edges`), every face centroid. With a face each lies on (the warm start
/// of its query on the other surface, which has the same connectivity).
struct SamplePlan {
    edges: Vec<[usize; 2]>,
    face_edges: Vec<[usize; 3]>,
    hints: Vec<u32>,
}

impl SamplePlan {
    fn new(vertex_count: usize, triangles: &[[usize; 3]], topology: &Topology) -> Self {
        let mut hints = vec![0u32; vertex_count + topology.edges.len() + triangles.len()];
        for (f, t) in triangles.iter().enumerate().rev() {
            for &v in t {
                hints[v] = f as u32;
            }
        }
        for (e, faces) in topology.edge_faces.iter().enumerate() {
            hints[vertex_count + e] = faces[0].unwrap_or(0) as u32;
        }
        let first_face = vertex_count + topology.edges.len();
        for (f, h) in hints[first_face..].iter_mut().enumerate() {
            *h = f as u32;
        }
        SamplePlan {
            edges: topology.edges.clone(),
            face_edges: topology.face_edges.clone(),
            hints,
        }
    }

    fn len(&self) -> usize {
        self.hints.len()
    }

    fn points_into(&self, positions: &[[f64; 3]], triangles: &[[usize; 3]], out: &mut [[f64; 3]]) {
        let (nv, ne) = (positions.len(), self.edges.len());
        out[..nv].copy_from_slice(positions);
        for (o, &[a, b]) in out[nv..nv + ne].iter_mut().zip(&self.edges) {
            *o = scale(add(positions[a], positions[b]), 0.5);
        }
        for (o, t) in out[nv + ne..].iter_mut().zip(triangles) {
            *o = scale(
                add(add(positions[t[0]], positions[t[1]]), positions[t[2]]),
                1.0 / 3.0,
            );
        }
    }

    fn weights_into(&self, triangles: &[[usize; 3]], face_areas: &[f64], out: &mut [f64]) {
        let nv = self.len() - self.edges.len() - triangles.len();
        let ne = self.edges.len();
        out.fill(0.0);
        for ((t, es), &a) in triangles.iter().zip(&self.face_edges).zip(face_areas) {
            for &v in t {
                out[v] += VERTEX_WEIGHT * a;
            }
            for &e in es {
                out[nv + e] += EDGE_WEIGHT * a;
            }
        }
        for (o, &a) in out[nv + ne..].iter_mut().zip(face_areas) {
            *o = CENTROID_WEIGHT * a;
        }
    }
}

/// Samples per side whose exact distance enters the mean: all of them up to this many,
/// else an evenly strided subset of about this many (see [`Deviation`]). An exact query
/// costs about the number of triangles within the distance's slack of the sample (tens of
/// them once the surface moved a few edge lengths: measured 5 µs per query on nefertiti
/// after one step at τ 0.5), so every sample of a 100k-triangle mesh (600k queries) would
/// cost several conformal steps; 2048 per side keep the mean's sampling error near 1%.
pub const MEAN_SAMPLES: usize = 2048;
/// Steps of the greedy walk over face neighbours that improves a query's starting face.
const WALK_STEPS: usize = 8;

/// A face near `p`: walk from `face` to the edge neighbour nearest to `p` while that gets
/// nearer (at most [`WALK_STEPS`] steps). Only a starting point for an exact query, which
/// then opens fewer boxes: the surface may have slid along itself since the input, so the
/// same face on the other surface can be far.
fn walk_down(
    p: [f64; 3],
    face: usize,
    neighbours: &[[u32; 3]],
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
) -> usize {
    let d2_of = |f: usize| {
        let t = triangles[f];
        dist2(
            p,
            closest_point_on_triangle(p, positions[t[0]], positions[t[1]], positions[t[2]]),
        )
    };
    let mut best = (face, d2_of(face));
    for _ in 0..WALK_STEPS {
        let here = best.0;
        for &g in &neighbours[here] {
            if g != u32::MAX {
                let d2 = d2_of(g as usize);
                if d2 < best.1 {
                    best = (g as usize, d2);
                }
            }
        }
        if best.0 == here {
            break;
        }
    }
    best.0
}

/// One surface's side of the measure: its samples, their weights, its tree, and the other
/// surface to measure against.
struct Side<'a> {
    samples: &'a [[f64; 3]],
    weights: &'a [f64],
    hints: &'a [u32],
    /// This surface (its samples lie in its tree's boxes).
    own: &'a Bvh,
    own_positions: &'a [[f64; 3]],
    /// The other surface.
    other: &'a Bvh,
    other_positions: &'a [[f64; 3]],
    triangles: &'a [[usize; 3]],
    neighbours: &'a [[u32; 3]],
}

impl Side<'_> {
    fn exact(&self, p: [f64; 3], hint: usize) -> (usize, f64) {
        self.other
            .nearest(self.other_positions, self.triangles, p, Some(hint))
            .map_or((hint, 0.0), |(f, d2)| (f, d2.sqrt()))
    }

    /// The exact largest and weighted mean distance over the strided subset of the
    /// [`Deviation`] docs.
    fn subset(&self) -> (f64, f64) {
        let n = self.samples.len();
        let stride = n.div_ceil(MEAN_SAMPLES).max(1);
        let (mut max, mut sum, mut total) = (0.0f64, 0.0, 0.0);
        for i in (0..n).step_by(stride) {
            let p = self.samples[i];
            let start = walk_down(
                p,
                self.hints[i] as usize,
                self.neighbours,
                self.other_positions,
                self.triangles,
            );
            let d = self.exact(p, start).1;
            max = max.max(d);
            sum += self.weights[i] * d;
            total += self.weights[i];
        }
        (max, if total > 0.0 { sum / total } else { 0.0 })
    }

    /// The largest distance over every sample of this side, exactly, given `max`, one
    /// already reached. Top-down through this surface's tree: every sample of a node lies
    /// in its box (vertices of its triangles, and midpoints and centroids between them), and
    /// the distance to a surface is 1-Lipschitz, so no sample of a node is further than
    /// `d(centre) + half diagonal`; a node whose bound is not above `max` is skipped whole.
    /// Only the leaves near the largest distance have their samples measured.
    fn settle_max(&self, mut max: f64, stack: &mut Vec<(u32, u32)>) -> f64 {
        if self.own.nodes.is_empty() {
            return max;
        }
        stack.clear();
        stack.push((0, self.own.order[0]));
        while let Some((index, hint)) = stack.pop() {
            let node = self.own.nodes[index as usize];
            let centre = scale(add(node.min, node.max), 0.5);
            let radius = 0.5 * dist2(node.max, node.min).sqrt();
            if radius > max && node.count == 0 {
                // No distance can cull a box this big: open it without a query (from the
                // centre of a big box deep inside a closed surface, a query would open
                // most of the other tree).
                stack.push((node.start, hint));
                stack.push((index + 1, hint));
                continue;
            }
            let (face, d) = self.exact(centre, hint as usize);
            if d + radius <= max {
                continue;
            }
            if node.count == 0 {
                stack.push((node.start, face as u32));
                stack.push((index + 1, face as u32));
                continue;
            }
            let s = node.start as usize;
            for &f in &self.own.order[s..s + node.count as usize] {
                let t = self.triangles[f as usize];
                let [a, b, c] = t.map(|v| self.own_positions[v]);
                // The same arithmetic as `SamplePlan::points_into`, so the same points.
                let points = [
                    a,
                    b,
                    c,
                    scale(add(a, b), 0.5),
                    scale(add(b, c), 0.5),
                    scale(add(c, a), 0.5),
                    scale(add(add(a, b), c), 1.0 / 3.0),
                ];
                for p in points {
                    if dist2(p, centre).sqrt() + d <= max {
                        continue;
                    }
                    max = max.max(self.exact(p, face).1);
                }
            }
        }
        max
    }
}

/// The two-sided sampled distance between the input surface and a moving one with the same
/// connectivity (module docs). The input's tree and samples are built once; the current
/// surface's tree is refitted every call.
///
/// The maximum is exact over every sample. The mean is exact over every sample up to
/// [`MEAN_SAMPLES`] per side, and over every k-th sample (k = ⌈samples / MEAN_SAMPLES⌉,
/// weights as for all) above that: the cost of exact nearest points grows with how far the
/// surface moved, and the mean, unlike the max, does not need every sample.
pub struct Deviation {
    plan: SamplePlan,
    /// Per face, the faces across its edges (`u32::MAX` across a boundary edge).
    neighbours: Vec<[u32; 3]>,
    input_positions: Vec<[f64; 3]>,
    input_bvh: Bvh,
    input_samples: Vec<[f64; 3]>,
    input_weights: Vec<f64>,
    current_bvh: Bvh,
    samples: Vec<[f64; 3]>,
    weights: Vec<f64>,
    stack: Vec<(u32, u32)>,
}

impl Deviation {
    /// `face_areas` are the input's (one per triangle).
    pub fn new(
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        topology: &Topology,
        face_areas: &[f64],
    ) -> Self {
        let plan = SamplePlan::new(positions.len(), triangles, topology);
        let mut input_samples = vec![[0.0; 3]; plan.len()];
        let mut input_weights = vec![0.0; plan.len()];
        plan.points_into(positions, triangles, &mut input_samples);
        plan.weights_into(triangles, face_areas, &mut input_weights);
        let input_bvh = Bvh::new(positions, triangles);
        let neighbours = topology
            .face_edges
            .iter()
            .enumerate()
            .map(|(f, edges)| {
                edges.map(|e| {
                    match topology.edge_faces[e] {
                        [Some(a), Some(b)] => {
                            if a == f {
                                b
                            } else {
                                a
                            }
                        }
                        _ => usize::MAX,
                    }
                    .try_into()
                    .unwrap_or(u32::MAX)
                })
            })
            .collect();
        Deviation {
            current_bvh: input_bvh.clone(),
            samples: input_samples.clone(),
            weights: input_weights.clone(),
            input_positions: positions.to_vec(),
            input_bvh,
            input_samples,
            input_weights,
            plan,
            neighbours,
            stack: Vec::new(),
        }
    }

    /// `(deviation_max, deviation_mean)` of the surface at `positions` (whose face areas are
    /// `face_areas`) against the input: see the module docs for exactly what is measured.
    pub fn measure(
        &mut self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        face_areas: &[f64],
    ) -> (f64, f64) {
        self.plan
            .points_into(positions, triangles, &mut self.samples);
        self.plan
            .weights_into(triangles, face_areas, &mut self.weights);
        self.current_bvh.refit(positions, triangles);
        let out = Side {
            samples: &self.samples,
            weights: &self.weights,
            hints: &self.plan.hints,
            own: &self.current_bvh,
            own_positions: positions,
            other: &self.input_bvh,
            other_positions: &self.input_positions,
            triangles,
            neighbours: &self.neighbours,
        };
        let back = Side {
            samples: &self.input_samples,
            weights: &self.input_weights,
            hints: &self.plan.hints,
            own: &self.input_bvh,
            own_positions: &self.input_positions,
            other: &self.current_bvh,
            other_positions: positions,
            triangles,
            neighbours: &self.neighbours,
        };
        let (max_out, mean_out) = out.subset();
        let (max_in, mean_in) = back.subset();
        // Both sides' exact distances so far bound the max below before either settles it,
        // so the side with the smaller distances mostly has nothing left to check.
        let max = back.settle_max(max_out.max(max_in), &mut self.stack);
        let max = out.settle_max(max, &mut self.stack);
        (max, 0.5 * (mean_out + mean_in))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::bumpy_sphere;

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
        // A twist about z grows with height: a smooth deformation, refitted.
        let twisted: Vec<[f64; 3]> = mesh
            .positions
            .iter()
            .map(|p| {
                let (s, c) = (0.8 * p[2]).sin_cos();
                [c * p[0] - s * p[1], s * p[0] + c * p[1], 1.3 * p[2]]
            })
            .collect();
        bvh.refit(&twisted, &mesh.triangles);
        check(&bvh, &twisted);
    }
}
