//! How far a surface moved from the input: nearest points on triangles through a bounding
//! volume hierarchy, and the two-sided sampled distance the flows report
//! (`StepMetrics::deviation_max`, `deviation_mean`).
//!
//! - [`closest_point_on_triangle`] and [`Bvh`] (in [`super::bvh`]): the exact nearest point of
//!   one triangle, and a tree of boxes over a mesh's triangles, refitted as the surface moves.
//! - [`Deviation`]: samples on each surface (every vertex, edge midpoint and face centroid)
//!   and their distance to the other surface's triangles.
//!
//! What is measured: with `S_A` the samples of surface A, `d(x, B)` the distance from x to
//! the nearest point of B's triangles, `deviation_max = max(max_{x∈S_cur} d(x, input),
//! max_{x∈S_in} d(x, current))` (a sampled symmetric Hausdorff distance, exact over every
//! sample), and `deviation_mean` the mean of the two one-sided area-weighted means (every
//! sample up to [`MEAN_SAMPLES`] per side; above, a stratified estimate within
//! [`MEAN_ACCURACY`] as its stated bound [`Deviation::mean_bound`] says: see
//! [`super::stratified`]).
//! The weights are the 7-point triangle rule (vertices 1/20, edge midpoints 2/15, centroid 9/20 of each incident face's area;
//! exact for cubic integrands), so a one-sided mean approximates `∫ d(x, B) dA / A`.

pub use super::bvh::{closest_point_on_triangle, Bvh};
use super::bvh::{dist2, triangle_d2};
use super::stratified::{estimate_pair, Strata, FIRST_SAMPLES, STRATA, STRATA_MIN};
use super::vec3::{add, scale};
use crate::mesh::topology::Topology;
use crate::parallel::join;

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

    /// Per face, the samples of its seven rule points ([`rule_points`]).
    fn face_samples(&self, triangles: &[[usize; 3]]) -> Vec<[u32; 7]> {
        let (nv, ne) = (
            self.len() - self.edges.len() - triangles.len(),
            self.edges.len(),
        );
        (0..triangles.len())
            .map(|f| rule_points(f, triangles, &self.face_edges, nv, ne).map(|i| i as u32))
            .collect()
    }
}

/// The samples of face `f`'s seven rule points, in the order of [`super::stratified::RULE`]:
/// its corners, its edge midpoints, its centroid (`nv` vertices, `ne` edges).
fn rule_points(
    f: usize,
    triangles: &[[usize; 3]],
    face_edges: &[[usize; 3]],
    nv: usize,
    ne: usize,
) -> [usize; 7] {
    let (t, es) = (triangles[f], face_edges[f]);
    [
        t[0],
        t[1],
        t[2],
        nv + es[0],
        nv + es[1],
        nv + es[2],
        nv + ne + f,
    ]
}

/// Where a side's sample points come from: stored (the input's, computed once) or computed
/// when asked from the current positions (a frame asks for a few thousand of the 300k at
/// 100k triangles; writing them all cost ~1 ms a frame).
#[derive(Clone, Copy)]
enum Points<'a> {
    Stored(&'a [[f64; 3]]),
    Computed {
        positions: &'a [[f64; 3]],
        edges: &'a [[usize; 2]],
        triangles: &'a [[usize; 3]],
    },
}

impl Points<'_> {
    /// Sample `i` (the order of [`SamplePlan`]).
    #[inline]
    fn at(&self, i: usize) -> [f64; 3] {
        match *self {
            Points::Stored(points) => points[i],
            Points::Computed {
                positions,
                edges,
                triangles,
            } => {
                let (nv, ne) = (positions.len(), edges.len());
                if i < nv {
                    positions[i]
                } else if i < nv + ne {
                    let [a, b] = edges[i - nv];
                    scale(add(positions[a], positions[b]), 0.5)
                } else {
                    let t = triangles[i - nv - ne];
                    scale(
                        add(add(positions[t[0]], positions[t[1]]), positions[t[2]]),
                        1.0 / 3.0,
                    )
                }
            }
        }
    }
}

