//! A stratified estimate of the two-sided area-weighted mean distance with its error bound
//! (used by [`super::distance::Deviation`] for `deviation_mean`).
//!
//! The mean needs 1% accuracy (issue 29), not every sample. Each side's samples are laid out
//! in a fixed, spatially coherent order (the faces they lie on, along the input tree's leaves)
//! and cut each frame into [`STRATA`] runs of equal weight (area): each stratum is a patch of
//! the surface over which the distance, a 1-Lipschitz function, varies little. Each stratum
//! draws samples with probability proportional to their weight (with replacement), so its
//! draws' plain mean estimates its weighted mean without bias, and the strata's estimates
//! average to the side's (stratified sampling with probabilities proportional to size:
//! Cochran, *Sampling Techniques*, 3rd ed., §5.3 and §9A.3). The variance comes from the
//! draws' own spread, `Var = Σ_k s_k² / m_k / S²`.
//!
//! `deviation_mean` is the average of the two sides' means, and their draws are independent
//! (each side its own pseudo-random stream), so its variance is `(Var_out + Var_in) / 4`: the
//! two sides' errors add in quadrature, not in sum, and with equal variances the pair needs
//! half the draws that two separate 1% estimates would. The stated bound is [`CONFIDENCE_Z`]
//! standard errors of that average plus half the nearest-point queries' slack (each value is
//! re-centred in its slack interval); while it is wider than the accuracy asked, the strata
//! (of either side) holding most of the variance double their draws, and a side past a quarter
//! of its samples has every sample measured (exact up to the slack).
//!
//! Equal-weight strata and weight-proportional draws matter: a flow can shrink or grow face
//! areas by orders of magnitude (nefertiti at τ 0.5), and equal-count strata sampled
//! uniformly then have a standard error of several percent at 2,000 draws.
//!
//! Which samples are measured depends only on the weights, the fixed pseudo-random draws and
//! the distances measured, never on what was remembered from the last frame.

/// Strata per side: with [`FIRST_SAMPLES`] each, about 2,000 queries per side on a large
/// mesh. On nefertiti's frames (100k triangles, moved 2 to 50 edge lengths), each side alone
/// would state about 1% after that first round and need a second; the pair states 0.74-0.97%
/// after the first (4,100-4,900 queries in all, against 5,100-6,600 for two separate 1%
/// estimates).
pub const STRATA: usize = 1024;
/// Samples measured first in each stratum: two, the fewest that give a variance.
const FIRST_SAMPLES: usize = 2;
/// Standard errors in the stated bound: 3 (a two-sided normal interval of 99.7%; the
/// estimate is a sum over a thousand strata, so the normal approximation holds).
pub const CONFIDENCE_Z: f64 = 3.0;
/// Refinement rounds before every sample is measured: each round doubles the draws of the
/// strata above the mean variance contribution.
const ROUNDS: usize = 6;

/// One side's mean and what it knows about its error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeanEstimate {
    /// Weighted mean distance (estimated).
    pub mean: f64,
    /// The side's own stated error bound: its true mean is within `mean ± bound` (module
    /// docs; `deviation_mean`'s bound combines both sides').
    pub bound: f64,
    /// The largest distance measured, divided by `1 + slack`: a lower bound of the max.
    pub max_seen: f64,
    /// Queries made (a sample drawn twice counts twice).
    pub measured: usize,
}

