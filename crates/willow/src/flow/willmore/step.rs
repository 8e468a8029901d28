//! One step of Table 1 (right column), numbered as the paper's steps: the curvature change
//! (I–V), the tangents (VI: λ by Eq. 5 and App. G, then the new edges `λ̄ e λ`) and the new
//! positions (VII, Eq. 6).

use super::*;
use crate::flow::dirac::{assemble_dirac_into, TriangleAssembly};
use crate::flow::dirichlet;
use crate::flow::prescribed::SurfaceState;
use crate::flow::FlowError;
use crate::geometry::vec3::{norm2, sub};
use crate::geometry::Quaternion;
use crate::linalg::solver::{
    add_diagonal, assemble_cotan_laplacian_into, BlockPattern, Cholesky, SolverError,
};
use faer::c64;

impl ConformalFlow {
    /// Table 1 steps I–V: `ρ = −2τ·P(H)`, plus Möbius balancing when asked. (Step I, `H`,
    /// is the geometry cache's, refilled after the last step; II is [`Self::flow_direction`],
    /// III the basis built here and by [`Self::exactness_constraints`], IV the projection, V
    /// the scaling by τ.)
    pub(super) fn curvature_change(&mut self) -> Result<(), FlowError> {
        self.constraints.clear();
        if self.free_component.iter().any(|&f| f) {
            let g = &self.geometry;
            // Constraints act on free components only: pinned vertices already hold a
            // component's position, size and boundary (§6.3.2), so every function is zero on
            // a component with pinned vertices (without any, this is every component).
            let on = |v: usize| self.free_component[self.vertex_component[v]];
            let closed = &self.closed_vertex;
            // Prescribed boundary vectors (§6.3.1) change which curvature changes can be
            // integrated on a component with boundary. The constant one cannot: with `V = B`
            // fixed along the boundary, a uniform ρ would change the annulus' or disk's
            // conformal shape, so the λ problem has no good solution and the flow drifts
            // (measured: W rising step after step on a bumpy hemisphere). Projecting `1` out
            // there too, as App. B does for closed surfaces, leaves the flow only the
            // non-constant part of H to remove, so its fixed points are the CMC surfaces the
            // paper promises for `V = B`. Sphere inversions, which `N` excludes on closed
            // components (App. D), do not respect the prescribed boundary anyway; keeping
            // `N` out there too held H away from constant (std/mean 0.089 vs 0.055 after 10
            // steps on the same hemisphere).
            let prescribed = self.prescribed.is_some();
            for axis in 0..3 {
                self.constraints.push_with(&g.vertex_areas, |f| {
                    for (v, ((fi, n), &c)) in f.iter_mut().zip(&g.normals).zip(closed).enumerate() {
                        *fi = if on(v) && (c || !prescribed) {
                            n[axis]
                        } else {
                            0.0
                        };
                    }
                });
            }
            // Total curvature is conserved on closed components (App. B integrates over a
            // surface without boundary), and held under prescribed boundary vectors (above).
            self.constraints.push_with(&g.vertex_areas, |f| {
                for (v, (fi, &c)) in f.iter_mut().zip(closed).enumerate() {
                    *fi = if on(v) && (c || prescribed) { 1.0 } else { 0.0 };
                }
            });
        }
        self.exactness_constraints()?;
        self.assemble_laplacian();
        if self.direction_ready {
            // The end of the last step filtered this surface's direction already.
            self.rho.copy_from_slice(&self.direction);
        } else {
            self.flow_direction()?;
        }
        self.direction_ready = false;
        let g = &self.geometry;
        self.constraints.project(&mut self.rho, &g.vertex_areas);
        if let Some(mobius) = &mut self.mobius {
            // App. E: added after the inversion constraint has been projected out (otherwise
            // it would be removed again); it lies in span{N^x, N^y, N^z}, which is orthogonal
            // to the remaining constraints, so projecting those again would change nothing.
            mobius.add_direction(
                &self.positions,
                g,
                &self.vertex_component,
                self.tau,
                &mut self.rho,
            );
        }
        for r in &mut self.rho {
            *r *= self.tau;
        }
        Ok(())
    }