/// Samples per side the mean measures first (two per stratum, [`super::stratified`]); a side
/// with at most this many has every sample measured. A query costs about the number of boxes
/// within the distance of the sample (hundreds once the surface moved tens of edge lengths,
/// as nefertiti does in one step at τ 0.5), so every sample of a 100k-triangle mesh (600k
/// queries) would cost several conformal steps.
pub const MEAN_SAMPLES: usize = 2 * STRATA;
/// The relative accuracy the mean is measured to (issue 29): its stated error bound
/// ([`Deviation::mean_bound`], a 95% interval) is at most this fraction of it, or every
/// sample was measured.
pub const MEAN_ACCURACY: f64 = 0.01;
/// Samples per side above which the mean's distances are taken within [`MEAN_SLACK`]
/// rather than exactly (see [`Deviation`]).
pub const EXACT_MEAN_SAMPLES: usize = 16 * MEAN_SAMPLES;
/// The relative slack of the mean's nearest-point queries on large meshes: each value drawn
/// is between the exact distance and `1 + slack` times it. The slack does not enter the
/// stated bound as a worst case: an exact subsample measures what it added, and the mean is
/// corrected by that (its error enters the bound beside the sampling error:
/// [`super::stratified`]). On nefertiti's recorded frames (one thread, 3,072 queries) a
/// query within 5% costs 25-50% less than within 0.1-0.3% (8.6 against 11.8 ms on τ 0.01's
/// first frame, 6.1 against 12.7 ms on τ 0.5's), where the worst case took a quarter of the
/// accuracy at 0.5%.
pub const MEAN_SLACK: f64 = 0.05;
/// The sampling error, as a fraction of the mean, that [`next_strata`] picks the next frame's
/// number of strata for: below [`MEAN_ACCURACY`] by enough that a frame whose error came out
/// a little larger than the last one's still needs no second round.
const STRATA_AIM: f64 = 0.0085;

/// The next frame's number of strata for the mean, from this frame's: `bound` and `mean` as
/// measured with `strata` strata in `queries` queries (`exact`: a side was measured whole).
/// The bound scaled to the first round's draws (it falls as one over their square root) is
/// what two draws a stratum gave; at two draws a stratum it grows as one over the number of
/// strata (fewer, larger patches, whose distances differ more within: nefertiti's frames at
/// τ 0.5 gave 1.49 times the error with 512 strata as with 768). The next frame takes the
/// fewest, at least [`STRATA_MIN`] and at most [`STRATA`], whose predicted error is
/// [`STRATA_AIM`]: a surface moved far from the input, whose distances vary little relative
/// to their mean, is measured with fewer queries. A frame that says nothing of the sampling
/// error (a side measured whole, nothing measured) starts the next afresh. The choice never
/// changes whether a frame's bound holds (each frame's comes from its own draws), only what
/// the frame costs; a frame predicted too well takes a second round.
fn next_strata(bound: f64, mean: f64, exact: bool, strata: usize, queries: usize) -> usize {
    if exact || mean.is_nan() || mean <= 0.0 || queries == 0 || strata == 0 {
        return STRATA;
    }
    let first_round = (2 * FIRST_SAMPLES * strata) as f64;
    let sampling = bound / mean * (queries as f64 / first_round).max(1.0).sqrt();
    let wanted = (strata as f64 * sampling / STRATA_AIM).ceil();
    if wanted.is_finite() {
        (wanted as usize).clamp(STRATA_MIN, STRATA)
    } else {
        STRATA
    }
}

/// Relative slack of the queries that only bound a distance from above for the max (the
/// max itself is exact): the bound a face gives is its own distance, so a face within 1%
/// of the nearest costs at most 1% of tightness, and the query skips the boxes in the thin
/// shell just inside the nearest distance, most of what it opens far from the surface.
const BOUND_SLACK: f64 = 0.01;
/// What one side keeps from frame to frame (a flow moves the surface a little per step, so
/// last frame's answers are this frame's best starting points; only the speed depends on
/// them, never the result).
#[derive(Clone)]
struct Memory {
    /// Per sample, the face of the other surface found nearest to it last.
    nearest: Vec<u32>,
    /// Per node of this side's tree, a face of the other surface near the node's centre
    /// (`u32::MAX`: none yet, start from the parent's).
    node_face: Vec<u32>,
    /// Per sample, the frame in which its distance was shown to be at most the max.
    settled: Vec<u32>,
    /// The sample whose exact distance set the last max (`usize::MAX`: none): measured
    /// first, it bounds this frame's max from below before anything is pruned.
    argmax: usize,
    /// Scratch of [`Side::mean_query`]: a round's sample points, remembered faces and
    /// their squared distances.
    points: Vec<([f64; 3], usize, f64)>,
}

