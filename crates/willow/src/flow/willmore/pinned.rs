//! λ with pinned vertices (§6.3.2), and the components that hold none.
//!
//! Where a component holds pinned vertices, λ minimizes `|(D − ρ)λ|²` with λ = 1 on them: a
//! linear least-squares problem `X_II λ_I = −X_IB λ_B`, not an eigenproblem. A component with
//! no pinned vertex (a region that selects a whole closed component of a multi-component
//! mesh, issue 29) has no boundary data: the same solve would give it λ = 0 and collapse it.
//! It flows as a free surface instead, by inverse iteration `(X + S) λ' = M λ` (§6.4.2), in
//! the *same* factorization: X couples no two components, so the Dirichlet rows and columns of
//! the pinned components leave the free components' block as it was, and one right-hand side
//! `b = (Dirichlet data) + M λ` (the second part on free vertices only) serves both.
//!
//! **The curvature change a held border cannot realize.** λ = 1 on the pinned vertices is
//! the whole Dirichlet data of a first-order (Dirac) system: too much for it, so
//! `(D − ρ)λ = 0` has a solution only for a thin subspace of ρ, and the least-squares λ of
//! §6.3.2 carries the rest as a residual, which is exactly the part of the new edges that is
//! not integrable. The Poisson solve (Eq. 6) then turns it into non-conformal motion. In a
//! region's flow ρ does not decay (the smooth seam's target `H − H̃` keeps a part no held
//! border allows): measured on spot's ear, ρ stays at 1.9 (rms) from step 10 on while
//! `|λ − 1|` falls to 5e-3, all of it non-integrable (closure residual 4.5e-3), so each step
//! lowers W by 0.03% and raises the region's Q by 0.5%: Q 1.43 after 20 steps, spread over
//! the whole region, not its border ring. On a genus-2 rim the same residual grows at
//! τ = 0.5 (closure 0.03 → 0.1 over ten steps) until the safeguard halves τ: Q 1.39.
//!
//! [`ConformalFlow::absorb_unrealizable_curvature`] lets the solve change ρ as well: it
//! minimizes `|(D − ρ − δ)λ|² + μ|δ|²_M` over λ (λ = 1 on pinned vertices) *and* a real δ on
//! the free vertices of pinned components, by [`ABSORB_ROUNDS`] rounds of block coordinate
//! descent: λ by the paper's least squares, then δ from the normal equations of the δ part
//! linearized at the current λ (a sparse SPD system on L's pattern), `ρ ← ρ + δ`. The part of
//! ρ the border forbids goes into δ and stops driving non-conformal motion; the realizable
//! part flows as before. δ is carried from step to step ([`ABSORB_MEMORY`]).

use super::pcg;
use super::step::{assemble_dirac_with_unit_boundary, normalize_components_where};
use super::*;
use crate::flow::dirac::{opposite_edges, sparse_matvec};
use crate::flow::dirichlet;
use crate::linalg::solver::add_diagonal;