    /// L (unshifted) of the current surface, for the filter and the Poisson solve.
    pub(super) fn assemble_laplacian(&mut self) {
        assemble_cotan_laplacian_into(
            &self.laplace_pattern,
            &self.triangles,
            &self.geometry.cotangents,
            1.0,
            &mut self.laplace_unshifted,
        );
    }

    /// The flow direction `−2H` of the current surface (boundary vertices averaged from
    /// their interior neighbours), spectrally filtered when asked (§4), into `rho`: Table 1
    /// step II, before the projection. Needs [`Self::assemble_laplacian`] first.
    pub(super) fn flow_direction(&mut self) -> Result<(), FlowError> {
        let g = &self.geometry;
        for (r, h) in self.rho.iter_mut().zip(&g.mean_curvature) {
            *r = -2.0 * h;
        }
        if let Some(boundary) = &self.boundary_vertex {
            // At a boundary vertex the cotan formula measures the boundary curve's bending
            // (the conormal term), not the surface's mean curvature; a curved boundary then
            // gets a spurious, large H that blows the flow up. Take the average over the
            // vertex's interior neighbours instead.
            let (sums, counts) = self.boundary_sums.split_at_mut(self.rho.len());
            sums.fill(0.0);
            counts.fill(0.0);
            for tri in &self.triangles {
                for &b in tri {
                    if boundary[b] {
                        for &i in tri {
                            if !boundary[i] {
                                sums[b] += self.rho[i];
                                counts[b] += 1.0;
                            }
                        }
                    }
                }
            }
            for ((r, (&s, &c)), &is_boundary) in self
                .rho
                .iter_mut()
                .zip(sums.iter().zip(counts.iter()))
                .zip(boundary)
            {
                if is_boundary {
                    *r = if c > 0.0 { s / c } else { 0.0 };
                }
            }
        }
        self.seam_target()?;
        let g = &self.geometry;
        if let Some(target) = &self.curvature_target {
            // A smooth seam: toward the curvature that continues the surroundings (seam.rs).
            for (r, &h) in self.rho.iter_mut().zip(target) {
                *r += 2.0 * h;
            }
        }
        if let Some(filter) = &mut self.filter {
            // §4 / docs/algorithm.md §3: filter the direction before projecting it.
            filter
                .apply(
                    &self.laplace_pattern,
                    &self.laplace_unshifted,
                    &g.vertex_areas,
                    &mut self.rho,
                )
                .map_err(|e| FlowError::Numerical {
                    step: self.step + 1,
                    reason: e.to_string(),
                })?;
        }
        Ok(())
    }

    /// Appendix C.1 on the current surface (see [`Exactness::push_constraints`]): X₀ is
    /// factored once for the 2g solves, in the same factor storage that X(ρ) uses next.
    pub(super) fn exactness_constraints(&mut self) -> Result<(), FlowError> {
        if self.exactness.is_none() {
            return Ok(());
        }
        self.rho.fill(0.0);
        self.factor_dirac(false)?;
        let step = self.step + 1;
        let g = &self.geometry;
        if let Some(exactness) = self.exactness.as_mut() {
            exactness
                .push_constraints(
                    &self.positions,
                    &self.triangles,
                    self.topology.as_ref().ok_or_else(|| FlowError::Numerical {
                        step,
                        reason: "the exactness constraints need the topology".into(),
                    })?,
                    &g.face_areas,
                    &g.vertex_areas,
                    self.dirac
                        .double_mut()
                        .ok_or_else(|| FlowError::Numerical {
                            step,
                            reason: "the exactness constraints need the double-precision factor"
                                .into(),
                        })?,
                    &mut self.constraints,
                )
                .map_err(|e| FlowError::Numerical {
                    step,
                    reason: e.to_string(),
                })?;
        }
        Ok(())
    }

