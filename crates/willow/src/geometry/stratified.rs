//! A stratified estimate of the two-sided area-weighted mean distance with its error bound
//! (used by [`super::distance::Deviation`] for `deviation_mean`).
//!
//! The mean needs 1% accuracy (issue 29), not every sample. A side's weighted mean is a sum
//! over (face, rule point) pairs: each face's area times the 7-point rule's weight of the
//! point ([`super::distance`]), times the distance of that point's sample. The faces are laid
//! out in a fixed, spatially coherent order (the input tree's leaves) and cut each frame into
//! runs of equal area ([`STRATA`] on a first frame, fewer where the last frame's error left
//! room: [`super::distance`]'s `next_strata`): each stratum is a patch of the surface over
//! which the distance, a 1-Lipschitz function, varies little. Each stratum draws a face with
//! probability proportional to its area and then one of its seven points with its rule weight
//! (one uniform number does both: where it falls inside the face's interval picks the point),
//! with replacement, so a sample comes with probability proportional to its weight and the
//! draws' plain mean estimates the stratum's weighted mean without bias; the strata's
//! estimates average to the side's (stratified sampling with probabilities proportional to
//! size: Cochran, *Sampling Techniques*, 3rd ed., §5.3 and §9A.3). The variance comes from the
//! draws' own spread, `Var = Σ_k s_k² / m_k / S²`. Drawing faces rather than samples keeps
//! the per-frame work to one running sum over the faces (a third of the samples), over the
//! face areas the flow computes anyway.
//!
//! `deviation_mean` is the average of the two sides' means, and their draws are independent
//! (each side its own pseudo-random stream), so its variance is `(Var_out + Var_in) / 4`: the
//! two sides' errors add in quadrature, not in sum, and with equal variances the pair needs
//! half the draws that two separate 1% estimates would. The stated bound is [`CONFIDENCE_Z`]
//! standard errors of that average; while it is wider than the accuracy asked, every stratum
//! of both sides gets more draws alike, as many as the projected variance needs, and a side
//! past a quarter of its samples has every sample measured exactly.
//!
//! On a large mesh the draws' distances are taken within a slack of a few percent above the
//! exact ones (a query that may stop at any face that near costs much less). What the slack
//! added is not bounded by its worst case but measured: [`CORRECTIONS`] of a side's first
//! round's draws are measured again exactly, the mean of the differences is subtracted, and its
//! variance added (double sampling with a difference estimator, [`Strata::correct`]).
//!
//! Equal-weight strata and weight-proportional draws matter: a flow can shrink or grow face
//! areas by orders of magnitude (nefertiti at τ 0.5), and equal-count strata sampled
//! uniformly then have a standard error of several percent at 2,000 draws.
//!
//! Which samples are measured depends only on the weights, the fixed pseudo-random draws, the
//! number of strata and the distances measured; what a side remembers from the last frame
//! (where its queries start) changes only where within the slack a query stops.
use super::distance::{CENTROID_WEIGHT, EDGE_WEIGHT, VERTEX_WEIGHT};
use crate::parallel::join;

