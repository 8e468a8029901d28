//! Safeguarded steps: a step is kept only if it made the surface better and left it sound.
//!
//! Forward Euler in curvature space (§6.1) is stable for τ < 1 on a smooth surface, but what
//! users upload is not smooth: noise, slivers and thin handles make a step at the requested τ
//! overshoot, and a classic flow (implicit MCF) pinches. [`Safeguarded`] wraps any [`Flow`]:
//!
//! - a try is **accepted** when every position and metric is finite, the Willmore energy did
//!   not rise by more than [`W_RISE`] (relative), no face turned over (its normal reversed
//!   against the last accepted surface), Q max did not more than double in one step and stays
//!   below [`Q_MAX_LIMIT`], and the closure residual stays below [`CLOSURE_LIMIT`];
//! - otherwise the flow is put back on the last accepted surface and the step is **retried at
//!   τ/2**, down to τ/2^[`MAX_HALVINGS`]; after [`GROW_AFTER`] steps accepted at their first
//!   try τ doubles again, up to the requested value (doubling after every step would retry
//!   the same too-large τ every other step);
//! - when no try is accepted the flow stays on the last accepted surface and the step fails
//!   with [`FlowError::NoProgress`], so a caller keeps that surface as its result.
//!
//! Each report carries the τ the step used and how many tries were rejected
//! ([`StepMetrics::tau`], [`StepMetrics::rejected`]). With the safeguard off (`FlowParams::
//! safeguard = false`) every step is taken at the requested τ and reported as is.

use super::{Flow, FlowError};
use crate::metrics::StepMetrics;

/// Largest relative rise of W an accepted step may have (rounding and the solver's tolerance
/// move a converged surface's W by ~1e-9; anything beyond this is the flow going uphill).
pub const W_RISE: f64 = 1e-6;
/// Largest Q max (against the input) an accepted surface may have: past this a triangle has
/// all but collapsed.
pub const Q_MAX_LIMIT: f64 = 1e3;
/// Largest closure residual an accepted step may have: 10% of the new edges' length missing
/// from the integrated surface means the step is far outside the regime it was derived for.
pub const CLOSURE_LIMIT: f64 = 0.1;
/// How many times τ is halved before the step gives up (τ/1024).
pub const MAX_HALVINGS: u32 = 10;
/// Steps accepted at their first try before τ doubles back toward the requested value.
pub const GROW_AFTER: u32 = 3;

/// What a flow must offer for [`Safeguarded`] to retry its steps.
pub trait Retry: Flow {
    /// The time step the next [`Flow::step`] takes.
    fn tau(&self) -> f64;
    /// Sets the time step of the following steps.
    fn set_tau(&mut self, tau: f64);
    /// Puts the flow back on `positions`, the surface it had after `step` steps (every cached
    /// quantity is recomputed from them).
    fn restore(&mut self, positions: &[[f64; 3]], step: usize);
    /// Whether every step should lower W and stay near integrable. Not when the flow first has
    /// to meet boundary data that differs from the input's (prescribed vectors turned by an
    /// angle, §6.3.1): bending the boundary raises W on purpose, and the turn is imposed
    /// whatever τ is, so a smaller τ would not shrink it. Finiteness, folds and Q still count.
    fn descends(&self) -> bool {
        true
    }
}

/// A flow whose steps are accepted or retried as the module docs describe.
pub struct Safeguarded<F: Retry> {
    inner: F,
    enabled: bool,
    requested_tau: f64,
    /// τ of the next first try (below `requested_tau` after a rejection, doubling back).
    next_tau: f64,
    /// Steps accepted at their first try since τ last changed.
    clean_steps: u32,
    triangles: Vec<[usize; 3]>,
    /// The last accepted surface and its metrics.
    accepted: Vec<[f64; 3]>,
    accepted_metrics: StepMetrics,
}

impl<F: Retry> Safeguarded<F> {
    pub fn new(inner: F, triangles: &[[usize; 3]], enabled: bool) -> Self {
        let requested_tau = inner.tau();
        Safeguarded {
            accepted: inner.positions().to_vec(),
            accepted_metrics: inner.initial_metrics(),
            inner,
            enabled,
            requested_tau,
            next_tau: requested_tau,
            clean_steps: 0,
            triangles: triangles.to_vec(),
        }
    }