    /// Assemble `X(ρ)` for the current `ρ` with its diagonal shift and factor it, retrying
    /// with a larger shift if a pivot is not positive.
    pub(super) fn factor_dirac(&mut self, dirichlet: bool) -> Result<(), FlowError> {
        let g = &self.geometry;
        let n = self.positions.len();
        let mean_area = g.total_area() / n as f64;
        self.shift.fill(0.0);
        // A fixed boundary: its mask, and X's full pattern (kept for it).
        let fixed = match (dirichlet, self.fixed.as_deref()) {
            (true, Some(fixed)) => Some((
                fixed,
                self.dirac_pattern
                    .as_ref()
                    .ok_or_else(|| FlowError::Numerical {
                        step: self.step + 1,
                        reason: "a fixed boundary needs the full pattern of X".into(),
                    })?,
            )),
            _ => None,
        };
        let mean_diagonal = match fixed {
            None => self.dirac_assembly.assemble(
                &self.positions,
                &self.triangles,
                &g.face_areas,
                &self.rho,
                self.dirac.triangle_values_mut(),
            ),
            Some((fixed, pattern)) => assemble_dirac_with_unit_boundary(
                pattern,
                fixed,
                (&self.positions, &self.triangles, &g.face_areas),
                (&self.rho, &self.shift),
                &mut self.dirac_values,
                &mut self.solve_rhs,
            ),
        };
        self.profile.lap("X assembly");
        // X is dimensionless (|e|²/A and Aρ² are scale-free), so the shift is relative to its
        // mean diagonal; weighting by relative vertex area makes it a multiple of the mass M.
        // A failed factorization adds more shift on the diagonal, without reassembling.
        let mut attempt = 0;
        loop {
            let eps = DIRAC_SHIFT * 100f64.powi(attempt as i32) * mean_diagonal;
            for (v, (s, &a)) in self.shift.iter_mut().zip(&g.vertex_areas).enumerate() {
                let target = eps * a / mean_area;
                let add = target - *s;
                match fixed {
                    None => {
                        self.dirac_assembly.add_to_diagonal(
                            v,
                            add,
                            self.dirac.triangle_values_mut(),
                        );
                    }
                    Some((fixed, pattern)) if !fixed[v] => {
                        let slot = pattern.diagonal_slot(v);
                        let add = c64::new(add, 0.0);
                        self.dirac_values[pattern.entry(slot, v, 0, 0)] += add;
                        self.dirac_values[pattern.entry(slot, v, 1, 1)] += add;
                    }
                    Some(_) => continue,
                }
                *s = target;
            }
            let factored = match (fixed, self.dirac.double_mut()) {
                (None, _) => self.dirac.factorize_triangle(),
                (Some((_, pattern)), Some(double)) => double.factorize(pattern, &self.dirac_values),
                (Some(_), None) => Err(SolverError::Symbolic(
                    "a fixed boundary needs the double-precision factor".into(),
                )),
            };
            match factored {
                Ok(()) => {
                    self.profile.lap("X factor");
                    return Ok(());
                }
                // Rounded to single precision, X may lose a pivot that double precision keeps:
                // the double factor decides, before any extra shift changes the problem.
                Err(_) if matches!(self.dirac, DiracFactor::Mixed(_)) => {
                    self.fall_back_to_double()?;
                    return self.factor_dirac(dirichlet);
                }
                Err(e) if attempt >= SHIFT_RETRIES => {
                    return Err(FlowError::Numerical {
                        step: self.step + 1,
                        reason: format!("Dirac matrix X: {e}"),
                    })
                }
                Err(_) => attempt += 1,
            }
        }
    }

    /// Replace the mixed-precision factor of X by the double-precision one for the rest of the
    /// flow (same ordering and triangle layout, so the assembly is rebuilt identically).
    pub(super) fn fall_back_to_double(&mut self) -> Result<(), FlowError> {
        let numerical = |e: SolverError| FlowError::Numerical {
            step: self.step + 1,
            reason: e.to_string(),
        };
        // Rebuilt where the setup did not keep it (once a flow at most: tens of milliseconds
        // at 100k triangles).
        let rebuilt;
        let pattern = match &self.dirac_pattern {
            Some(pattern) => pattern,
            None => {
                rebuilt = BlockPattern::new(self.positions.len(), &self.triangles, 2);
                &rebuilt
            }
        };
        if let DiracFactor::Mixed(m) = &mut self.dirac {
            m.release();
        }
        let threads = self.threads;
        let mut double = Cholesky::<c64>::analyze_with_vertex_order(pattern, 1, &self.vertex_fwd)
            .map_err(numerical)?;
        double.set_quaternionic();
        double.release_triangle();
        self.dirac = DiracFactor::Double(Box::new(double));
        self.dirac.set_threads(threads);
        self.dirac_assembly = TriangleAssembly::new(
            pattern,
            &self.triangles,
            &self.dirac.triangle_slots(pattern.nnz()),
        )
        .map_err(numerical)?;
        if self.fixed.is_none() {
            self.dirac.release_gather();
        }
        self.profile.count("fell back to double", 1.0);
        Ok(())
    }

