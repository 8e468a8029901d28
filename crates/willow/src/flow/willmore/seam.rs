//! The smooth seam of a region (issue 29 item 1): the flow's fixed points continue the
//! surroundings instead of flattening the region against its border.
//!
//! With pinned vertices (a fixed boundary, §6.3.2: λ = 1 and the input position there) and
//! no constraints, the flow `ρ = −2τH` stops where `H = 0` at every free vertex: the region
//! becomes the discrete minimal surface spanning its held rings and meets them at whatever
//! angle that surface makes. λ = 1 holds the tangent planes of the held faces (the paper's
//! boundary frame, §6.3.1), but the first free faces still turn as far as `H → 0` asks:
//! `H = 0` is a second-order condition, and position *and* tangent plane on the border are
//! one condition too many for it (measured on spot's ear, 20 steps: the border's mean normal
//! jump 8.7° → 18.9° with two held rings, 37° with one).
//!
//! The smooth seam flows toward `H̃` instead, `ρ = −2τ(H − H̃)`, where `H̃` is the harmonic
//! extension (`L H̃ = 0` on the free vertices, cotan L) of the *current* mean curvature on the
//! held vertices, recomputed every step. The fixed points satisfy `ΔH = 0` on the free
//! vertices: the Willmore equation `ΔH + 2H(H² − K) = 0` without its cubic term, a
//! fourth-order condition that takes both the border's positions and its tangent planes (the
//! two held rings) as boundary data, like the clamped Willmore problem. A crease at the seam
//! raises |H| on the held ring next to it, which `H̃` carries inward, so the region bends back
//! toward the surroundings' tangent plane (measured, 20 steps: spot's ear 8.7° → 11.6°, a
//! genus-2 rim 5.7° → 8.3°, an open cap 4.5° → 5.4°; with the unrealizable part of ρ absorbed,
//! `pinned.rs`: 8.7°, 5.1°, 5.3°). The target is recomputed every step on purpose: frozen
//! after the first step, W stalls (ear 6.47 from 8.43 with τ halved to 1/256; genus-2 rim
//! 4.64 at 100 steps against 4.05 updated). `H̃` is harmonic, so the detail inside
//! (the part of H a harmonic function cannot hold) is still removed.

use super::*;
use crate::flow::dirichlet;
use crate::linalg::solver::add_diagonal;

impl ConformalFlow {
    /// Makes the flow drive toward the harmonic extension of the pinned vertices' mean
    /// curvature (see the module's comment). Needs pinned vertices.
    pub(crate) fn continue_pinned_curvature(&mut self) -> Result<(), FlowError> {
        if self.fixed.is_none() {
            return Err(FlowError::InvalidParameter {
                name: "seam",
                reason: "a smooth seam needs held vertices".into(),
            });
        }
        self.curvature_target = Some(vec![0.0; self.positions.len()]);
        self.direction_ready = false;
        Ok(())
    }

    /// `H̃` of the current surface into `curvature_target`. Needs
    /// [`Self::assemble_laplacian`] first; uses L's factor, which the Poisson solve
    /// refactors later in the step.
    pub(super) fn seam_target(&mut self) -> Result<(), FlowError> {
        let Some(mut target) = self.curvature_target.take() else {
            return Ok(());
        };
        let solved = self.harmonic_extension(&mut target);
        // Kept whatever happened: a retried step must still flow toward a target.
        self.curvature_target = Some(target);
        solved
    }

    /// `L H̃ = 0` on the free vertices, `H̃ = H` on the pinned ones, into `target`.
    fn harmonic_extension(&mut self, target: &mut [f64]) -> Result<(), FlowError> {
        let Some(pinned) = self.fixed.as_deref() else {
            return Ok(());
        };
        let g = &self.geometry;
        let n = self.positions.len();
        self.laplace_values.copy_from_slice(&self.laplace_unshifted);
        // The Poisson solve's shift (εM): a free component that touches no pinned vertex (a
        // region holding a whole closed component) gets H̃ = 0 instead of a singular solve.
        let mean_area = g.total_area() / n as f64;
        let trace: f64 = g.cotangents.iter().map(|c| c[0] + c[1] + c[2]).sum();
        let eps = POISSON_SHIFT * trace / n as f64;
        add_diagonal(
            &self.laplace_pattern,
            g.vertex_areas.iter().map(|&a| eps * a / mean_area),
            &mut self.laplace_values,
        );
        let held = &g.mean_curvature;
        target.fill(0.0);
        dirichlet::apply_real(
            &self.laplace_pattern,
            &mut self.laplace_values,
            pinned,
            |v, _| held[v],
            Some(&mut target[..]),
            1,
        );
        // The pinned rows are the identity: their right-hand side is the held value itself.
        for (t, (&p, &h)) in target.iter_mut().zip(pinned.iter().zip(held)) {
            if p {
                *t = h;
            }
        }
        self.laplace
            .factorize(&self.laplace_pattern, &self.laplace_values)
            .map_err(|e| FlowError::Numerical {
                step: self.step + 1,
                reason: format!("the seam's curvature extension: {e}"),
            })?;
        self.laplace.solve_in_place(target, 1);
        if target.iter().any(|t| !t.is_finite()) {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "the seam's curvature extension is not finite".into(),
            });
        }
        Ok(())
    }
}