/// μ of the absorbed curvature change, relative to the mass matrix: the δ-part's own normal
/// matrix is about `M/3` (each face adds `A_f/9` per corner pair), so μ = 0.1 lets δ take
/// most of what the residual asks while keeping its null space (δ summing to zero on every
/// face) regular. A larger μ absorbs less and lets Q creep again: on the ear's long run
/// (until converged, at most 150 steps) Q 1.28 at μ = 0.1, 1.43 at 0.3, 1.83 at 1.
const ABSORB_PENALTY: f64 = 0.1;
/// Rounds of (λ, δ) descent before the step's λ. A step factors X twice (at its start and
/// at the final ρ) and the δ-system once, whatever the rounds; the rounds in between refine
/// against their own matrices with those factors (`pcg.rs`, [`ConformalFlow::solve_dirichlet`]). One round left the ear creeping (Q 1.29 at 20 steps, 1.79
/// at 150, with the memory below); three hold it.
const ABSORB_ROUNDS: usize = 3;
/// The part of ρ a border forbids changes little from one step to the next, so each step
/// starts from the δ the earlier ones found (per unit τ), faded by this factor per step: the
/// rounds then refine instead of starting over. Measured, smooth seam, Q (area-weighted mean
/// in the region) after 20 / 150 steps and W/W₀ after 20:
/// - no absorption: ear 1.43 / (1.54 at 48, converged), genus-2 rim 1.39 / 1.72, cap
///   1.05; W/W₀ 0.70, 0.36, 0.57;
/// - three rounds, no memory: ear 1.26 / 1.48, rim 1.02, cap 1.03; W/W₀ 0.73, 0.52, 0.65;
/// - memory 0.8: ear 1.19 / 1.33, rim 1.01 / 1.02, cap 1.02 / 1.03; W/W₀ 0.74, 0.66, 0.73;
/// - memory 1 (never forget): every run stops within ten steps (ear Q 1.15) but short of
///   the descent the border allows (rim W/W₀ 0.82): ρ's realizable part is absorbed too,
///   through the step's higher-order residual.
///
/// W falls more slowly than without absorption: the faster descent was bought with
/// non-conformal motion. Per step, the carried δ comes to cancel nearly all of the request
/// (docs/algorithm.md §12: the ear keeps 2% of it at step 20, the rim and cap 11–12%); every
/// change tried against that (a floor on the kept part, μ on the total, no memory) raised the
/// ear's Q past its bound.
const ABSORB_MEMORY: f64 = 0.8;

impl ConformalFlow {
    /// λ for a flow with pinned vertices (module docs). Returns, with free components, the
    /// eigen-residual `|Xλ − γMλ| / |Xλ|` over their vertices (as a whole surface reports
    /// it); otherwise the relative residual `|X λ − b| / |b|` of the boundary-value solve.
    pub(super) fn solve_lambda_dirichlet(&mut self) -> Result<f64, FlowError> {
        let absorbing = !self.absorb_held.is_empty();
        if absorbing {
            // Start from what the last steps absorbed (fading: see ABSORB_MEMORY).
            for (r, o) in self.rho.iter_mut().zip(self.absorb_offset.iter_mut()) {
                *o *= ABSORB_MEMORY;
                *r += self.tau * *o;
            }
        }
        // The step's one factor of X: the rounds below change ρ by a little each, and their
        // solves are refined against the changed X with this factor (`pcg.rs`).
        self.factor_dirac(true)?;
        if absorbing {
            for round in 0..ABSORB_ROUNDS {
                // λ of the pinned components from their Dirichlet data alone (free
                // components get 0 here and δ = 0: they are solved below as they were).
                self.rhs.copy_from_slice(&self.solve_rhs);
                self.solve_dirichlet(round > 0, pcg::STEER_TOLERANCE)?;
                for (i, l) in self.lambda.iter_mut().enumerate() {
                    *l = Quaternion::from_complex_column([self.rhs[2 * i], self.rhs[2 * i + 1]]);
                }
                self.absorb_round(round == 0)?;
                if round + 1 < ABSORB_ROUNDS {
                    self.assemble_dirac_dirichlet()?;
                }
            }
            self.absorb_kept = Some(kept_share(
                &self.rho,
                &self.absorb_offset,
                self.tau,
                &self.geometry.vertex_areas,
                &self.absorb_held,
            ));
            // The step's λ at the final ρ: refined to the tight tolerance it takes 7–10
            // iterations (nefertiti's 5% region), and an iteration costs a fifth of a
            // factorization, so a second factor is cheaper.
            self.factor_dirac(true)?;
        }
        let any_free = self.free_component.iter().any(|&f| f);
        // The previous surface is the reference: inverse iteration starts from λ ≡ 1.
        self.lambda.fill(Quaternion::ONE);
        let rounds = if any_free { self.iterations.max(1) } else { 1 };
        for _ in 0..rounds {
            self.rhs.copy_from_slice(&self.solve_rhs);
            self.add_free_mass_lambda();
            // b, kept for the residual.
            self.product.copy_from_slice(&self.rhs);
            self.solve_rhs_with_dirac()?;
            if self
                .rhs
                .iter()
                .any(|z| !(z.re.is_finite() && z.im.is_finite()))
            {
                return Err(FlowError::Numerical {
                    step: self.step + 1,
                    reason: "the boundary-value solve for λ is not finite".into(),
                });
            }
            for (i, l) in self.lambda.iter_mut().enumerate() {
                *l = Quaternion::from_complex_column([self.rhs[2 * i], self.rhs[2 * i + 1]]);
            }
        }
        let residual = if any_free {
            self.free_eigen_residual()
        } else {
            self.dirichlet_residual()?
        };
        if any_free {
            normalize_free_components(
                &mut self.lambda,
                &self.geometry.vertex_areas,
                &self.vertex_component,
                &self.free_component,
                &mut self.component_norms,
                &mut self.component_areas,
            );
            if !self.pinned_closed {
                if let Some(exactness) = self.exactness.as_mut() {
                    // A free closed component of genus > 0: App. C's constraint holds to
                    // first order only, as on a whole surface. (Harmonic forms live on
                    // closed components; a pinned closed one would have its λ = 1 moved.)
                    exactness.project_periods(
                        &self.triangles,
                        &self.geometry.face_areas,
                        &mut self.lambda,
                    );
                }
            }
        }
        self.profile.lap("λ solve");
        Ok(residual)
    }

