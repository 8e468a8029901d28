//! Nearest points on triangles through a bounding volume hierarchy (used by
//! [`super::distance`]).
//!
//! - [`closest_point_on_triangle`]: the exact nearest point of one triangle (Ericson,
//!   *Real-Time Collision Detection*, §5.1.5: Voronoi regions of the vertices, edges, face).
//! - [`Bvh`]: a binary tree of axis-aligned boxes over a mesh's triangles, built once
//!   (median split on the longest axis of the centroids) and *refitted* when the vertices
//!   move: connectivity never changes during a flow, so only the boxes need refilling. A tree
//!   whose refitted boxes have grown much looser than a fresh build's is rebuilt.

use super::vec3::{add, dot, scale, sub};

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
pub(crate) fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
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
pub(crate) struct Node {
    pub(crate) min: [f64; 3],
    pub(crate) max: [f64; 3],
    /// Leaf: first index into `Bvh::order`; inner: index of the right child (the left
    /// child is the next node: the nodes are stored in depth-first pre-order).
    pub(crate) start: u32,
    /// Triangles in a leaf; 0 for an inner node.
    pub(crate) count: u32,
}

/// A bounding volume hierarchy over the triangles of one mesh (module docs).
#[derive(Clone, Debug)]
pub struct Bvh {
    pub(crate) nodes: Vec<Node>,
    /// Triangle indices, grouped by leaf.
    pub(crate) order: Vec<u32>,
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
        let root = self.nodes.first()?;
        let grow = (1.0 + slack) * (1.0 + slack);
        let pruned_d2 = |node: &Node, p: [f64; 3]| grow * box_d2(node, p);
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
        if pruned_d2(root, p) < best.1 {
            stack[0] = 0;
            top = 1;
        }
        while top > 0 && best.1 > enough {
            top -= 1;
            let node = self.nodes[stack[top] as usize];
            if pruned_d2(&node, p) >= best.1 {
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
                pruned_d2(&self.nodes[l as usize], p),
                pruned_d2(&self.nodes[r as usize], p),
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