/// A side's strata (module docs): the samples in a fixed spatially coherent order, cut each
/// frame into [`STRATA`] runs of equal weight.
pub(crate) struct Strata {
    /// Sample indices, in the order of the faces they lie on along a tree's leaves.
    order: Vec<u32>,
    /// Scratch: `cumulative[j]` is the weight of `order[..j]`.
    cumulative: Vec<f64>,
    /// Scratch: per stratum boundary `k·total/STRATA`, the index into `order` of the sample
    /// whose weight interval holds it: a draw in stratum k searches only between two of these.
    edges: Vec<usize>,
    /// Per stratum: draws so far, their sum and sum of squares, its variance contribution.
    draws: Vec<u32>,
    sum: Vec<f64>,
    sum2: Vec<f64>,
    contribution: Vec<f64>,
    /// Per stratum, the draws the next round brings it to.
    goal: Vec<u32>,
    /// This frame's total weight.
    total: f64,
    /// This side's pseudo-random stream ([`uniform`]).
    seed: u64,
    /// This frame's largest value and number of queries so far.
    max_seen: f64,
    measured: usize,
    /// This frame's mean once every sample was measured (sampling no longer applies).
    exact: Option<f64>,
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
    /// `owner[i]`: a face sample i lies on; `face_order`: the faces in a spatially coherent
    /// order (a tree's leaf order).
    pub(crate) fn new(owner: &[u32], face_order: &[u32], seed: u64) -> Self {
        let n = owner.len();
        let mut rank = vec![0u32; face_order.len()];
        for (r, &f) in face_order.iter().enumerate() {
            rank[f as usize] = r as u32;
        }
        let mut order: Vec<u32> = (0..n as u32).collect();
        order.sort_by_key(|&i| (rank[owner[i as usize] as usize], i));
        Strata {
            order,
            cumulative: vec![0.0; n + 1],
            edges: vec![0; STRATA + 1],
            draws: vec![0; STRATA],
            sum: vec![0.0; STRATA],
            sum2: vec![0.0; STRATA],
            contribution: vec![0.0; STRATA],
            goal: vec![0; STRATA],
            total: 0.0,
            seed,
            max_seen: 0.0,
            measured: 0,
            exact: None,
        }
    }

    /// Start a frame: the weights' running sums and the strata's edges; no draw yet.
    fn begin(&mut self, weights: &[f64]) {
        let n = self.order.len();
        let mut total = 0.0;
        for (j, &i) in self.order.iter().enumerate() {
            self.cumulative[j] = total;
            total += weights[i as usize];
        }
        self.cumulative[n] = total;
        self.total = total;
        self.draws.fill(0);
        self.goal.fill(FIRST_SAMPLES as u32);
        self.sum.fill(0.0);
        self.sum2.fill(0.0);
        self.contribution.fill(0.0);
        self.max_seen = 0.0;
        self.measured = 0;
        self.exact = None;
        if n <= FIRST_SAMPLES * STRATA || total <= 0.0 {
            // Too few samples to sample: measure them all.
            self.exact = Some(0.0);
            return;
        }
        // One sweep finds every stratum's edges (the boundaries increase with k).
        let width = total / STRATA as f64;
        let mut at = 0;
        for (k, edge) in self.edges.iter_mut().enumerate() {
            let u = width * k as f64;
            while at + 1 < n && self.cumulative[at + 1] <= u {
                at += 1;
            }
            *edge = at;
        }
    }

    /// Draw what the strata's goals ask for (each value divided by `centre`, the middle of
    /// its slack interval).
    fn draw(&mut self, centre: f64, distance: &mut impl FnMut(usize) -> f64) {
        if self.exact.is_some() {
            return;
        }
        let n = self.order.len();
        let width = self.total / STRATA as f64;
        for k in 0..STRATA {
            for j in self.draws[k]..self.goal[k] {
                let u = width * (k as f64 + uniform(self.seed, k, j as usize));
                // The sample whose weight interval holds u (probability ∝ weight).
                let (lo, hi) = (self.edges[k], (self.edges[k + 1] + 1).min(n));
                let at =
                    (lo + self.cumulative[lo + 1..=hi].partition_point(|&c| c <= u)).min(n - 1);
                let d = distance(self.order[at] as usize);
                self.max_seen = self.max_seen.max(d);
                self.measured += 1;
                let d = d / centre;
                self.sum[k] += d;
                self.sum2[k] += d * d;
            }
            self.draws[k] = self.goal[k].max(self.draws[k]);
        }
    }

    /// The side's mean and the variance of it, from the draws so far (0 variance once every
    /// sample was measured).
    fn summary(&mut self) -> (f64, f64) {
        if let Some(mean) = self.exact {
            return (mean, 0.0);
        }
        // Stratified sampling with replacement, probability ∝ weight within each of the
        // equal-weight strata: mean = Σ_k d̄_k / S, Var = Σ_k s_k² / m_k / S².
        let (mut mean, mut variance) = (0.0, 0.0);
        for k in 0..STRATA {
            let m = f64::from(self.draws[k]);
            let dk = self.sum[k] / m;
            let s2 = ((self.sum2[k] - m * dk * dk) / (m - 1.0)).max(0.0);
            self.contribution[k] = s2 / m;
            mean += dk;
            variance += self.contribution[k];
        }
        let strata = STRATA as f64;
        (mean / strata, variance / (strata * strata))
    }