    /// The eigen-residual of the last inverse iteration over the free components' vertices:
    /// there `b = M λ_prev` (no pinned neighbour adds Dirichlet data), so `X λ' = b − S λ'`
    /// without a product (as [`Self::eigen_residual`] does for a whole surface); λ' is in
    /// `rhs`, b in `product`. The residual is invariant under a scale of λ', so the free
    /// components' normalization does not change it (one free component; with several, γ
    /// is shared, as it is on a whole surface's per-component scaled λ).
    fn free_eigen_residual(&self) -> f64 {
        let g = &self.geometry;
        let free = |i: usize| self.free_component[self.vertex_component[i]];
        let (mut x_dot, mut m_dot) = (0.0, 0.0);
        for i in (0..self.lambda.len()).filter(|&i| free(i)) {
            for k in [2 * i, 2 * i + 1] {
                let xl = self.product[k] - self.rhs[k] * self.shift[i];
                x_dot += (self.rhs[k].conj() * xl).re;
                m_dot += self.rhs[k].norm_sqr() * g.vertex_areas[i];
            }
        }
        let gamma = if m_dot > 0.0 { x_dot / m_dot } else { 0.0 };
        let (mut res, mut xnorm) = (0.0, 0.0);
        for i in (0..self.lambda.len()).filter(|&i| free(i)) {
            for k in [2 * i, 2 * i + 1] {
                let xl = self.product[k] - self.rhs[k] * self.shift[i];
                res += (xl - self.rhs[k] * (gamma * g.vertex_areas[i])).norm_sqr();
                xnorm += xl.norm_sqr();
            }
        }
        if xnorm > 0.0 {
            (res / xnorm).sqrt()
        } else {
            0.0
        }
    }