    /// Table 1 step VI, first half: λ by inverse iteration on `X(ρ)` (Eq. 5, App. G); returns
    /// the eigen-residual. The new edges `λ̄ e λ`, the rest of step VI, are made in
    /// [`Self::integrate`].
    pub(super) fn solve_lambda(&mut self) -> Result<f64, FlowError> {
        if self.fixed.is_some() {
            return self.solve_lambda_dirichlet();
        }
        if let Some(prescribed) = &mut self.prescribed {
            let g = &self.geometry;
            let state = SurfaceState {
                positions: &self.positions,
                triangles: &self.triangles,
                face_areas: &g.face_areas,
                vertex_areas: &g.vertex_areas,
                normals: &g.normals,
                vertex_component: &self.vertex_component,
            };
            return prescribed
                .solve(
                    &state,
                    &self.rho,
                    self.iterations,
                    DIRAC_SHIFT,
                    SHIFT_RETRIES,
                    &mut self.lambda,
                )
                .map_err(|e| FlowError::Numerical {
                    step: self.step + 1,
                    reason: format!("prescribed boundary: {e}"),
                });
        }
        self.factor_dirac(false)?;
        self.lambda.fill(Quaternion::ONE);
        for _ in 0..self.iterations.max(1) {
            let g = &self.geometry;
            // Generalized inverse iteration X λ' = M λ: X integrates over faces, so the mass
            // matrix M (barycentric areas) is the matching right-hand side.
            for (i, (l, &a)) in self.lambda.iter().zip(&g.vertex_areas).enumerate() {
                let [z0, z1] = l.scale(a).to_complex_column();
                self.rhs[2 * i] = z0;
                self.rhs[2 * i + 1] = z1;
            }
            // M λ, kept: it gives X λ' for the residual below without a product with X.
            self.product.copy_from_slice(&self.rhs);
            if self.dirac.solve_in_place(&mut self.rhs).is_err() {
                // The single-precision factor is too far from X for CG: solve this step and
                // the rest of the flow with the double one.
                self.fall_back_to_double()?;
                self.factor_dirac(false)?;
                self.rhs.copy_from_slice(&self.product);
                self.solve_rhs_with_dirac()?;
            }
            if let DiracFactor::Mixed(m) = &self.dirac {
                self.profile
                    .count("CG iterations", m.last_iterations as f64);
                self.profile
                    .count("X factor kept", f64::from(u8::from(m.reused())));
            }
            for (i, l) in self.lambda.iter_mut().enumerate() {
                *l = Quaternion::from_complex_column([self.rhs[2 * i], self.rhs[2 * i + 1]]);
            }
            normalize_per_component(
                &mut self.lambda,
                &self.geometry.vertex_areas,
                &self.vertex_component,
                &mut self.component_norms,
                &mut self.component_areas,
            );
        }
        if self.lambda.iter().any(|l| !l.norm2().is_finite()) {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "the eigenvector λ is not finite".into(),
            });
        }
        let residual = self.eigen_residual();
        self.profile.lap("λ solve");
        if let Some(exactness) = self.exactness.as_mut() {
            // App. C's constraint holds to first order only: cancel the rest of the periods.
            exactness.project_periods(&self.triangles, &self.geometry.face_areas, &mut self.lambda);
            self.profile.lap("period projection");
        }
        Ok(residual)
    }

    /// Eigen-residual `|Xλ − γMλ| / |Xλ|` of the last inverse iteration, with the Rayleigh
    /// quotient γ, on X without its shift. The last solve gave `(X + S) λ' = M λ_prev`, and
    /// λ is λ' scaled by `c` on each component (X does not couple components), so
    /// `X λ = c (M λ_prev − S λ')` up to the solve's rounding, far below any residual the
    /// iteration leaves: no product with X is needed (`rhs` holds λ', `product` M λ_prev).
    pub(super) fn eigen_residual(&mut self) -> f64 {
        for (i, &c) in self.vertex_component.iter().enumerate() {
            let scale = if self.component_norms[c] > 0.0 {
                (self.component_areas[c] / self.component_norms[c]).sqrt()
            } else {
                1.0
            };
            for k in [2 * i, 2 * i + 1] {
                let x_lambda = (self.product[k] - self.rhs[k] * self.shift[i]) * scale;
                self.rhs[k] *= scale;
                self.product[k] = x_lambda;
            }
        }
        relative_eigen_residual(&self.rhs, &self.product, &self.geometry.vertex_areas)
    }

    /// The same residual from an explicit product with X, to check [`Self::eigen_residual`].
    #[cfg(test)]
    pub(super) fn eigen_residual_by_product(&mut self) -> f64 {
        for (i, l) in self.lambda.iter().enumerate() {
            let [z0, z1] = l.to_complex_column();
            self.rhs[2 * i] = z0;
            self.rhs[2 * i + 1] = z1;
        }
        self.dirac.hermitian_matvec(&self.rhs, &mut self.product);
        for (i, &s) in self.shift.iter().enumerate() {
            for k in [2 * i, 2 * i + 1] {
                self.product[k] -= self.rhs[k] * s;
            }
        }
        relative_eigen_residual(&self.rhs, &self.product, &self.geometry.vertex_areas)
    }

    /// `rhs ← X⁻¹ rhs` with the factor as it is.
    pub(super) fn solve_rhs_with_dirac(&mut self) -> Result<(), FlowError> {
        self.dirac
            .solve_in_place(&mut self.rhs)
            .map_err(|e| FlowError::Numerical {
                step: self.step + 1,
                reason: e.to_string(),
            })
    }

    /// The end of Table 1 step VI (the new edges `λ̄ e λ`, per face) and step VII (their
    /// divergence and the Poisson solve, Eq. 6). Returns the closure
    /// residual `|d f̃ − ẽ| / |ẽ|` over all half-edges (unweighted), with `ẽ = ∫ λ̄ e λ` along
    /// the edge: the integrability of the new edges, whichever quadrature feeds the solve.
    pub(super) fn integrate(&mut self) -> Result<f64, FlowError> {
        let n = self.positions.len();
        let g = &self.geometry;
        self.divergence.fill(0.0);
        for ((tri, cots), edges) in self
            .triangles
            .iter()
            .zip(&g.cotangents)
            .zip(self.new_edges.iter_mut())
        {
            // Each face maps its edges by the face average of λ̄ e λ with λ linear on the face,
            // `T_f(e) = (1/A)∫_f λ̄ e λ dA = (1/12)(s̄ e s + Σ_i λ̄_i e λ_i)`, `s = Σ_i λ_i`
            // (∫ φ_i φ_j = A(1 + δ_ij)/12). With the cotan weights below this is the Galerkin
            // (P1 finite element) weak form of Eq. (6): the L² projection of the target
            // differential λ̄ df λ onto gradients of piecewise linear maps (the cotan matrix is
            // the P1 stiffness matrix; Wardetzky et al. 2007, "Discrete Laplace operators: no
            // free lunch"). T_f is linear in e, so every face closes exactly (Σ e = 0).
            // The edge integral ∫_edge λ̄ e λ (weights ⅓, ⅙, ⅙, ⅓; docs/algorithm.md §6) does
            // not close a face, and on needles the gap is far wider than the face: on
            // botijo_genus5_irregular (a 0.005°/179.6° face, width 1e-4 of its length) it
            // folded the needle out of its plane in one step at τ = 0.02 (one vertex's H
            // 0.7 → −57, W 557 → 628), so W rose at any τ. With T_f, W falls there. (Closing
            // each face's edge integrals with a least-change correction does not help:
            // W 557 → 601 in one step at τ = 0.0125.)
            let l = [
                self.lambda[tri[0]],
                self.lambda[tri[1]],
                self.lambda[tri[2]],
            ];
            // Both maps are linear in e and every λ̄ e λ is `λ.sandwich_matrix()·e`, so each
            // is summed as 3×3 matrices once per face and applied to the three edges.
            let r = [
                l[0].sandwich_matrix(),
                l[1].sandwich_matrix(),
                l[2].sandwich_matrix(),
            ];
            let face_map = mat3_scaled_sum(
                &[(l[0] + l[1] + l[2]).sandwich_matrix(), r[0], r[1], r[2]],
                1.0 / 12.0,
            );
            for c in 0..3 {
                let (ca, cb) = ((c + 1) % 3, (c + 2) % 3);
                let (a, b) = (tri[ca], tri[cb]);
                let e = sub(self.positions[b], self.positions[a]);
                let new_edge = mat3_apply(&face_map, e);
                // The closure residual keeps measuring the edge integral ∫ λ̄ e λ (λ linear:
                // weights ⅓, ⅙, ⅙, ⅓), the paper's new edge: with T_f it would also count
                // the O(h|∇λ|) spread between neighbouring faces' averages. With
                // `s = λ_a + λ_b` the cross terms are `s̄ e s − λ̄_a e λ_a − λ̄_b e λ_b`, so the
                // integral is `(λ̄_a e λ_a + λ̄_b e λ_b + s̄ e s) / 6`.
                let edge_map = mat3_scaled_sum(
                    &[r[ca], r[cb], (l[ca] + l[cb]).sandwich_matrix()],
                    1.0 / 6.0,
                );
                edges[c] = mat3_apply(&edge_map, e);
                let w = 0.5 * cots[c];
                for k in 0..3 {
                    self.divergence[k * n + a] -= w * new_edge[k];
                    self.divergence[k * n + b] += w * new_edge[k];
                }
            }
        }

        self.profile.lap("new edges");
        // L f̃ = ω with the current L, shifted by εM so the constant kernel is harmless
        // (ω sums to zero per component by construction).
        let mean_area = g.total_area() / n as f64;
        let trace: f64 = g.cotangents.iter().map(|c| c[0] + c[1] + c[2]).sum();
        let mut attempt = 0;
        loop {
            self.laplace_values.copy_from_slice(&self.laplace_unshifted);
            let eps = POISSON_SHIFT * 100f64.powi(attempt as i32) * trace / n as f64;
            add_diagonal(
                &self.laplace_pattern,
                g.vertex_areas.iter().map(|&a| eps * a / mean_area),
                &mut self.laplace_values,
            );
            if let Some(fixed) = &self.fixed {
                // Dirichlet Poisson: the boundary stays exactly at its input positions.
                let targets = &self.fixed_positions;
                dirichlet::apply_real(
                    &self.laplace_pattern,
                    &mut self.laplace_values,
                    fixed,
                    |v, axis| targets[v][axis],
                    (attempt == 0).then_some(&mut self.divergence[..]),
                    3,
                );
            }
            match self
                .laplace
                .factorize(&self.laplace_pattern, &self.laplace_values)
            {
                Ok(()) => break,
                Err(e) if attempt >= SHIFT_RETRIES => {
                    return Err(FlowError::Numerical {
                        step: self.step + 1,
                        reason: format!("Laplacian: {e}"),
                    })
                }
                Err(_) => attempt += 1,
            }
        }
        self.profile.lap("L factor");
        self.laplace.solve_in_place(&mut self.divergence, 3);
        self.profile.lap("L solve");
        for (i, p) in self.positions.iter_mut().enumerate() {
            *p = [
                self.divergence[i],
                self.divergence[n + i],
                self.divergence[2 * n + i],
            ];
        }
        if self
            .positions
            .iter()
            .any(|p| !(p[0].is_finite() && p[1].is_finite() && p[2].is_finite()))
        {
            return Err(FlowError::Numerical {
                step: self.step + 1,
                reason: "the Poisson solve produced non-finite positions".into(),
            });
        }

        let (mut gap, mut total) = (0.0, 0.0);
        for (tri, edges) in self.triangles.iter().zip(&self.new_edges) {
            for c in 0..3 {
                let (a, b) = (tri[(c + 1) % 3], tri[(c + 2) % 3]);
                gap += norm2(sub(sub(self.positions[b], self.positions[a]), edges[c]));
                total += norm2(edges[c]);
            }
        }
        Ok(if total > 0.0 {
            (gap / total).sqrt()
        } else {
            0.0
        })
    }
}