    /// Why the surface after a try may not be kept, or `None` if it may.
    fn rejection(&self, m: &StepMetrics) -> Option<String> {
        let prev = &self.accepted_metrics;
        let finite = [
            m.willmore_energy,
            m.q_max,
            m.q_mean,
            m.closure_residual,
            m.area,
        ]
        .iter()
        .all(|x| x.is_finite())
            && self
                .inner
                .positions()
                .iter()
                .flatten()
                .all(|x| x.is_finite());
        if !finite {
            return Some("the surface is not finite".into());
        }
        let w0 = prev.willmore_energy;
        if self.inner.descends() && m.willmore_energy > w0 + W_RISE * w0.abs() {
            return Some(format!(
                "Willmore energy would rise from {w0:.6} to {:.6}",
                m.willmore_energy
            ));
        }
        if m.q_max > Q_MAX_LIMIT || m.q_max > 2.0 * prev.q_max {
            return Some(format!(
                "Q max would jump from {:.3} to {:.3}",
                prev.q_max, m.q_max
            ));
        }
        if self.inner.descends() && m.closure_residual > CLOSURE_LIMIT {
            return Some(format!(
                "closure residual {:.3} exceeds {CLOSURE_LIMIT}",
                m.closure_residual
            ));
        }
        let flipped = flipped_faces(&self.accepted, self.inner.positions(), &self.triangles);
        if flipped > 0 {
            return Some(format!("{flipped} faces would turn over"));
        }
        None
    }
}

impl<F: Retry> Flow for Safeguarded<F> {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        if !self.enabled {
            let mut m = self.inner.step()?;
            m.tau = self.requested_tau;
            return Ok(m);
        }
        let step = self.accepted_metrics.step;
        let started = std::time::Instant::now();
        let mut tau = self.next_tau;
        let mut rejected = 0u32;
        loop {
            self.inner.set_tau(tau);
            let reason = match self.inner.step() {
                Ok(mut m) => match self.rejection(&m) {
                    None => {
                        m.tau = tau;
                        m.rejected = rejected;
                        m.step_ms = started.elapsed().as_secs_f64() * 1e3;
                        self.accepted.copy_from_slice(self.inner.positions());
                        self.accepted_metrics = m;
                        self.clean_steps = if rejected == 0 {
                            self.clean_steps + 1
                        } else {
                            0
                        };
                        self.next_tau = tau;
                        if self.clean_steps >= GROW_AFTER && tau < self.requested_tau {
                            self.next_tau = (2.0 * tau).min(self.requested_tau);
                            self.clean_steps = 0;
                        }
                        return Ok(m);
                    }
                    Some(reason) => reason,
                },
                Err(FlowError::Numerical { reason, .. }) => reason,
                Err(other) => return Err(other),
            };
            self.inner.restore(&self.accepted, step);
            rejected += 1;
            if rejected > MAX_HALVINGS {
                self.inner.set_tau(self.requested_tau);
                return Err(FlowError::NoProgress {
                    step: step + 1,
                    tau,
                    reason,
                });
            }
            tau *= 0.5;
        }
    }

    fn positions(&self) -> &[[f64; 3]] {
        self.inner.positions()
    }

    fn initial_metrics(&self) -> StepMetrics {
        self.inner.initial_metrics()
    }
}

/// Faces whose normal points against their normal on `before` (a fold): `(b − a) × (c − a)`
/// before and after have a non-positive dot product, where the face had a proper normal.
pub fn flipped_faces(before: &[[f64; 3]], after: &[[f64; 3]], triangles: &[[usize; 3]]) -> usize {
    let normal = |p: &[[f64; 3]], t: &[usize; 3]| {
        let (a, b, c) = (p[t[0]], p[t[1]], p[t[2]]);
        let (u, v) = (
            [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
            [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
        );
        [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ]
    };
    triangles
        .iter()
        .filter(|t| {
            let (n0, n1) = (normal(before, t), normal(after, t));
            let had_normal = n0.iter().any(|&x| x != 0.0);
            had_normal && n0[0] * n1[0] + n0[1] * n1[1] + n0[2] * n1[2] <= 0.0
        })
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_face_turned_over_is_counted_and_a_rotated_one_is_not() {
        let before = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let tri = [[0, 1, 2]];
        // Rotated a quarter turn about z: same orientation.
        let rotated = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]];
        assert_eq!(flipped_faces(&before, &rotated, &tri), 0);
        // Mirrored through the x axis: turned over.
        let mirrored = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]];
        assert_eq!(flipped_faces(&before, &mirrored, &tri), 1);
        // Collapsed to a segment: no normal any more, counted as turned over.
        let collapsed = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
        assert_eq!(flipped_faces(&before, &collapsed, &tri), 1);
    }
}