    /// X with the current ρ and its Dirichlet data (`dirac_values`, `solve_rhs`), with the
    /// diagonal shift of the last factorization, left unfactored: the absorbing rounds'
    /// solves refine against it ([`Self::solve_dirichlet`]).
    fn assemble_dirac_dirichlet(&mut self) -> Result<(), FlowError> {
        let (Some(pattern), Some(fixed)) = (self.dirac_pattern.as_ref(), self.fixed.as_deref())
        else {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "a fixed boundary needs the full pattern of X".into(),
            });
        };
        assemble_dirac_with_unit_boundary(
            pattern,
            fixed,
            (&self.positions, &self.triangles, &self.geometry.face_areas),
            (&self.rho, &self.shift),
            &mut self.dirac_values,
            &mut self.solve_rhs,
        );
        self.profile.lap("X assembly");
        Ok(())
    }

    /// `rhs ← X⁻¹ rhs` for the Dirichlet system in `dirac_values`: by the factor directly,
    /// or, when X changed since it was factored (`refine`), by conjugate gradients with that
    /// factor as the preconditioner to the relative residual `tolerance`, refactoring only
    /// if they stall.
    fn solve_dirichlet(&mut self, refine: bool, tolerance: f64) -> Result<(), FlowError> {
        if refine {
            let (Some(pattern), Some(factor)) =
                (self.dirac_pattern.as_ref(), self.dirac.double_mut())
            else {
                return Err(FlowError::Numerical {
                    step: self.step + 1,
                    reason: "a fixed boundary needs the double-precision factor of X".into(),
                });
            };
            let values = &self.dirac_values;
            if pcg::refine(
                |x: &[c64], y: &mut [c64]| pcg::matvec(pattern, values, x, y),
                |v: &mut [c64]| factor.solve_in_place(v, 1),
                &mut self.rhs,
                &mut self.absorb_refine_complex,
                tolerance,
            ) {
                self.profile.lap("λ refined");
                return Ok(());
            }
            // `refine` restored the right-hand side.
            self.factor_dirac(true)?;
        }
        self.solve_rhs_with_dirac()
    }

    /// Lets the λ solve change the curvature change where the held border forbids it (module
    /// docs). Needs pinned vertices.
    pub(crate) fn absorb_unrealizable_curvature(&mut self) -> Result<(), FlowError> {
        let Some(fixed) = self.fixed.as_deref() else {
            return Err(FlowError::InvalidParameter {
                name: "region",
                reason: "absorbing the curvature change needs held vertices".into(),
            });
        };
        self.absorb_held = fixed
            .iter()
            .zip(&self.vertex_component)
            .map(|(&p, &c)| p || self.free_component[c])
            .collect();
        self.absorb_delta = vec![0.0; fixed.len()];
        self.absorb_refine_real = pcg::Scratch::new(fixed.len());
        self.absorb_refine_complex = pcg::Scratch::new(2 * fixed.len());
        self.absorb_offset = vec![0.0; fixed.len()];
        self.absorb_offset_accepted = vec![0.0; fixed.len()];
        Ok(())
    }

    /// Puts a checkpoint's absorbed change (per unit τ) back as the offset the next step
    /// starts from ([`super::super::safeguard::Retry::carry`]); empty: none absorbed (a
    /// checkpoint from before it was kept). An error, with nothing changed, when it does
    /// not fit this flow.
    pub(super) fn carry_absorbed(&mut self, absorbed: &[f64]) -> Result<(), FlowError> {
        let refuse = |reason: String| {
            Err(FlowError::InvalidParameter {
                name: "checkpoint",
                reason,
            })
        };
        if !absorbed.is_empty() && absorbed.len() != self.absorb_offset.len() {
            return refuse(format!(
                "holds an absorbed curvature change for {} vertices, the flow absorbs on {}",
                absorbed.len(),
                self.absorb_offset.len()
            ));
        }
        if let Some(v) = absorbed.iter().position(|d| !d.is_finite()) {
            return refuse(format!(
                "holds a non-finite absorbed curvature change at vertex {v}"
            ));
        }
        if absorbed.is_empty() {
            self.absorb_offset.fill(0.0);
        } else {
            self.absorb_offset.copy_from_slice(absorbed);
        }
        self.absorb_offset_accepted
            .copy_from_slice(&self.absorb_offset);
        Ok(())
    }

    /// One δ-step (module docs): with the face residual `r_f = Σ_i c_i λ_i`, `c_i = e_i/(2√A)
    /// + ρ_i √A/3` (App. G's X is `Σ_f c_fᴴ c_f`), a change δ of ρ adds `(√A/3) Σ_i δ_i λ_i` to
    /// it; minimizing `Σ_f |r_f + (√A/3) Σ_i δ_i λ_i|² + μ Σ_i A_i δ_i²` gives
    /// `(G + μM) δ = −Σ_f (√A/3) Re(λ̄_i r_f)` with `G_ij = Σ_f (A_f/9) Re(λ̄_i λ_j)`, δ = 0
    /// on `absorb_held`. Solved with L's factor (refactored by the Poisson solve later).
    fn absorb_round(&mut self, first: bool) -> Result<(), FlowError> {
        let g = &self.geometry;
        let pattern = &self.laplace_pattern;
        let values = &mut self.laplace_values;
        let delta = &mut self.absorb_delta;
        values.fill(0.0);
        delta.fill(0.0);
        for ((tri, slots), &area) in self
            .triangles
            .iter()
            .zip(&pattern.face_slots)
            .zip(&g.face_areas)
        {
            let e = opposite_edges(&self.positions, tri);
            let root = area.sqrt();
            let mut r = Quaternion::default();
            for k in 0..3 {
                let c = e[k].scale(0.5 / root) + Quaternion::real(self.rho[tri[k]] * root / 3.0);
                r += c * self.lambda[tri[k]];
            }
            for a in 0..3 {
                let la = self.lambda[tri[a]].conj();
                delta[tri[a]] -= root / 3.0 * (la * r).w;
                for b in 0..3 {
                    let slot = pattern.entry(slots[3 * a + b], tri[b], 0, 0);
                    values[slot] += area / 9.0 * (la * self.lambda[tri[b]]).w;
                }
            }
        }
        add_diagonal(
            pattern,
            g.vertex_areas.iter().map(|&a| ABSORB_PENALTY * a),
            values,
        );
        // δ = 0 off the free vertices of pinned components: identity rows, zero data.
        let held = &self.absorb_held;
        dirichlet::apply_real(pattern, values, held, |_, _| 0.0, Some(&mut delta[..]), 1);
        for (d, &h) in delta.iter_mut().zip(held) {
            if h {
                *d = 0.0;
            }
        }
        // The step's first round factors the system; the later ones (λ moved a little)
        // refine against their own matrix with that factor (`pcg.rs`), refactoring only if
        // the refinement stalls.
        let refined = !first
            && pcg::refine(
                |x: &[f64], y: &mut [f64]| pcg::matvec(pattern, values, x, y),
                |v: &mut [f64]| self.laplace.solve_in_place(v, 1),
                delta,
                &mut self.absorb_refine_real,
                pcg::REFINE_TOLERANCE,
            );
        if !refined {
            self.laplace
                .factorize(pattern, values)
                .map_err(|e| FlowError::Numerical {
                    step: self.step + 1,
                    reason: format!("the absorbed curvature change: {e}"),
                })?;
            self.laplace.solve_in_place(delta, 1);
        }
        self.profile.lap("absorbed change");
        if delta.iter().any(|d| !d.is_finite()) {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "the absorbed curvature change is not finite".into(),
            });
        }
        for ((r, d), o) in self
            .rho
            .iter_mut()
            .zip(delta.iter())
            .zip(self.absorb_offset.iter_mut())
        {
            *r += d;
            *o += d / self.tau;
        }
        Ok(())
    }

    /// `rhs += M λ` on the vertices of free components.
    fn add_free_mass_lambda(&mut self) {
        let g = &self.geometry;
        for (i, ((l, &a), &c)) in self
            .lambda
            .iter()
            .zip(&g.vertex_areas)
            .zip(&self.vertex_component)
            .enumerate()
        {
            if self.free_component[c] {
                let [z0, z1] = l.scale(a).to_complex_column();
                self.rhs[2 * i] += z0;
                self.rhs[2 * i + 1] += z1;
            }
        }
    }

    /// `|X λ − b| / |b|` of the boundary-value solve, λ in `rhs`, `b` the Dirichlet data.
    fn dirichlet_residual(&mut self) -> Result<f64, FlowError> {
        let pattern = self
            .dirac_pattern
            .as_ref()
            .ok_or_else(|| FlowError::Numerical {
                step: self.step + 1,
                reason: "a fixed boundary needs the full pattern of X".into(),
            })?;
        sparse_matvec(pattern, &self.dirac_values, &self.rhs, &mut self.product);
        let (mut res, mut norm) = (0.0, 0.0);
        for (p, b) in self.product.iter().zip(&self.solve_rhs) {
            res += (p - b).norm_sqr();
            norm += b.norm_sqr();
        }
        Ok(if norm > 0.0 { (res / norm).sqrt() } else { 0.0 })
    }
}