/// `|Xλ − γMλ| / |Xλ|` with the Rayleigh quotient `γ = ⟨λ, Xλ⟩ / ⟨λ, Mλ⟩`, for λ and Xλ in
/// complex form (two entries per vertex) and M the vertex areas.
pub(super) fn relative_eigen_residual(lambda: &[c64], x_lambda: &[c64], areas: &[f64]) -> f64 {
    let (mut x_dot, mut m_dot) = (0.0, 0.0);
    for (k, (l, xl)) in lambda.iter().zip(x_lambda).enumerate() {
        x_dot += (l.conj() * xl).re;
        m_dot += l.norm_sqr() * areas[k / 2];
    }
    let gamma = if m_dot > 0.0 { x_dot / m_dot } else { 0.0 };
    let (mut res, mut xnorm) = (0.0, 0.0);
    for (k, (l, xl)) in lambda.iter().zip(x_lambda).enumerate() {
        res += (xl - l * (gamma * areas[k / 2])).norm_sqr();
        xnorm += xl.norm_sqr();
    }
    if xnorm > 0.0 {
        (res / xnorm).sqrt()
    } else {
        0.0
    }
}

/// `s · Σ m` for 3×3 matrices.
pub(super) fn mat3_scaled_sum(ms: &[[[f64; 3]; 3]], s: f64) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for m in ms {
        for r in 0..3 {
            for c in 0..3 {
                out[r][c] += m[r][c];
            }
        }
    }
    for row in &mut out {
        for v in row {
            *v *= s;
        }
    }
    out
}

