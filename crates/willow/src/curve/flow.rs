//! The isometric curve flow (§5): its parameters, per-step metrics and the flow itself.

use super::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Parameters of a curve flow.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CurveParams {
    /// Time step with the paper's meaning (§4 eq. 2): unconstrained curvature is updated as
    /// `κ ← (1 − 2τ)κ`, stable for `0 < τ < 1`. The default 0.5 removes all curvature outside
    /// the constraint span `{1, fˣ, fʸ}` in one step, the fastest descent: the noisy test curve
    /// (r = 1 + 0.2 sin 5t + jitter, 256 vertices) has σ(κ)/κ̄ ≈ 2e-3 after one step (§5 says
    /// "about six" steps to the minimum). At τ = 0.9 the same curve still has σ/κ̄ ≈ 1.9 after
    /// ten steps: the factor (1 − 2τ) = −0.8 overshoots and decays slowly.
    pub tau: f64,
}

impl Default for CurveParams {
    fn default() -> Self {
        CurveParams { tau: 0.5 }
    }
}

/// What a curve flow step reports about the curve it produced (step 0 is the input).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurveStepMetrics {
    /// Steps taken so far; 0 is the input.
    pub step: usize,
    /// `E_C = Σ κ_i² ℓ*_i` (§5), κ from the turning angles and the input dual lengths.
    pub energy: f64,
    /// Length-weighted `σ(κ)/|κ̄|` (see [`curvature_std_over_mean`]): 0 for a circle; `+∞` when
    /// κ̄ = 0 but κ varies (serialized as JSON `null`).
    pub curvature_std_over_mean: f64,
    /// `max_ij |ℓ̃_ij / ℓ_ij − 1|` against the input lengths: the isometry error (Figure 11).
    pub max_edge_length_distortion: f64,
    /// Closed curves: `|Σ T̃_ij| / Σ ℓ_ij`, how far the integrated tangents fail to close before
    /// the Poisson projection (Figure 11, top center). 0 for open curves and at step 0.
    pub closure_gap: f64,
    /// Relative residual of the Poisson solve, [`poisson_residual`]. 0 at step 0.
    pub poisson_residual: f64,
    /// `Σ ℓ̃`, the current length (the input length, up to the isometry error).
    pub total_length: f64,
    /// `Σ φ_i = Σ κ_i ℓ*_i`; `2πk` for a closed curve of turning number k.
    pub total_curvature: f64,
    /// Wall time of the step in milliseconds, metrics included. 0 at step 0.
    pub step_ms: f64,
}

/// One running isometric curve flow (§5). Build it once, then call [`CurveFlow::step`]; each
/// step is O(n) and allocation-free (all buffers and the Poisson factor are made in `new`).
#[derive(Clone, Debug)]
pub struct CurveFlow {
    curve: Curve,
    tau: f64,
    step: usize,
    /// ℓ of the input curve, the invariant of the flow (§5.2).
    edge_lengths: Vec<f64>,
    /// `1/ℓ`, used by the divergence and the residual.
    inv_edge_lengths: Vec<f64>,
    /// `ℓ*` from the input lengths.
    dual_lengths: Vec<f64>,
    /// `1/ℓ*`.
    inv_dual_lengths: Vec<f64>,
    /// `Σ ℓ`, the input length.
    length: f64,
    /// `R_i = Σ_{k≥i} ℓ_k`, for the mean change of angle (index 0 unused).
    suffix_lengths: Vec<f64>,
    /// Pinned Poisson factor; depends only on ℓ, so it is built once.
    poisson: CurvePoisson,
    /// φ of the current curve (kept from the last step's metrics, so each step calls atan2
    /// once per vertex).
    turning: Vec<f64>,
    /// κ of the current curve, then (during a step) the flow direction v.
    kappa: Vec<f64>,
    velocity: Vec<f64>,
    theta: Vec<f64>,
    /// ℓ̃ of the current curve, for the metrics.
    current_lengths: Vec<f64>,
    /// α_k of [`edge_rotations`], one per edge.
    edge_rotation: Vec<f64>,
    tangents: Vec<[f64; 2]>,
    rhs: Vec<[f64; 2]>,
    /// The next positions; swapped with `curve.points` at the end of a step.
    /// (`theta` holds the change of each edge angle, Δ_k, during a step.)
    next: Vec<[f64; 2]>,
    initial: CurveStepMetrics,
    last: CurveStepMetrics,
}