/// The part of the requested curvature change `ρ_req` the final `rho` still aims at,
/// `⟨ρ, ρ_req⟩_M / |ρ_req|²_M` over the vertices not `held` ([`Flow::kept_share`]). What was
/// absorbed this step and carried from earlier ones is `τ · offset` (the offset is the
/// absorbed change per unit τ), so `ρ_req = ρ − τ · offset`; 1 when nothing was requested.
fn kept_share(rho: &[f64], offset: &[f64], tau: f64, areas: &[f64], held: &[bool]) -> f64 {
    let (mut along, mut requested) = (0.0, 0.0);
    for i in (0..rho.len()).filter(|&i| !held[i]) {
        let r = rho[i] - tau * offset[i];
        along += areas[i] * rho[i] * r;
        requested += areas[i] * r * r;
    }
    if requested > 0.0 {
        along / requested
    } else {
        1.0
    }
}

/// [`normalize_per_component`] on the free components only: a pinned component's λ is the
/// boundary-value solution, whose scale the pinned λ = 1 sets.
fn normalize_free_components(
    lambda: &mut [Quaternion],
    areas: &[f64],
    vertex_component: &[usize],
    free: &[bool],
    norms: &mut [f64],
    component_areas: &mut [f64],
) {
    normalize_components_where(
        lambda,
        areas,
        vertex_component,
        norms,
        component_areas,
        |c| free[c],
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::safeguard::Retry;

    /// A try the safeguard refuses does not leave its absorbed curvature change behind: after
    /// `restore` the offset is the accepted steps' again, so the retry takes exactly the
    /// step a flow that never tried the refused one takes (`pinned.rs`, ABSORB_MEMORY).
    #[test]
    fn a_refused_try_leaves_no_absorbed_change_behind() {
        use crate::mesh::generate::{bumpy_cap, with_noise};
        let mesh = with_noise(bumpy_cap(3, 0.06), 0.05, 11);
        let pinned: Vec<bool> = mesh
            .positions
            .iter()
            .map(|p| p[0].abs() > 0.4 || p[1].abs() > 0.4)
            .collect();
        let build = || {
            let mut flow =
                ConformalFlow::with_pinned(&mesh, &FlowParams::default(), pinned.clone(), None)
                    .expect("flow");
            flow.absorb_unrealizable_curvature().expect("absorbs");
            flow.step().expect("step 1");
            flow
        };
        let mut tried = build();
        let accepted = tried.positions.clone();
        let offset = tried.absorb_offset.clone();
        assert!(
            offset.iter().any(|&o| o != 0.0),
            "step 1 absorbed something"
        );
        tried.step().expect("the try");
        assert_ne!(tried.absorb_offset, offset, "the try changed the offset");
        tried.restore(&accepted, 1);
        assert_eq!(tried.absorb_offset, offset, "restore puts it back");
        tried.set_tau(0.25);
        let retry = tried.step().expect("the retry");
        let mut direct = build();
        direct.set_tau(0.25);
        let step = direct.step().expect("the same step");
        // The same to rounding (the restored surface's geometry is recomputed).
        let scale = direct
            .absorb_offset
            .iter()
            .fold(0.0f64, |m, o| m.max(o.abs()));
        for (a, b) in tried.absorb_offset.iter().zip(&direct.absorb_offset) {
            assert!((a - b).abs() <= 1e-9 * scale, "offset {a} vs {b}");
        }
        let (a, b) = (retry.willmore_energy, step.willmore_energy);
        assert!((a - b).abs() <= 1e-12 * b, "W {a} vs {b}");
    }
}