impl Memory {
    fn new(hints: &[u32], nodes: usize) -> Self {
        Memory {
            nearest: hints.to_vec(),
            node_face: vec![u32::MAX; nodes],
            settled: vec![0; hints.len()],
            argmax: usize::MAX,
            points: Vec::new(),
        }
    }
}

/// One surface's side of the measure: its samples, its tree, and the other
/// surface to measure against.
struct Side<'a> {
    samples: Points<'a>,
    /// Samples per side.
    sample_count: usize,
    /// The same samples on the other surface (same connectivity): `|p − q|` bounds a
    /// sample's distance from above for free, since `q` lies on the other surface.
    counterparts: Points<'a>,
    /// This surface (its samples lie in its tree's boxes).
    own: &'a Bvh,
    own_positions: &'a [[f64; 3]],
    /// The other surface.
    other: &'a Bvh,
    other_positions: &'a [[f64; 3]],
    triangles: &'a [[usize; 3]],
    face_edges: &'a [[usize; 3]],
    /// This frame's number, for [`Memory::settled`].
    frame: u32,
    /// Samples per side above which the mean takes its distances within [`MEAN_SLACK`]
    /// ([`Deviation::with_exact_mean_samples`]).
    exact_mean_samples: usize,
}

impl Side<'_> {
    fn exact(&self, p: [f64; 3], hint: usize) -> (usize, f64) {
        self.other
            .nearest(self.other_positions, self.triangles, p, Some(hint))
            .map_or((hint, 0.0), |(f, d2)| (f, d2.sqrt()))
    }

    /// The slack of the mean's queries: 0 on small meshes (every distance exact), else
    /// [`MEAN_SLACK`] ([`Deviation::with_exact_mean_samples`]).
    fn mean_slack(&self) -> f64 {
        if self.sample_count > self.exact_mean_samples {
            MEAN_SLACK
        } else {
            0.0
        }
    }

    /// The mean's queries ([`super::stratified`] draws the samples): each listed sample's
    /// distance to the other surface, within the given slack above the exact one.
    fn mean_query<'m>(
        &'m self,
        memory: &'m mut Memory,
    ) -> impl FnMut(&[u32], f64, &mut [f64]) + 'm {
        // The draws come stratum by stratum, each stratum a patch: the last draw's nearest
        // face is a near start for a sample not drawn last frame (the draws move with the
        // weights), whose own remembered face may be its initial hint, far off.
        let mut last = usize::MAX;
        move |samples, slack, out| {
            // The points, their remembered faces and those faces' distances first, in one
            // loop whose lookups (all scattered) do not wait on each other; then the
            // queries, in order, each from the nearer of its remembered face and the last
            // draw's.
            let mut points = std::mem::take(&mut memory.points);
            points.clear();
            points.extend(samples.iter().map(|&i| {
                let p = self.samples.at(i as usize);
                let remembered = memory.nearest[i as usize] as usize;
                (p, remembered, self.face_d2(p, remembered))
            }));
            for ((&i, &(p, remembered, d2)), out) in samples.iter().zip(&points).zip(out) {
                let i = i as usize;
                // A sample drawn twice in a round starts its second query where its first
                // ended, as it would one at a time.
                let (remembered, d2) = match memory.nearest[i] as usize {
                    now if now != remembered => (now, self.face_d2(p, now)),
                    _ => (remembered, d2),
                };
                let mut start = (remembered, d2);
                if last != remembered && last < self.triangles.len() {
                    let other = triangle_d2(self.other_positions, self.triangles, p, last);
                    if other < d2 {
                        start = (last, other);
                    }
                }
                let (face, d) = self
                    .other
                    .nearest_from(self.other_positions, self.triangles, p, start, slack, -1.0)
                    .map_or((start.0, 0.0), |(f, d2)| (f, d2.sqrt()));
                memory.nearest[i] = face as u32;
                last = face;
                if slack == 0.0 {
                    memory.settled[i] = self.frame;
                }
                *out = d;
            }
            memory.points = points;
        }
    }

    /// The exact distance of the sample that set the last frame's max (0 if none): a lower
    /// bound of this frame's max, near it while the surface moves a little per frame.
    fn last_argmax(&self, memory: &mut Memory) -> f64 {
        let i = memory.argmax;
        if i >= self.sample_count {
            return 0.0;
        }
        let (face, d) = self.exact(self.samples.at(i), memory.nearest[i] as usize);
        memory.nearest[i] = face as u32;
        d
    }

    /// The largest distance over every sample of this side, exactly, given `max`, one
    /// already reached. A sample is skipped once an upper bound of its distance is at most
    /// `max` (the max only grows); only the samples whose bounds exceed it get an exact
    /// query, which may raise it. Top-down through this surface's tree, with bounds from the
    /// faces that queries within [`BOUND_SLACK`] find (any face's distance bounds the
    /// surface's from above), each query stopping at the first face near enough to skip what
    /// it bounds (most of them, below the max):
    /// - a node: the distance to a surface is 1-Lipschitz and every sample of a node lies in
    ///   its box, so none is further than `d(centre, F) + half diagonal`;
    /// - a leaf: the samples of its triangles lie in the convex hull of their vertices and
    ///   the distance to one triangle F is convex, so none is further than `max_v d(v, F)`
    ///   over the leaf's vertices (far from the other surface, this is within a fraction of an
    ///   edge length of the samples' own distances, where the Lipschitz bound is a whole
    ///   leaf's size above them);
    /// - a sample: its distance to the face a query within the slack finds.
    ///
    /// Before any query, a node or sample none of whose vertices moved further than the max
    /// is settled: `|p − q|` bounds a sample's distance (q is its counterpart on the other
    /// surface) and, each sample being a convex combination of its triangle's corners on both
    /// surfaces alike, the corners' largest displacement bounds every sample on them.
    /// `node_moved` holds that largest displacement per node of this side's tree (empty: not
    /// computed this frame).
    fn settle_max(
        &self,
        mut max: f64,
        node_moved: &[f64],
        memory: &mut Memory,
        stack: &mut Vec<(u32, u32)>,
    ) -> f64 {
        if self.own.nodes.is_empty() {
            return max;
        }
        let (nv, ne) = (
            self.own_positions.len(),
            self.sample_count - self.own_positions.len() - self.triangles.len(),
        );
        stack.clear();
        stack.push((0, memory.nearest[nv + ne]));
        while let Some((index, parent_face)) = stack.pop() {
            // Nothing under this node moved further than the max: settled without a query
            // (most of a surface after a small step).
            if node_moved.get(index as usize).is_some_and(|&m| m <= max) {
                continue;
            }
            let node = self.own.nodes[index as usize];
            let radius = 0.5 * dist2(node.max, node.min).sqrt();
            if radius > max && node.count == 0 {
                // No distance can cull a box this big: open it without a query (from the
                // centre of a big box deep inside a closed surface, a query would open
                // most of the other tree).
                stack.push((node.start, parent_face));
                stack.push((index + 1, parent_face));
                continue;
            }
            let centre = scale(add(node.min, node.max), 0.5);
            let remembered = memory.node_face[index as usize] as usize;
            let hint = self.nearer(centre, parent_face as usize, remembered);
            let (face, d) = self.bound(centre, hint, max - radius);
            memory.node_face[index as usize] = face as u32;
            if d + radius <= max {
                continue;
            }
            if node.count == 0 {
                stack.push((node.start, face as u32));
                stack.push((index + 1, face as u32));
                continue;
            }
            let s = node.start as usize;
            let leaf = &self.own.order[s..s + node.count as usize];
            if self.hull_bound(leaf, face) <= max {
                continue;
            }
            for &f in leaf {
                for i in rule_points(f as usize, self.triangles, self.face_edges, nv, ne) {
                    if memory.settled[i] == self.frame {
                        continue;
                    }
                    memory.settled[i] = self.frame;
                    let p = self.samples.at(i);
                    if dist2(p, self.counterparts.at(i)) <= max * max {
                        continue;
                    }
                    let hint = self.nearer(p, face, memory.nearest[i] as usize);
                    // Exact (no slack), stopping at the first face within the max: either
                    // the sample is settled, or the search ran to the end and `d` is its
                    // exact distance, a new max. (A bound within a slack first, then an
                    // exact query for the samples it left above the max, queried every
                    // sample near the max twice: 300 exact queries of ~17 µs on one of
                    // nefertiti's frames.)
                    let (nearest, d) = self.within(p, hint, max);
                    memory.nearest[i] = nearest as u32;
                    if d <= max {
                        continue;
                    }
                    if d > max {
                        max = d;
                        memory.argmax = i;
                    }
                }
            }
        }
        max
    }

    /// A face of the other surface within `max` of `p` (the first found) and its distance,
    /// else the nearest face and `p`'s exact distance, above `max`.
    fn within(&self, p: [f64; 3], hint: usize, max: f64) -> (usize, f64) {
        self.other
            .nearest_until(
                self.other_positions,
                self.triangles,
                p,
                Some(hint),
                0.0,
                max * max,
            )
            .map_or((hint, 0.0), |(f, d2)| (f, d2.sqrt()))
    }

    /// The squared distance from `p` to face `f` of the other surface (∞ if out of range).
    fn face_d2(&self, p: [f64; 3], f: usize) -> f64 {
        if f < self.triangles.len() {
            triangle_d2(self.other_positions, self.triangles, p, f)
        } else {
            f64::INFINITY
        }
    }

    /// Of two faces of the other surface, the one nearer to `p` (`b` may be out of range:
    /// none).
    fn nearer(&self, p: [f64; 3], a: usize, b: usize) -> usize {
        if b >= self.triangles.len() || b == a {
            return a;
        }
        let da = triangle_d2(self.other_positions, self.triangles, p, a);
        let db = triangle_d2(self.other_positions, self.triangles, p, b);
        if db < da {
            b
        } else {
            a
        }
    }

    /// A face of the other surface and its distance, an upper bound of `p`'s: the first
    /// found within `enough` (all the caller needs to skip what it bounds), else one within
    /// [`BOUND_SLACK`] of the nearest.
    fn bound(&self, p: [f64; 3], hint: usize, enough: f64) -> (usize, f64) {
        let enough = if enough > 0.0 { enough * enough } else { -1.0 };
        self.other
            .nearest_until(
                self.other_positions,
                self.triangles,
                p,
                Some(hint),
                BOUND_SLACK,
                enough,
            )
            .map_or((hint, 0.0), |(f, d2)| (f, d2.sqrt()))
    }

    /// The largest distance from a vertex of `faces` (of this surface) to the face `face` of
    /// the other: a bound for every sample of `faces` (convexity, [`Side::settle_max`]).
    fn hull_bound(&self, faces: &[u32], face: usize) -> f64 {
        let mut d2 = 0.0f64;
        for &f in faces {
            for v in self.triangles[f as usize] {
                d2 = d2.max(triangle_d2(
                    self.other_positions,
                    self.triangles,
                    self.own_positions[v],
                    face,
                ));
            }
        }
        d2.sqrt()
    }
}