pub(super) fn mat3_apply(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

/// X of a flow with held vertices, with its Dirichlet data λ = 1 there (the boundary keeps
/// its tangents: §6.3.2 with the input boundary as target) moved into `rhs`; returns X's mean
/// diagonal as [`assemble_dirac_into`] does.
pub(super) fn assemble_dirac_with_unit_boundary(
    pattern: &crate::linalg::solver::BlockPattern,
    fixed: &[bool],
    (positions, triangles, face_areas): (&[[f64; 3]], &[[usize; 3]], &[f64]),
    (rho, shift): (&[f64], &[f64]),
    values: &mut [c64],
    rhs: &mut [c64],
) -> f64 {
    let mean_diagonal = assemble_dirac_into(
        pattern, positions, triangles, face_areas, rho, shift, values,
    );
    rhs.fill(c64::new(0.0, 0.0));
    dirichlet::apply_complex(
        pattern,
        values,
        fixed,
        |_| Quaternion::ONE.to_complex_column(),
        Some(rhs),
    );
    mean_diagonal
}

/// Scale λ on each component so that `Σ |λ_i|² A_i = Σ A_i` there: λ is defined up to a
/// quaternion factor per component, and a unit mean keeps edge lengths of the order of the
/// input's before the scale policy restores the area exactly. `norms` and `component_areas`
/// are per-component scratch.
pub(super) fn normalize_per_component(
    lambda: &mut [Quaternion],
    areas: &[f64],
    vertex_component: &[usize],
    norms: &mut [f64],
    component_areas: &mut [f64],
) {
    normalize_components_where(
        lambda,
        areas,
        vertex_component,
        norms,
        component_areas,
        |_| true,
    );
}

/// [`normalize_per_component`] on the components `scaled` accepts; the others keep their λ.
pub(super) fn normalize_components_where(
    lambda: &mut [Quaternion],
    areas: &[f64],
    vertex_component: &[usize],
    norms: &mut [f64],
    component_areas: &mut [f64],
    scaled: impl Fn(usize) -> bool,
) {
    norms.fill(0.0);
    component_areas.fill(0.0);
    for ((l, &a), &c) in lambda.iter().zip(areas).zip(vertex_component) {
        norms[c] += l.norm2() * a;
        component_areas[c] += a;
    }
    for (l, &c) in lambda.iter_mut().zip(vertex_component) {
        if scaled(c) && norms[c] > 0.0 {
            *l = l.scale((component_areas[c] / norms[c]).sqrt());
        }
    }
}