/// Strata per side on a frame that knows nothing of the last (the first): with
/// [`FIRST_SAMPLES`] each, 1,536 queries per side on a large mesh. On nefertiti's first frames
/// (100k triangles; τ 0.5 and 0.01) the pair states 0.77-0.95% after that first round. Measured
/// against 512, 640 and 1024 strata on such frames: fewer strata needed second rounds of more
/// than they saved (their patches are coarser, so each draw says less), more strata a first
/// round larger than needed. Later frames take as many as the last frame's error asks, down
/// to [`STRATA_MIN`].
pub const STRATA: usize = 768;
/// The fewest strata a later frame takes ([`estimate_pair`]'s `strata`): a first round of
/// 768 queries per side.
pub const STRATA_MIN: usize = 384;
/// Samples measured first in each stratum: two, the fewest that give a variance.
pub(crate) const FIRST_SAMPLES: usize = 2;
/// Standard errors in the stated bound: 2, the coverage factor of an expanded uncertainty
/// (JCGM 100:2008, the *Guide to the expression of uncertainty in measurement*, §6.3: a
/// two-sided normal interval of about 95%; the estimate is a sum over hundreds of strata,
/// so the normal approximation holds). `tests/deviation.rs` checks that coverage over 120
/// independent estimates. (The max, which `max_deviation` stops on, is exact: no interval.)
pub const CONFIDENCE_Z: f64 = 2.0;
/// The variance a refinement round aims at, as a fraction of what the accuracy allows: below
/// 1, so that the strata's estimates, which move as they get more draws, still meet it.
const REFINE_MARGIN: f64 = 0.9;
/// The most and the least a refinement round multiplies the draws by.
const GROWTH: f64 = 4.0;
const GROWTH_MIN: f64 = 1.05;
/// Mixed into a side's seed for the refinement's random rounding ([`estimate_pair`]).
const ROUNDING_STREAM: u64 = 0x0005_EED0_F0A1_D000;
/// Refinement rounds before every sample is measured ([`estimate_pair`]).
const ROUNDS: usize = 6;
/// Draws per side measured again exactly ([`Strata::correct`]), one in every
/// `strata / CORRECTIONS` strata: the correction's own variance is then a few percent of the
/// sampling's on nefertiti's frames, and 96 cost 0.5-1 ms more a frame for less than that.
/// Fewer are not enough: most draws' values are exact and a few are up to the slack above,
/// so the mean of a small subsample is skewed, and with 24 (a frame drawing from 384 strata)
/// the large-mesh test's near frame came out 2.5 standard errors off.
const CORRECTIONS: usize = 48;
/// Mixed into a side's seed to pick which strata [`Strata::correct`] measures again.
const CORRECTION_STREAM: u64 = 0x00C0_44EC_7104_0000;

/// One side's mean and what it knows about its error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeanEstimate {
    /// Weighted mean distance (estimated).
    pub mean: f64,
    /// The side's own stated error bound: its true mean is within `mean ± bound` (module
    /// docs; `deviation_mean`'s bound combines both sides').
    pub bound: f64,
    /// The largest distance measured exactly, or measured within the slack and divided by
    /// `1 + slack`: a lower bound of the max.
    pub max_seen: f64,
    /// Queries made (a sample drawn twice counts twice).
    pub measured: usize,
    /// Whether every sample was measured (no sampling error).
    pub exact: bool,
}

/// The 7-point rule's weights as fractions of a face's area, in the order of a face's
/// points in [`Strata::new`]'s `face_samples`: its corners, its edge midpoints, its centroid.
pub(crate) const RULE: [f64; 7] = [
    VERTEX_WEIGHT,
    VERTEX_WEIGHT,
    VERTEX_WEIGHT,
    EDGE_WEIGHT,
    EDGE_WEIGHT,
    EDGE_WEIGHT,
    CENTROID_WEIGHT,
];

/// A side's strata (module docs): the faces in a fixed spatially coherent order, cut each
/// frame into [`STRATA`] runs of equal area.
pub(crate) struct Strata {
    /// Face indices, along a tree's leaves.
    order: Vec<u32>,
    /// This frame's number of strata (at most [`STRATA`]: the per-stratum arrays hold that
    /// many, and the first `count` are used).
    count: usize,
    /// Per face, the samples of its seven rule points ([`RULE`]'s order).
    face_samples: Vec<[u32; 7]>,
    /// Samples of the side (some shared between faces: corners and edge midpoints).
    samples: usize,
    /// Whether the areas never change between frames (the input's side): the running sum and
    /// the strata's edges are then computed once.
    fixed: bool,
    /// Scratch: `cumulative[j]` is the area of `order[..j]`.
    cumulative: Vec<f64>,
    /// Scratch: per stratum boundary `k·total/count`, the index into `order` of the face
    /// whose area interval holds it: a draw in stratum k searches only between two of these.
    edges: Vec<usize>,
    /// Scratch for [`Strata::measure_all`]: per sample, its weight.
    weights: Vec<f64>,
    /// Scratch for [`Strata::draw`] and [`Strata::measure_all`]: the samples to measure (with
    /// their strata) and their distances.
    pending_strata: Vec<u32>,
    pending_draws: Vec<u32>,
    pending_samples: Vec<u32>,
    values: Vec<f64>,
    /// Per stratum: draws so far, their sum and sum of squares, its variance contribution.
    draws: Vec<u32>,
    sum: Vec<f64>,
    sum2: Vec<f64>,
    contribution: Vec<f64>,
    /// Per stratum, the draws the next round brings it to.
    goal: Vec<u32>,
    /// This frame's total area (`None`: not computed yet).
    total: Option<f64>,
    /// This side's pseudo-random stream ([`uniform`]).
    seed: u64,
    /// This frame's largest value and number of queries so far.
    max_seen: f64,
    measured: usize,
    /// This frame's mean once every sample was measured (sampling no longer applies).
    exact: Option<f64>,
    /// Per stratum, its first round's draws' samples and values ([`Strata::correct`]).
    first_samples: Vec<[u32; FIRST_SAMPLES]>,
    first_values: Vec<[f64; FIRST_SAMPLES]>,
    /// The differences between the first draws' values and their exact distances, over the
    /// strata [`Strata::correct`] measured again: count, sum, sum of squares.
    correction: (usize, f64, f64),
}

