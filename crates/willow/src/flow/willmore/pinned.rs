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

use super::*;
use crate::flow::dirac::sparse_matvec;

impl ConformalFlow {
    /// λ for a flow with pinned vertices (module docs). Returns, with free components, the
    /// eigen-residual `|Xλ − γMλ| / |Xλ|` over their vertices (as a whole surface reports
    /// it); otherwise the relative residual `|X λ − b| / |b|` of the boundary-value solve.
    pub(super) fn solve_lambda_dirichlet(&mut self) -> Result<f64, FlowError> {
        self.factor_dirac(true)?;
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
    norms.fill(0.0);
    component_areas.fill(0.0);
    for ((l, &a), &c) in lambda.iter().zip(areas).zip(vertex_component) {
        norms[c] += l.norm2() * a;
        component_areas[c] += a;
    }
    for (l, &c) in lambda.iter_mut().zip(vertex_component) {
        if free[c] && norms[c] > 0.0 {
            *l = l.scale((component_areas[c] / norms[c]).sqrt());
        }
    }
}