impl CurveFlow {
    /// Validate the curve and the parameters (`0 < τ < 1`, §4), allocate every buffer and
    /// factor the Poisson matrix.
    pub fn new(curve: Curve, params: CurveParams) -> Result<Self, CurveError> {
        curve.validate()?;
        let tau = params.tau;
        if !(tau > 0.0 && tau < 1.0) {
            return Err(CurveError::InvalidParameter {
                name: "tau",
                reason: format!("{tau} is outside (0, 1), where the flow is stable (§4)"),
            });
        }
        let n = curve.points.len();
        let m = curve.edge_count();
        let mut edge_lengths_buf = zeroed(m)?;
        edge_lengths(&curve.points, curve.closed, &mut edge_lengths_buf);
        let mut inv_edge_lengths = zeroed(m)?;
        for (inv, l) in inv_edge_lengths.iter_mut().zip(&edge_lengths_buf) {
            *inv = 1.0 / l;
        }
        let mut dual = zeroed(n)?;
        dual_lengths(&edge_lengths_buf, curve.closed, &mut dual);
        let poisson = CurvePoisson::new(&edge_lengths_buf, curve.closed)?;
        let length: f64 = edge_lengths_buf.iter().sum();
        let mut inv_dual_lengths = zeroed(n)?;
        for (inv, d) in inv_dual_lengths.iter_mut().zip(&dual) {
            *inv = 1.0 / d;
        }
        let mut suffix_lengths = zeroed(m)?;
        let mut suffix = 0.0;
        for (r, l) in suffix_lengths.iter_mut().zip(&edge_lengths_buf).rev() {
            suffix += l;
            *r = suffix;
        }
        let mut turning = zeroed(n)?;
        turning_angles(&curve.points, curve.closed, &mut turning);
        let zero_metrics = CurveStepMetrics {
            step: 0,
            energy: 0.0,
            curvature_std_over_mean: 0.0,
            max_edge_length_distortion: 0.0,
            closure_gap: 0.0,
            poisson_residual: 0.0,
            total_length: 0.0,
            total_curvature: 0.0,
            step_ms: 0.0,
        };
        let mut flow = CurveFlow {
            tau,
            step: 0,
            edge_lengths: edge_lengths_buf,
            inv_edge_lengths,
            dual_lengths: dual,
            poisson,
            length,
            inv_dual_lengths,
            suffix_lengths,
            turning,
            kappa: zeroed(n)?,
            velocity: zeroed(n)?,
            theta: zeroed(m)?,
            current_lengths: zeroed(m)?,
            edge_rotation: zeroed(m)?,
            tangents: zeroed(m)?,
            rhs: zeroed(n)?,
            next: zeroed(n)?,
            initial: zero_metrics,
            last: zero_metrics,
            curve,
        };
        flow.initial = flow.measure(0.0, 0.0, 0.0);
        flow.last = flow.initial;
        Ok(flow)
    }

    /// Advance one step (Table 1, left column) and report the metrics of the new curve.
    pub fn step(&mut self) -> CurveStepMetrics {
        let start = Instant::now();
        let closed = self.curve.closed;
        let n = self.curve.points.len();

        // I. Curvature of the current curve: `measure`, at the end of the last step (or in
        // `new`), left it in `self.kappa`.

        // II. Flow direction v = −2κ (§4 eq. 1).
        for (v, k) in self.velocity.iter_mut().zip(&self.kappa) {
            *v = -2.0 * k;
        }
        // III–IV. Closed curves: project out {1, fˣ, fʸ} (§5, App. A).
        if closed {
            project_out_closure_constraints(
                &self.curve.points,
                &self.dual_lengths,
                &mut self.velocity,
            );
        }
        // V. κ̃ = κ + τ v (§4 eq. 2 with the projected direction).
        for (k, v) in self.kappa.iter_mut().zip(&self.velocity) {
            *k += self.tau * v;
        }

        // VI. New tangents. §5.2 sums θ_k = θ_0 + Σ_{i≤k} ℓ*_i κ̃_i ([`tangent_angles`]) and
        // sets T̃_k = ℓ_k (cos θ_k, sin θ_k) ([`tangents`]). The current edge angles are the
        // same sum over the current turning angles φ_i, so θ_k is the current angle plus the
        // change Δ_k = Σ_{1≤i≤k} δ_i, δ_i = ℓ*_i κ̃_i − φ_i, and we rotate each current unit
        // edge by Δ_k ([`rotate_edges`]): the same tangents, with a short series instead of
        // sin_cos once the flow is near its minimum and the changes are small.
        //
        // §5.1: remove the mean change of angle, length-weighted over edges. Swapping sums,
        // `Σ_k ℓ_k Δ_k = Σ_{i≥1} δ_i R_i` with the suffix lengths `R_i = Σ_{k≥i} ℓ_k` (fixed,
        // since ℓ is): one dot product. (Vertex 0 does not enter: for a closed curve its turn
        // is the closing one.)
        let m = self.theta.len();
        let mean_change = {
            let (d, k, phi, r) = (
                &self.dual_lengths[1..m],
                &self.kappa[1..m],
                &self.turning[1..m],
                &self.suffix_lengths[1..m],
            );
            sum4(m - 1, |i| (d[i] * k[i] - phi[i]) * r[i]) / self.length
        };
        let mut change = -mean_change;
        for (k, delta) in self.theta.iter_mut().enumerate() {
            if k > 0 {
                change += self.dual_lengths[k] * self.kappa[k] - self.turning[k];
            }
            *delta = change;
        }
        rotate_edges(
            &self.curve.points,
            &self.theta,
            &self.edge_lengths,
            &mut self.tangents,
        );
        let closure_gap = if closed {
            let t = &self.tangents[..];
            let gap_x = sum4(t.len(), |i| t[i][0]);
            let gap_y = sum4(t.len(), |i| t[i][1]);
            gap_x.hypot(gap_y) / self.length
        } else {
            0.0
        };

        // VII. Positions: L f̃ = ∇·T̃ (§5.2), then restore the mean position (§5.1).
        divergence(
            &self.tangents,
            &self.inv_edge_lengths,
            closed,
            &mut self.rhs,
        );
        self.poisson.solve(&self.rhs, &mut self.next);
        let residual = poisson_residual(&self.inv_edge_lengths, closed, &self.next, &self.rhs);
        let shift = {
            let (old, new) = (&self.curve.points[..n], &self.next[..n]);
            let inv_n = 1.0 / n as f64;
            [
                sum4(n, |i| old[i][0] - new[i][0]) * inv_n,
                sum4(n, |i| old[i][1] - new[i][1]) * inv_n,
            ]
        };
        for p in &mut self.next {
            p[0] += shift[0];
            p[1] += shift[1];
        }
        std::mem::swap(&mut self.curve.points, &mut self.next);
        self.step += 1;

        // Turning angles of the new curve, for the metrics and the next step, without an atan2
        // per vertex: see `update_turning_angles`.
        edge_rotations(&self.tangents, &self.curve.points, &mut self.edge_rotation);
        update_turning_angles(
            &self.kappa,
            &self.dual_lengths,
            &self.edge_rotation,
            closed,
            &mut self.turning,
        );
        #[cfg(debug_assertions)]
        self.debug_check_turning();
        self.last = self.measure(closure_gap, residual, 0.0);
        // Measured last, so the metrics pass counts as part of the step.
        self.last.step_ms = start.elapsed().as_secs_f64() * 1e3;
        self.last
    }