/// A number in [0, 1) from a seed and two integers: splitmix64 of their combination
/// (reproducible pseudo-random draws, the same every frame and every run; one stream per
/// side, so the two sides' errors are independent).
fn uniform(seed: u64, k: usize, j: usize) -> f64 {
    let mut z = (k as u64)
        .wrapping_add(seed.wrapping_mul(0xA076_1D64_78BD_642F))
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add((j as u64).wrapping_mul(0xD1B5_4A32_D192_ED03))
        .wrapping_add(0x5EED);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

impl Strata {
    /// `face_order`: the faces in a spatially coherent order (a tree's leaf order);
    /// `face_samples`: per face, its seven rule points' samples, among `samples`; `fixed`:
    /// whether every frame brings the same areas.
    pub(crate) fn new(
        face_order: &[u32],
        face_samples: Vec<[u32; 7]>,
        samples: usize,
        fixed: bool,
        seed: u64,
    ) -> Self {
        Strata {
            order: face_order.to_vec(),
            count: STRATA,
            face_samples,
            samples,
            fixed,
            cumulative: vec![0.0; face_order.len() + 1],
            edges: vec![0; STRATA + 1],
            weights: Vec::new(),
            pending_strata: Vec::new(),
            pending_draws: Vec::new(),
            pending_samples: Vec::new(),
            values: Vec::new(),
            draws: vec![0; STRATA],
            sum: vec![0.0; STRATA],
            sum2: vec![0.0; STRATA],
            contribution: vec![0.0; STRATA],
            goal: vec![0; STRATA],
            total: None,
            seed,
            max_seen: 0.0,
            measured: 0,
            exact: None,
            first_samples: vec![[0; FIRST_SAMPLES]; STRATA],
            first_values: vec![[0.0; FIRST_SAMPLES]; STRATA],
            correction: (0, 0.0, 0.0),
        }
    }

    /// Draw from another pseudo-random stream ([`uniform`]).
    pub(crate) fn reseed(&mut self, seed: u64) {
        self.seed = seed;
    }

    /// Start a frame: the areas' running sums and the strata's edges (once, if fixed); no
    /// draw yet.
    fn begin(&mut self, face_areas: &[f64], count: usize) {
        let count = count.clamp(1, STRATA);
        let recount = count != self.count;
        self.count = count;
        self.draws.fill(0);
        self.goal.fill(FIRST_SAMPLES as u32);
        self.sum.fill(0.0);
        self.sum2.fill(0.0);
        self.contribution.fill(0.0);
        self.max_seen = 0.0;
        self.measured = 0;
        self.exact = None;
        self.correction = (0, 0.0, 0.0);
        let total = match self.total {
            Some(total) if self.fixed && !recount => total,
            _ => self.sweep(face_areas),
        };
        if self.samples <= FIRST_SAMPLES * STRATA || total <= 0.0 {
            // Too few samples to sample: measure them all.
            self.exact = Some(0.0);
        }
    }

    /// The running sum of the areas along the order and the strata's edges; the total.
    fn sweep(&mut self, face_areas: &[f64]) -> f64 {
        let n = self.order.len();
        let mut total = 0.0;
        for (j, &f) in self.order.iter().enumerate() {
            self.cumulative[j] = total;
            total += face_areas[f as usize];
        }
        self.cumulative[n] = total;
        self.total = Some(total);
        // One sweep finds every stratum's edges (the boundaries increase with k).
        let width = total / self.count as f64;
        let mut at = 0;
        for (k, edge) in self.edges[..=self.count].iter_mut().enumerate() {
            let u = width * k as f64;
            while at + 1 < n && self.cumulative[at + 1] <= u {
                at += 1;
            }
            *edge = at;
        }
        total
    }

    /// Draw what the strata's goals ask for, each value within `slack` above the exact
    /// distance. Which samples are drawn is listed first, in one loop whose iterations do not
    /// wait on each other, and only then measured: interleaved with the queries, each draw's
    /// lookups (running sums, faces, their samples: all scattered over megabytes) waited on
    /// memory alone.
    fn draw(&mut self, slack: f64, distances: &mut impl FnMut(&[u32], f64, &mut [f64])) {
        if self.exact.is_some() {
            return;
        }
        let n = self.order.len();
        let width = self.total.unwrap_or(0.0) / self.count as f64;
        self.pending_strata.clear();
        self.pending_draws.clear();
        self.pending_samples.clear();
        for k in 0..self.count {
            for j in self.draws[k]..self.goal[k] {
                let u = width * (k as f64 + uniform(self.seed, k, j as usize));
                // The face whose area interval holds u (probability ∝ area), then the rule
                // point whose share of that interval holds it (probability ∝ its weight).
                let (lo, hi) = (self.edges[k], (self.edges[k + 1] + 1).min(n));
                let at =
                    (lo + self.cumulative[lo + 1..=hi].partition_point(|&c| c <= u)).min(n - 1);
                let (start, span) = (
                    self.cumulative[at],
                    self.cumulative[at + 1] - self.cumulative[at],
                );
                let mut within = if span > 0.0 { (u - start) / span } else { 0.0 };
                let mut point = 0;
                while point < RULE.len() - 1 && within >= RULE[point] {
                    within -= RULE[point];
                    point += 1;
                }
                let sample = self.face_samples[self.order[at] as usize][point];
                if let Some(first) = self.first_samples[k].get_mut(j as usize) {
                    *first = sample;
                }
                self.pending_strata.push(k as u32);
                self.pending_draws.push(j);
                self.pending_samples.push(sample);
            }
            self.draws[k] = self.goal[k].max(self.draws[k]);
        }
        self.values.resize(self.pending_samples.len(), 0.0);
        distances(&self.pending_samples, slack, &mut self.values);
        for ((&k, &j), &d) in (self.pending_strata.iter())
            .zip(&self.pending_draws)
            .zip(&self.values)
        {
            let k = k as usize;
            if let Some(first) = self.first_values[k].get_mut(j as usize) {
                *first = d;
            }
            self.max_seen = self.max_seen.max(d / (1.0 + slack));
            self.measured += 1;
            self.sum[k] += d;
            self.sum2[k] += d * d;
        }
    }

    /// Measure again, exactly, one of the first round's draws in [`CORRECTIONS`] strata evenly
    /// spread (which strata and which draw, from this side's seed alone: every
    /// draw alike likely, since a stratum's later draws start their queries nearer their
    /// answers and stop within the slack at a different place), and keep the differences from
    /// the values drawn within the slack: a subsample whose mean estimates what the slack
    /// added to the draws' mean (double sampling with a difference estimator: Cochran, *Sampling
    /// Techniques*, 3rd ed., §12.7). The mean is then taken as the draws' less that
    /// estimate, and its variance adds the estimate's ([`Strata::summary`]). Queries within
    /// a slack of several percent cost half as much as within 0.1% on a surface moved far
    /// (a third less near it), and fifty exact ones pay for the correction.
    fn correct(&mut self, distances: &mut impl FnMut(&[u32], f64, &mut [f64])) {
        let step = (self.count / CORRECTIONS).max(1);
        let offset = (uniform(self.seed ^ CORRECTION_STREAM, 0, 0) * step as f64) as usize % step;
        self.pending_strata.clear();
        self.pending_samples.clear();
        self.pending_draws.clear();
        for k in (offset..self.count).step_by(step) {
            let drawn = (self.draws[k] as usize).min(FIRST_SAMPLES);
            if drawn > 0 {
                let j = (uniform(self.seed ^ CORRECTION_STREAM, k, 1) * drawn as f64) as usize;
                let j = j.min(drawn - 1);
                self.pending_strata.push(k as u32);
                self.pending_draws.push(j as u32);
                self.pending_samples.push(self.first_samples[k][j]);
            }
        }
        self.values.resize(self.pending_samples.len(), 0.0);
        distances(&self.pending_samples, 0.0, &mut self.values);
        let (mut n, mut sum, mut sum2) = (0, 0.0, 0.0);
        for ((&k, &j), &d) in (self.pending_strata.iter())
            .zip(&self.pending_draws)
            .zip(&self.values)
        {
            let difference = self.first_values[k as usize][j as usize] - d;
            self.max_seen = self.max_seen.max(d);
            self.measured += 1;
            n += 1;
            sum += difference;
            sum2 += difference * difference;
        }
        self.correction = (n, sum, sum2);
    }

    /// The correction's mean (subtracted from the draws') and variance ([`Strata::correct`]);
    /// zero if it was not made.
    fn correction(&self) -> (f64, f64) {
        let (n, sum, sum2) = self.correction;
        if n < 2 {
            return (0.0, 0.0);
        }
        let n = n as f64;
        let mean = sum / n;
        let variance = ((sum2 - n * mean * mean) / (n - 1.0)).max(0.0) / n;
        (mean, variance)
    }

    /// The side's mean and the variance of it, from the draws so far and the correction for
    /// their slack ([`Strata::correct`]; 0 variance once every sample was measured exactly).
    fn summary(&mut self) -> (f64, f64) {
        if let Some(mean) = self.exact {
            return (mean, 0.0);
        }
        // Stratified sampling with replacement, probability ∝ weight within each of the
        // equal-weight strata: mean = Σ_k d̄_k / S, Var = Σ_k s_k² / m_k / S².
        let (mut mean, mut variance) = (0.0, 0.0);
        for k in 0..self.count {
            let m = f64::from(self.draws[k]);
            let dk = self.sum[k] / m;
            let s2 = ((self.sum2[k] - m * dk * dk) / (m - 1.0)).max(0.0);
            self.contribution[k] = s2 / m;
            mean += dk;
            variance += self.contribution[k];
        }
        let strata = self.count as f64;
        let (shift, shift_variance) = self.correction();
        (
            mean / strata - shift,
            variance / (strata * strata) + shift_variance,
        )
    }

    /// Every sample, exactly: the side's weighted mean, from then on its value.
    fn measure_all(
        &mut self,
        face_areas: &[f64],
        distances: &mut impl FnMut(&[u32], f64, &mut [f64]),
    ) {
        self.weights.clear();
        self.weights.resize(self.samples, 0.0);
        for (points, &area) in self.face_samples.iter().zip(face_areas) {
            for (&i, rule) in points.iter().zip(RULE) {
                self.weights[i as usize] += rule * area;
            }
        }
        self.pending_samples.clear();
        self.pending_samples.extend(0..self.samples as u32);
        self.values.resize(self.samples, 0.0);
        distances(&self.pending_samples, 0.0, &mut self.values);
        let (mut sum, mut max) = (0.0, 0.0f64);
        for (&w, &d) in self.weights.iter().zip(&self.values) {
            max = max.max(d);
            sum += w * d;
        }
        self.measured += self.samples;
        self.max_seen = self.max_seen.max(max);
        let total = self.total.unwrap_or(0.0);
        self.exact = Some(if total > 0.0 { sum / total } else { 0.0 });
    }

    /// Whether sampling is no longer worth it after `round` refinements.
    fn exhausted(&self, round: usize) -> bool {
        self.exact.is_none() && (round > ROUNDS || self.measured > self.samples / 4)
    }

    fn estimate(&self, mean: f64, variance: f64) -> MeanEstimate {
        MeanEstimate {
            mean,
            bound: CONFIDENCE_Z * variance.sqrt(),
            max_seen: self.max_seen,
            measured: self.measured,
            exact: self.exact.is_some(),
        }
    }
}

/// The two sides' means (each side's own [`MeanEstimate`]) and the stated error bound of
/// their average, `deviation_mean` (module docs): within `accuracy` of it, or every sample
/// of a side whose draws passed a quarter of its samples was measured exactly.
/// `distance_*(samples, slack, out)` write, for each listed sample of a side, a value between
/// its exact distance and `1 + slack` times it (a round's samples come in one list, so that
/// their lookups need not wait on the queries in between). The draws take `slack`; with a
/// slack, the first round's are corrected by an exact subsample ([`Strata::correct`]). Each
/// side is cut into `strata` strata (at most [`STRATA`]). With
/// `parallel`, the two sides draw on two threads (each side's draws and queries are its own:
/// the result is the same either way).
#[allow(clippy::too_many_arguments)]
pub(crate) fn estimate_pair(
    sides: [&mut Strata; 2],
    face_areas: [&[f64]; 2],
    accuracy: f64,
    strata: usize,
    slack: f64,
    mut distance_out: impl FnMut(&[u32], f64, &mut [f64]) + Send,
    mut distance_in: impl FnMut(&[u32], f64, &mut [f64]) + Send,
    parallel: bool,
) -> ([MeanEstimate; 2], f64) {
    let [out, back] = sides;
    out.begin(face_areas[0], strata);
    back.begin(face_areas[1], strata);
    join(
        parallel && out.exact.is_some() && back.exact.is_some(),
        || {
            if out.exact.is_some() {
                out.measure_all(face_areas[0], &mut distance_out);
            }
        },
        || {
            if back.exact.is_some() {
                back.measure_all(face_areas[1], &mut distance_in);
            }
        },
    );
    let mut round = 0;
    loop {
        let sampling = out.exact.is_none() && back.exact.is_none();
        join(
            parallel && sampling,
            || {
                out.draw(slack, &mut distance_out);
                if round == 0 && slack > 0.0 && out.exact.is_none() {
                    out.correct(&mut distance_out);
                }
            },
            || {
                back.draw(slack, &mut distance_in);
                if round == 0 && slack > 0.0 && back.exact.is_none() {
                    back.correct(&mut distance_in);
                }
            },
        );
        let ((m_out, v_out), (m_in, v_in)) = (out.summary(), back.summary());
        let mean = 0.5 * (m_out + m_in);
        let bound = CONFIDENCE_Z * (0.25 * (v_out + v_in)).sqrt();
        if bound <= accuracy * mean || (out.exact.is_some() && back.exact.is_some()) {
            let estimates = [out.estimate(m_out, v_out), back.estimate(m_in, v_in)];
            return (estimates, bound);
        }
        round += 1;
        // A side whose draws got past a quarter of its samples (or past the rounds) has them
        // all measured instead.
        let exhausted = [out.exhausted(round), back.exhausted(round)];
        join(
            parallel && exhausted[0] && exhausted[1],
            || {
                if exhausted[0] {
                    out.measure_all(face_areas[0], &mut distance_out);
                }
            },
            || {
                if exhausted[1] {
                    back.measure_all(face_areas[1], &mut distance_in);
                }
            },
        );
        // More draws in every stratum alike, as many as the projected variance needs (it
        // falls as 1/draws) to meet [`REFINE_MARGIN`] of what the accuracy allows. Alike,
        // not where the first draws looked spread (Neyman allocation): a stratum whose two
        // draws happened to agree would keep its too-small variance while the spread ones
        // were corrected down, and the stated bound came out about 1.5 times too narrow (the
        // coverage test in tests/deviation.rs caught it).
        let allowed = REFINE_MARGIN * 4.0 * (accuracy * mean / CONFIDENCE_Z).powi(2);
        let factor = if allowed > 0.0 {
            ((v_out + v_in) / allowed).clamp(GROWTH_MIN, GROWTH)
        } else {
            GROWTH
        };
        // `draws · factor` in every stratum, rounded up or down at random (a stream of its
        // own, so which strata round up does not depend on any distance either): the total
        // grows by the factor without a whole draw more in every stratum.
        for side in [&mut *out, &mut *back] {
            if side.exact.is_none() {
                for k in 0..side.count {
                    let target = f64::from(side.draws[k]) * factor;
                    let up = uniform(side.seed ^ ROUNDING_STREAM, k, round) < target.fract();
                    side.goal[k] = target.floor() as u32 + u32::from(up);
                }
            }
        }
    }
}