/// The two-sided sampled distance between the input surface and a moving one with the same
/// connectivity (module docs). The input's tree and samples are built once; the current
/// surface's tree is refitted every call, and each side keeps its last frame's nearest faces
/// ([`Memory`]).
///
/// The maximum is exact over every sample. The mean is exact over every sample up to
/// [`MEAN_SAMPLES`] per side; above that it is a stratified estimate
/// ([`super::stratified`]: samples drawn with probability ∝ weight in equal-area strata
/// along the input tree's leaves) whose stated error bound ([`Deviation::mean_bound`], a 95%
/// interval) is at most [`MEAN_ACCURACY`] of it: the cost of exact nearest points grows with how far the
/// surface moved, and the mean, unlike the max, does not need every sample. Above
/// [`EXACT_MEAN_SAMPLES`] per side, each of those distances is within [`MEAN_SLACK`] above the
/// exact one, and an exact subsample corrects the mean for it (its error inside the bound).
/// What a side remembers from the last frame changes how fast, never what, it measures (up
/// to that slack, which the correction measures).
pub struct Deviation {
    plan: SamplePlan,
    input_positions: Vec<[f64; 3]>,
    input_bvh: Bvh,
    input_samples: Vec<[f64; 3]>,
    input_face_areas: Vec<f64>,
    current_bvh: Bvh,
    /// Per vertex, how far it moved from the input; per node of the current and the input
    /// tree, the most any of its vertices moved ([`Side::node_moved`]).
    moved: Vec<f64>,
    out_moved: Vec<f64>,
    back_moved: Vec<f64>,
    /// The current surface's samples against the input, and the input's against it.
    out_memory: Memory,
    back_memory: Memory,
    /// Each side's strata for the mean ([`super::stratified`]).
    out_strata: Strata,
    back_strata: Strata,
    /// The stated error bound of the last mean ([`Deviation::mean_bound`]).
    mean_bound: f64,
    /// The nearest-point queries the last mean made, both sides ([`Deviation::mean_queries`]).
    mean_queries: usize,
    frame: u32,
    /// Each side's traversal stack for its max (the input's side, the current surface's).
    stacks: [Vec<(u32, u32)>; 2],
    /// Whether the two sides are measured on two threads ([`Deviation::with_threads`]).
    parallel: bool,
    /// The next frame's number of strata for the mean ([`next_strata`]).
    strata: usize,
    /// See [`Deviation::with_exact_mean_samples`].
    exact_mean_samples: usize,
    /// Where the last [`Deviation::measure`] spent its time ([`Deviation::profile`]).
    profile: [(&'static str, f64); 3],
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
        plan.points_into(positions, triangles, &mut input_samples);
        let input_bvh = Bvh::new(positions, triangles);
        let memory = Memory::new(&plan.hints, input_bvh.nodes.len());
        // One pseudo-random stream per side: their errors are independent. The input's
        // areas never change.
        let face_samples = plan.face_samples(triangles);
        let strata = Strata::new(&input_bvh.order, face_samples.clone(), plan.len(), false, 0);
        let back_strata = Strata::new(&input_bvh.order, face_samples, plan.len(), true, 1);
        Deviation {
            out_strata: strata,
            back_strata,
            mean_bound: 0.0,
            mean_queries: 0,
            current_bvh: input_bvh.clone(),
            input_positions: positions.to_vec(),
            input_bvh,
            input_samples,
            input_face_areas: face_areas.to_vec(),
            moved: vec![0.0; positions.len()],
            out_moved: Vec::new(),
            back_moved: Vec::new(),
            out_memory: memory.clone(),
            back_memory: memory,
            frame: 0,
            plan,
            stacks: [Vec::new(), Vec::new()],
            parallel: false,
            strata: STRATA,
            exact_mean_samples: EXACT_MEAN_SAMPLES,
            profile: [("samples", 0.0), ("mean", 0.0), ("max", 0.0)],
        }
    }

    /// The same measure with another threshold than [`EXACT_MEAN_SAMPLES`] for the large-mesh
    /// mean (distances within [`MEAN_SLACK`], so what a side remembers changes the result
    /// within that slack): a test lowers it to check that regime against a brute force, frame
    /// after frame, on a mesh small enough for one.
    pub fn with_exact_mean_samples(mut self, samples: usize) -> Self {
        self.exact_mean_samples = samples;
        self
    }

    /// The same measure with its next frame's mean drawn from `strata` strata (clamped to
    /// [`STRATA_MIN`]..=[`STRATA`]) instead of [`STRATA`]; later frames take what
    /// [`next_strata`] says, as always. With [`Deviation::strata`], a test measures a frame
    /// afresh as a measure that saw the frames before it would.
    pub fn with_strata(mut self, strata: usize) -> Self {
        self.strata = strata.clamp(STRATA_MIN, STRATA);
        self
    }

    /// How many strata the next frame's mean draws from ([`next_strata`]).
    pub fn strata(&self) -> usize {
        self.strata
    }

    /// The same measure with its two sides (the current surface against the input, the
    /// input against the current surface) on two threads when `threads` > 1: a flow passes
    /// its own [`crate::flow::FlowParams::threads`], so that a job the service gives idle
    /// cores measures its distance as much faster as its step. Each side's draws, queries and
    /// memory are its own, so the result is bitwise the same for any count.
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.parallel = threads > 1;
        self
    }