    /// Debug builds: the incrementally updated turning angles equal atan2 of the edges.
    #[cfg(debug_assertions)]
    fn debug_check_turning(&self) {
        let p = &self.curve.points;
        let (n, m) = (p.len(), self.edge_lengths.len());
        for i in 0..n {
            if !self.curve.closed && (i == 0 || i == n - 1) {
                continue;
            }
            let a = edge_vector(p, (i + m - 1) % m);
            let b = edge_vector(p, i);
            let direct = (a[0] * b[1] - a[1] * b[0]).atan2(a[0] * b[0] + a[1] * b[1]);
            let diff = wrap_angle(self.turning[i] - direct);
            debug_assert!(
                diff.abs() < 1e-9,
                "turning angle {i}: updated {} vs atan2 {direct}",
                self.turning[i]
            );
        }
    }

    /// Metrics of the current curve; `self.turning` must be current. Leaves `self.kappa`
    /// holding κ of the current curve.
    fn measure(
        &mut self,
        closure_gap: f64,
        poisson_residual: f64,
        step_ms: f64,
    ) -> CurveStepMetrics {
        // κ = φ/ℓ* as in [`curvature`], by a multiplication: a division per vertex is the
        // slowest arithmetic left in the step.
        for ((k, phi), inv) in self
            .kappa
            .iter_mut()
            .zip(&self.turning)
            .zip(&self.inv_dual_lengths)
        {
            *k = phi * inv;
        }
        let current = &mut self.current_lengths;
        edge_lengths(&self.curve.points, self.curve.closed, current);
        let m = current.len();
        let (current, inv) = (&current[..m], &self.inv_edge_lengths[..m]);
        let total_length = sum4(m, |i| current[i]);
        let distortion = max4(m, |i| (current[i] * inv[i] - 1.0).abs());
        let turning = &self.turning[..];
        CurveStepMetrics {
            step: self.step,
            energy: curvature_energy(&self.kappa, &self.dual_lengths),
            curvature_std_over_mean: curvature_std_over_mean(&self.kappa, &self.dual_lengths),
            max_edge_length_distortion: distortion,
            closure_gap,
            poisson_residual,
            total_length,
            total_curvature: sum4(turning.len(), |i| turning[i]),
            step_ms,
        }
    }

    /// Current positions, in input order.
    pub fn points(&self) -> &[[f64; 2]] {
        &self.curve.points
    }

    /// The current curve.
    pub fn curve(&self) -> &Curve {
        &self.curve
    }

    /// κ of the current curve: its turning angles over the **input** dual lengths.
    pub fn curvature(&self) -> &[f64] {
        &self.kappa
    }

    /// The input edge lengths ℓ, which the flow preserves.
    pub fn edge_lengths(&self) -> &[f64] {
        &self.edge_lengths
    }

    /// The time step τ.
    pub fn tau(&self) -> f64 {
        self.tau
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> usize {
        self.step
    }

    /// Metrics of the input curve (step 0).
    pub fn initial_metrics(&self) -> CurveStepMetrics {
        self.initial
    }

    /// Metrics of the current curve (the last step's, or the input's before any step).
    pub fn last_metrics(&self) -> CurveStepMetrics {
        self.last
    }
}