    /// Every sample, exact up to the slack: the side's weighted mean, from then on its value.
    fn measure_all(
        &mut self,
        weights: &[f64],
        centre: f64,
        distance: &mut impl FnMut(usize) -> f64,
    ) {
        let (mut sum, mut max) = (0.0, 0.0f64);
        for (i, &w) in weights.iter().enumerate() {
            let d = distance(i);
            max = max.max(d);
            sum += w * d / centre;
        }
        self.measured += weights.len();
        self.max_seen = self.max_seen.max(max);
        self.exact = Some(if self.total > 0.0 {
            sum / self.total
        } else {
            0.0
        });
    }

    /// Whether sampling is no longer worth it after `round` refinements.
    fn exhausted(&self, round: usize) -> bool {
        self.exact.is_none() && (round > ROUNDS || self.measured > self.order.len() / 4)
    }

    fn estimate(&self, mean: f64, variance: f64, slack: f64) -> MeanEstimate {
        MeanEstimate {
            mean,
            bound: CONFIDENCE_Z * variance.sqrt() + 0.5 * slack * mean,
            max_seen: self.max_seen / (1.0 + slack),
            measured: self.measured,
        }
    }
}

/// The two sides' means (each side's own [`MeanEstimate`]) and the stated error bound of
/// their average, `deviation_mean` (module docs): within `accuracy` of it, or every sample
/// of a side whose draws passed a quarter of its samples was measured. `distance_*` return a
/// value between the exact distance of a side's sample and `1 + slack` times it.
pub(crate) fn estimate_pair(
    sides: [&mut Strata; 2],
    weights: [&[f64]; 2],
    accuracy: f64,
    slack: f64,
    mut distance_out: impl FnMut(usize) -> f64,
    mut distance_in: impl FnMut(usize) -> f64,
) -> ([MeanEstimate; 2], f64) {
    let [out, back] = sides;
    // A queried value is within [d, (1 + slack) d]; divided by 1 + slack/2 it is within
    // slack/2 of d either way.
    let centre = 1.0 + 0.5 * slack;
    out.begin(weights[0]);
    back.begin(weights[1]);
    if out.exact.is_some() {
        out.measure_all(weights[0], centre, &mut distance_out);
    }
    if back.exact.is_some() {
        back.measure_all(weights[1], centre, &mut distance_in);
    }
    let mut round = 0;
    loop {
        out.draw(centre, &mut distance_out);
        back.draw(centre, &mut distance_in);
        let ((m_out, v_out), (m_in, v_in)) = (out.summary(), back.summary());
        let mean = 0.5 * (m_out + m_in);
        let bound = CONFIDENCE_Z * (0.25 * (v_out + v_in)).sqrt() + 0.5 * slack * mean;
        if bound <= accuracy * mean || (out.exact.is_some() && back.exact.is_some()) {
            let estimates = [
                out.estimate(m_out, v_out, slack),
                back.estimate(m_in, v_in, slack),
            ];
            return (estimates, bound);
        }
        round += 1;
        // A side whose draws got past a quarter of its samples (or past the rounds) has them
        // all measured instead.
        if out.exhausted(round) {
            out.measure_all(weights[0], centre, &mut distance_out);
        }
        if back.exhausted(round) {
            back.measure_all(weights[1], centre, &mut distance_in);
        }
        // Double the draws where the variance is, over both sides' strata (Neyman
        // allocation, roughly): each stratum's share of the average's variance.
        let average = (v_out + v_in) * (STRATA * STRATA) as f64 / (2 * STRATA) as f64;
        for side in [&mut *out, &mut *back] {
            if side.exact.is_none() {
                for k in 0..STRATA {
                    if side.contribution[k] >= average {
                        side.goal[k] = 2 * side.draws[k];
                    }
                }
            }
        }
    }
}