    /// The same measure drawing the mean's samples from another pseudo-random stream (the
    /// default is stream 0; each side draws from its own): the stated bound of the mean is a
    /// statement about these draws, and a test checks it over many streams.
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.out_strata.reseed(2 * seed);
        self.back_strata.reseed(2 * seed + 1);
        self
    }

    /// `(deviation_max, deviation_mean)` of the surface at `positions` (whose face areas are
    /// `face_areas`) against the input: see the module docs for exactly what is measured.
    pub fn measure(
        &mut self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        face_areas: &[f64],
    ) -> (f64, f64) {
        if triangles.is_empty() {
            return (0.0, 0.0);
        }
        let mut clock = std::time::Instant::now();
        let mut lap = |profile: &mut [(&'static str, f64); 3], k: usize| {
            let now = std::time::Instant::now();
            profile[k].1 = (now - clock).as_secs_f64() * 1e3;
            clock = now;
        };
        self.current_bvh
            .refit_with(positions, triangles, self.parallel);
        self.frame = self.frame.wrapping_add(1);
        if self.frame == 0 {
            self.out_memory.settled.fill(0);
            self.back_memory.settled.fill(0);
            self.frame = 1;
        }
        // A rebuilt tree may have another number of nodes: its nodes' faces start afresh.
        self.out_memory
            .node_face
            .resize(self.current_bvh.nodes.len(), u32::MAX);
        let current = Points::Computed {
            positions,
            edges: &self.plan.edges,
            triangles,
        };
        let out = Side {
            samples: current,
            sample_count: self.input_samples.len(),
            counterparts: Points::Stored(&self.input_samples),
            own: &self.current_bvh,
            own_positions: positions,
            other: &self.input_bvh,
            other_positions: &self.input_positions,
            triangles,
            face_edges: &self.plan.face_edges,
            frame: self.frame,
            exact_mean_samples: self.exact_mean_samples,
        };
        let back = Side {
            samples: Points::Stored(&self.input_samples),
            sample_count: self.input_samples.len(),
            counterparts: current,
            own: &self.input_bvh,
            own_positions: &self.input_positions,
            other: &self.current_bvh,
            other_positions: positions,
            triangles,
            face_edges: &self.plan.face_edges,
            frame: self.frame,
            exact_mean_samples: self.exact_mean_samples,
        };
        lap(&mut self.profile, 0);
        let slack = out.mean_slack();
        let ([mean_out, mean_in], mean_bound) = estimate_pair(
            [&mut self.out_strata, &mut self.back_strata],
            [face_areas, &self.input_face_areas],
            MEAN_ACCURACY,
            self.strata,
            slack,
            out.mean_query(&mut self.out_memory),
            back.mean_query(&mut self.back_memory),
            self.parallel,
        );
        self.mean_bound = mean_bound;
        self.mean_queries = mean_out.measured + mean_in.measured;
        self.strata = next_strata(
            mean_bound,
            0.5 * (mean_out.mean + mean_in.mean),
            mean_out.exact || mean_in.exact,
            self.strata,
            self.mean_queries,
        );
        lap(&mut self.profile, 1);
        let (max_out, max_in) = (mean_out.max_seen, mean_in.max_seen);
        let max_out = max_out.max(out.last_argmax(&mut self.out_memory));
        let max_in = max_in.max(back.last_argmax(&mut self.back_memory));
        // Both sides' distances so far bound the max below before either settles it, so the
        // side with the smaller distances mostly has nothing left to check.
        let max = max_out.max(max_in);
        // The per-node displacement bounds cost a pass over each tree (2-3 ms at 100k
        // triangles); they pay off only where most of the surface moved less than the max
        // (small steps), and settle nothing after a large one.
        let mut still = 0;
        for ((m, p), q) in self
            .moved
            .iter_mut()
            .zip(positions)
            .zip(&self.input_positions)
        {
            *m = dist2(*p, *q).sqrt();
            still += usize::from(*m <= max);
        }
        // The current tree starts as a copy of the input's: until a refit rebuilds it, both
        // group the same vertices into the same nodes, and one pass serves both sides.
        let shared = self.current_bvh.same_layout(&self.input_bvh);
        if 4 * still >= 3 * self.moved.len() {
            self.current_bvh
                .max_per_node(&self.moved, &mut self.out_moved);
            if shared {
                self.back_moved.clear();
            } else {
                self.input_bvh
                    .max_per_node(&self.moved, &mut self.back_moved);
            }
        } else {
            self.out_moved.clear();
            self.back_moved.clear();
        }
        // Each side settles its own max from the same lower bound (on two threads when
        // allowed; either way alike, so what the sides remember, and with it every later
        // frame, does not depend on the threads).
        let [back_stack, out_stack] = &mut self.stacks;
        let back_moved = if shared {
            &self.out_moved
        } else {
            &self.back_moved
        };
        let (max_in, max_out) = join(
            self.parallel,
            || back.settle_max(max, back_moved, &mut self.back_memory, back_stack),
            || out.settle_max(max, &self.out_moved, &mut self.out_memory, out_stack),
        );
        let max = max_in.max(max_out);
        lap(&mut self.profile, 2);
        (max, 0.5 * (mean_out.mean + mean_in.mean))
    }

    /// Where the last [`Deviation::measure`] spent its time, in ms: the samples and the
    /// current tree's refit, the mean (both sides), the max (both sides).
    pub fn profile(&self) -> &[(&'static str, f64)] {
        &self.profile
    }

    /// The stated error bound of the last [`Deviation::measure`]'s mean: the mean over every
    /// sample is within `mean ± mean_bound` with 95% confidence ([`super::stratified`]: two
    /// standard errors of the two sides' stratified average, corrected for the queries'
    /// slack, their independent errors added in quadrature; 0 where every sample was measured
    /// exactly). At most [`MEAN_ACCURACY`] times the mean, unless every sample was measured.
    pub fn mean_bound(&self) -> f64 {
        self.mean_bound
    }

    /// How many nearest-point queries the last [`Deviation::measure`]'s mean made (both
    /// sides; a sample drawn twice counts twice): what its cost scales with.
    pub fn mean_queries(&self) -> usize {
        self.mean_queries
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The next frame takes as many strata as this frame's error, scaled to two draws a
    /// stratum and to one over the strata, says reach [`STRATA_AIM`]: fewer where the error
    /// left room (never below [`STRATA_MIN`]), all of them where it did not or says nothing.
    #[test]
    fn the_strata_are_what_the_last_error_asks() {
        let mean = 10.0;
        let first = 2 * FIRST_SAMPLES * STRATA;
        // Half the aim at every stratum: half the strata, the fewest allowed.
        let bound = mean * 0.5 * STRATA_AIM;
        assert_eq!(next_strata(bound, mean, false, STRATA, first), STRATA_MIN);
        // 0.6% at 768 strata: 768 · 0.6 / 0.85 = 542.1, rounded up.
        assert_eq!(next_strata(mean * 0.006, mean, false, STRATA, first), 543);
        // 0.4% reached with twice the first round's draws: √2 · 0.4% at two draws a stratum,
        // 768 · 0.566 / 0.85 = 511.1.
        let next = next_strata(mean * 0.004, mean, false, STRATA, 2 * first);
        assert_eq!(next, 512);
        // From 600 strata (a first round of 2,400 queries), 0.5%: 600 · 0.5 / 0.85 = 352.9,
        // below the fewest.
        let from = 2 * FIRST_SAMPLES * 600;
        assert_eq!(
            next_strata(mean * 0.005, mean, false, 600, from),
            STRATA_MIN
        );
        // An error above the aim, a side measured whole, nothing measured: all the strata.
        assert_eq!(
            next_strata(mean * 0.009, mean, false, STRATA, first),
            STRATA
        );
        assert_eq!(next_strata(0.0, mean, true, 400, first), STRATA);
        assert_eq!(next_strata(0.0, 0.0, false, 400, 0), STRATA);
    }
}
