//! A stratified estimate of one side's area-weighted mean distance with its error bound
//! (used by [`super::distance::Deviation`] for `deviation_mean`).
//!
//! The mean needs 1% accuracy (issue 29), not every sample. The samples are laid out in a
//! fixed, spatially coherent order (the faces they lie on, along the input tree's leaves) and
//! cut each frame into [`STRATA`] runs of equal weight (area): each stratum is a patch of
//! the surface over which the distance, a 1-Lipschitz function, varies little. Each stratum
//! draws samples with probability proportional to their weight (with replacement), so its
//! draws' plain mean estimates its weighted mean without bias, and the strata's estimates
//! average to the side's (stratified sampling with probabilities proportional to size:
//! Cochran, *Sampling Techniques*, 3rd ed., §5.3 and §9A.3). The variance comes from the
//! draws' own spread, `Var = Σ_k s_k² / m_k / S²`. The stated bound is [`CONFIDENCE_Z`]
//! standard errors plus half the nearest-point queries' slack (each value is re-centred in its
//! slack interval); while it is wider than the accuracy asked, the strata holding most of the
//! variance double their draws, and past a quarter of the samples every sample is measured
//! (exact up to the slack).
//!
//! Equal-weight strata and weight-proportional draws matter: a flow can shrink or grow face
//! areas by orders of magnitude (nefertiti at τ 0.5), and equal-count strata sampled
//! uniformly then have a standard error of several percent at 2,000 draws.
//!
//! Which samples are measured depends only on the weights, the fixed pseudo-random draws and
//! the distances measured, never on what was remembered from the last frame.

/// Strata per side: with [`FIRST_SAMPLES`] each, about 2,000 queries per side on a large
/// mesh; on nefertiti (100k triangles) the first round's bound is near 1% and one round of
/// refinement (about 2,400 draws per side) brings it below.
pub const STRATA: usize = 1024;
/// Samples measured first in each stratum: two, the fewest that give a variance.
const FIRST_SAMPLES: usize = 2;
/// Standard errors in the stated bound: 3 (a two-sided normal interval of 99.7%; the
/// estimate is a sum over a thousand strata, so the normal approximation holds).
pub const CONFIDENCE_Z: f64 = 3.0;
/// Refinement rounds before every sample is measured: each round doubles the draws of the
/// strata above the mean variance contribution.
const ROUNDS: usize = 6;

/// A side's mean and what it knows about its error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeanEstimate {
    /// Weighted mean distance (estimated).
    pub mean: f64,
    /// The stated error bound: the true mean is within `mean ± bound` (module docs).
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
}

/// A number in [0, 1) from two integers: splitmix64 of their combination (reproducible
/// pseudo-random draws, the same every frame and every run).
fn uniform(k: usize, j: usize) -> f64 {
    let mut z = (k as u64)
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
    pub(crate) fn new(owner: &[u32], face_order: &[u32]) -> Self {
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
        }
    }

    /// The weighted mean of `distance(i)` over every sample i (weights `weights`) to within
    /// `accuracy` relative, as [`MeanEstimate::bound`] states (module docs). `distance`
    /// returns a value between the exact distance and `1 + slack` times it. A side of at
    /// most [`STRATA`]·[`FIRST_SAMPLES`] samples, or one whose bound stays wide, has every
    /// sample measured.
    pub(crate) fn estimate(
        &mut self,
        weights: &[f64],
        accuracy: f64,
        slack: f64,
        mut distance: impl FnMut(usize) -> f64,
    ) -> MeanEstimate {
        let n = self.order.len();
        let mut total = 0.0;
        for (j, &i) in self.order.iter().enumerate() {
            self.cumulative[j] = total;
            total += weights[i as usize];
        }
        self.cumulative[n] = total;
        // A queried value is within [d, (1 + slack) d]; divided by 1 + slack/2 it is within
        // slack/2 of d either way.
        let centre = 1.0 + 0.5 * slack;
        let mut max_seen = 0.0f64;
        let mut measured = 0;
        if n > FIRST_SAMPLES * STRATA && total > 0.0 {
            self.draws.fill(0);
            self.sum.fill(0.0);
            self.sum2.fill(0.0);
            let width = total / STRATA as f64;
            // One sweep finds every stratum's edges (the boundaries increase with k).
            let mut at = 0;
            for (k, edge) in self.edges.iter_mut().enumerate() {
                let u = width * k as f64;
                while at + 1 < n && self.cumulative[at + 1] <= u {
                    at += 1;
                }
                *edge = at;
            }
            let mut goal = vec![FIRST_SAMPLES as u32; STRATA];
            for _ in 0..=ROUNDS {
                for k in 0..STRATA {
                    for j in self.draws[k]..goal[k] {
                        let u = width * (k as f64 + uniform(k, j as usize));
                        // The sample whose weight interval holds u (probability ∝ weight).
                        let (lo, hi) = (self.edges[k], (self.edges[k + 1] + 1).min(n));
                        let at = (lo + self.cumulative[lo + 1..=hi].partition_point(|&c| c <= u))
                            .min(n - 1);
                        let d = distance(self.order[at] as usize);
                        max_seen = max_seen.max(d);
                        measured += 1;
                        let d = d / centre;
                        self.sum[k] += d;
                        self.sum2[k] += d * d;
                    }
                    self.draws[k] = goal[k].max(self.draws[k]);
                }
                // Stratified sampling with replacement, probability ∝ weight within each of
                // the equal-weight strata: mean = Σ_k d̄_k / S, Var = Σ_k s_k² / m_k / S².
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
                let (mean, variance) = (mean / strata, variance / (strata * strata));
                let bound = CONFIDENCE_Z * variance.sqrt() + 0.5 * slack * mean;
                if bound <= accuracy * mean {
                    return MeanEstimate {
                        mean,
                        bound,
                        max_seen: max_seen / (1.0 + slack),
                        measured,
                    };
                }
                if measured > n / 4 {
                    break;
                }
                // Double the draws where the variance is (Neyman allocation, roughly).
                let average = variance * strata * strata / strata;
                for k in 0..STRATA {
                    if self.contribution[k] >= average {
                        goal[k] = 2 * self.draws[k];
                    }
                }
            }
        }
        // Every sample: exact up to the slack.
        let (mut sum, mut max) = (0.0, 0.0f64);
        for (i, &w) in weights.iter().enumerate() {
            let d = distance(i);
            max = max.max(d);
            sum += w * d / centre;
        }
        let mean = if total > 0.0 { sum / total } else { 0.0 };
        MeanEstimate {
            mean,
            bound: 0.5 * slack * mean,
            max_seen: max.max(max_seen) / (1.0 + slack),
            measured: measured + n,
        }
    }
}
