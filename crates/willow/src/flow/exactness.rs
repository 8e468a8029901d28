//! Exactness for surfaces of genus g > 0 (§6.2, Appendix C): the new edges `λ̄ df λ` must have
//! no harmonic part, or the Poisson solve (Eq. 6) throws the periods away and the step stops
//! being conformal.
//!
//! Two pieces, both on the harmonic vector fields `v_i` of App. C.1 steps I–IV:
//!
//! 1. **The constraint functions** (App. C.1 step V) for the curvature change ρ. They are the
//!    *discrete* linearization of the periods, not a transcription of the smooth `D Z_i = v_i`:
//!    - one inverse iteration from λ = 1 gives `λ = 1 + μ` with `X₀ μ = Dᵀ M_F P ρ` to first
//!      order (`X(ρ) = X₀ + X₁(ρ) + O(ρ²)`, and App. G's potential term gives
//!      `X₁(ρ)·1 = −Dᵀ M_F P ρ`, with `P` the face average and `(Dλ)_f = −Σ e_i λ_i / 2A_f`);
//!    - the face-averaged new edges (`willmore::integrate`) change by `2 Im(e (Pμ)_f)`, so the
//!      period against `v_j` changes by `2 Im Σ_f A_f v_j (Pμ)_f`;
//!    - hence `Im⟨⟨λ̇, v_j⟩⟩ = 0` (App. C) becomes, for `W_j = X₀⁺ Pᵀ M_F v_j`,
//!      `⟨ρ, c_j^a⟩_M = 0` with `c_j = M⁻¹ Pᵀ M_F Im(D W_j)` (x, y, z parts).
//!
//!    In the smooth limit `D W_j = D D⁻² v_j = Z_j`, the paper's function. The previous
//!    discretization, `Im Z_j` with `X₀ Z_j = Dᵀ M_F v_j`, agrees only in that limit: measured on
//!    a torus with 13% noise its period error after one step was first order in τ (3.1e-5,
//!    2.7e-4, 2.2e-3 at τ = 0.001, 0.01, 0.1), and Q grew until the flow diverged even at
//!    τ = 0.01. With `c_j` the error is second order (6.6e-7, 6.6e-5, 6.4e-3).
//! 2. **Period projection** of λ, after the eigenvector solve: the second-order remainder is
//!    still large where ρ is (noise, big τ), so λ is corrected by `δλ = Σ_j W_j a_j`
//!    (`a_j ∈ Im ℍ`), the correction of least `|D δλ|²` (least change of the curvature the
//!    eigenvector realizes) that cancels the periods. The periods are quadratic in λ; a few
//!    chord-Newton steps on the 6g × 6g Jacobian bring them to rounding (6.7e-2 → 2.4e-4 →
//!    2.6e-9 → 2.6e-15 on the same torus).

use super::constraints::ConstraintBasis;
use super::dirac::opposite_edges;
use crate::geometry::hodge::{harmonic_vector_field_into, HarmonicBasisSolver, HodgeError};
use crate::geometry::Quaternion;
use crate::linalg::solver::Cholesky;
use crate::mesh::topology::Topology;
use faer::c64;

/// Chord-Newton steps of the period projection (each one multiplies the period by ~1e-3..1e-6).
const PERIOD_ITERATIONS: usize = 4;
/// Relative period below which the projection stops early.
const PERIOD_TOLERANCE: f64 = 1e-13;

/// Why the exactness data could not be computed this step.
#[derive(Debug, thiserror::Error)]
pub enum ExactnessError {
    #[error("harmonic 1-forms: {0}")]
    Harmonic(#[from] HodgeError),
}

/// Harmonic fields, the `W_j` solves and the period Jacobian, allocated once per flow.
pub struct Exactness {
    harmonic: HarmonicBasisSolver,
    forms: Vec<Vec<f64>>,
    /// `v_j` per face, one block of `|F|` vectors per form.
    fields: Vec<[f64; 3]>,
    /// Right-hand sides `Pᵀ M_F v_j`, then the solutions `W_j`, in complex form, column-major.
    w: Vec<c64>,
    /// `W_j` as quaternions, one block of `|V|` per form.
    w_quat: Vec<Quaternion>,
    /// Scratch: one quaternion per vertex.
    scratch: Vec<Quaternion>,
    component_sums: Vec<f64>,
    component_counts: Vec<f64>,
    /// Period Jacobian (row-major, `3m × 3m`) and right-hand side.
    jacobian: Vec<f64>,
    periods: Vec<f64>,
    pivots: Vec<usize>,
}

impl Exactness {
    /// `None` when the surface has no harmonic 1-forms (every component a sphere or a disk).
    pub fn new(
        mesh: &crate::mesh::Mesh,
        topology: &Topology,
        seed: u64,
    ) -> Result<Option<Exactness>, ExactnessError> {
        let harmonic = HarmonicBasisSolver::new(mesh, topology, seed)?;
        let m = harmonic.form_count();
        if m == 0 {
            return Ok(None);
        }
        let (n, nf) = (mesh.vertex_count(), mesh.face_count());
        let k = 3 * m;
        Ok(Some(Exactness {
            harmonic,
            forms: Vec::with_capacity(m),
            fields: vec![[0.0; 3]; m * nf],
            w: vec![c64::new(0.0, 0.0); 2 * n * m],
            w_quat: vec![Quaternion::default(); n * m],
            scratch: vec![Quaternion::default(); n],
            component_sums: vec![0.0; topology.components.len()],
            component_counts: vec![0.0; topology.components.len()],
            jacobian: vec![0.0; k * k],
            periods: vec![0.0; k],
            pivots: vec![0; k],
        }))
    }

    /// Number of harmonic forms (2g per closed component of genus g).
    pub fn form_count(&self) -> usize {
        self.harmonic.form_count()
    }

    /// App. C.1 on the current surface: harmonic fields `v_j`, the solves `X₀ W_j = Pᵀ M_F v_j`
    /// with `dirac` holding the factor of X at ρ = 0, and the 3 constraint functions per form
    /// pushed onto `constraints`.
    #[allow(clippy::too_many_arguments)]
    pub fn push_constraints(
        &mut self,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        topology: &Topology,
        face_areas: &[f64],
        vertex_areas: &[f64],
        dirac: &mut Cholesky<c64>,
        constraints: &mut ConstraintBasis,
    ) -> Result<(), ExactnessError> {
        self.harmonic.compute(positions, &mut self.forms)?;
        let (n, nf) = (positions.len(), triangles.len());
        for (form, (field, rhs)) in self.forms.iter().zip(
            self.fields
                .chunks_exact_mut(nf)
                .zip(self.w.chunks_exact_mut(2 * n)),
        ) {
            harmonic_vector_field_into(positions, triangles, topology, form, field);
            // Pᵀ M_F v: each face gives A_f/3 of its field to each corner.
            self.scratch.fill(Quaternion::default());
            for ((tri, v), &area) in triangles.iter().zip(field.iter()).zip(face_areas) {
                let share = Quaternion::imaginary(*v).scale(area / 3.0);
                for &i in tri {
                    self.scratch[i] += share;
                }
            }
            // X₀'s kernel is the constant quaternions per component: the right-hand side must
            // be orthogonal to it (ℓ², as X₀ is applied in coordinates).
            remove_means(
                &mut self.scratch,
                &topology.vertex_component,
                &mut self.component_sums,
                &mut self.component_counts,
            );
            for (i, q) in self.scratch.iter().enumerate() {
                let [z0, z1] = q.to_complex_column();
                rhs[2 * i] = z0;
                rhs[2 * i + 1] = z1;
            }
        }
        // All 2g solves in one block: the supernodal solve runs matrix-matrix kernels over the
        // factor once instead of streaming it 2g times.
        dirac.solve_in_place(&mut self.w, self.forms.len());
        for (z, w) in self
            .w
            .chunks_exact(2 * n)
            .zip(self.w_quat.chunks_exact_mut(n))
        {
            for (i, q) in w.iter_mut().enumerate() {
                *q = Quaternion::from_complex_column([z[2 * i], z[2 * i + 1]]);
            }
            // c = M⁻¹ Pᵀ M_F Im(D W): per face A_f/3 · (−Σ e_i W_i / 2A_f) = −Σ e_i W_i / 6.
            self.scratch.fill(Quaternion::default());
            for tri in triangles {
                let e = opposite_edges(positions, tri);
                let mut dw = Quaternion::default();
                for (&i, &e_i) in tri.iter().zip(&e) {
                    dw += e_i * w[i];
                }
                let share = dw.scale(-1.0 / 6.0);
                for &i in tri {
                    self.scratch[i] += share;
                }
            }
            let c = &self.scratch;
            for part in 0..3 {
                constraints.push_with(vertex_areas, |f| {
                    for ((fi, q), &a) in f.iter_mut().zip(c).zip(vertex_areas) {
                        *fi = [q.x, q.y, q.z][part] / a;
                    }
                });
            }
        }
        Ok(())
    }

    /// Correct λ by `Σ_j W_j a_j` so the face-averaged new edges have no periods (module
    /// docs, point 2). Returns the relative period left (`|periods| / Σ_f A_f |v_f|`), or
    /// `None` if the Jacobian is singular (λ is then left as it was).
    pub fn project_periods(
        &mut self,
        triangles: &[[usize; 3]],
        face_areas: &[f64],
        lambda: &mut [Quaternion],
    ) -> Option<f64> {
        let m = self.forms.len();
        let (n, nf) = (lambda.len(), triangles.len());
        let k = 3 * m;
        let scale: f64 = self
            .fields
            .iter()
            .zip(face_areas.iter().cycle())
            .map(|(v, &a)| a * (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt())
            .sum::<f64>()
            .max(f64::MIN_POSITIVE);
        // Jacobian at the current λ, kept for all iterations (chord method). The period of
        // field j is Im Σ_f (A_f/12)(s̄ v s + Σ_c λ̄_c v λ_c), s = Σ_c λ_c. Along δλ = W_i a,
        // a ∈ Im ℍ, its derivative is Im(−a P + Q a) with P = S̄ v s + Σ_c W̄_c v λ_c and
        // Q = s̄ v S + Σ_c λ̄_c v W_c (S = Σ_c W_c): two quaternion sums per (i, j) pair.
        self.jacobian.fill(0.0);
        for j in 0..m {
            let field = &self.fields[j * nf..(j + 1) * nf];
            for i in 0..m {
                let w = &self.w_quat[i * n..(i + 1) * n];
                let (mut p, mut q) = (Quaternion::default(), Quaternion::default());
                for ((tri, v), &area) in triangles.iter().zip(field).zip(face_areas) {
                    let v = Quaternion::imaginary(*v).scale(area / 12.0);
                    let l = [lambda[tri[0]], lambda[tri[1]], lambda[tri[2]]];
                    let d = [w[tri[0]], w[tri[1]], w[tri[2]]];
                    let s = l[0] + l[1] + l[2];
                    let sd = d[0] + d[1] + d[2];
                    p += sd.conj() * v * s;
                    q += s.conj() * v * sd;
                    for c in 0..3 {
                        p += d[c].conj() * v * l[c];
                        q += l[c].conj() * v * d[c];
                    }
                }
                for (col, a) in IMAGINARY_UNITS.iter().enumerate() {
                    let dv = (q * *a + (*a * p).scale(-1.0)).vector();
                    for (row, x) in dv.iter().enumerate() {
                        self.jacobian[(3 * j + row) * k + 3 * i + col] = *x;
                    }
                }
            }
        }
        if !lu_in_place(&mut self.jacobian, &mut self.pivots, k) {
            return None;
        }
        let mut left = self.evaluate_periods(triangles, face_areas, lambda) / scale;
        for _ in 0..PERIOD_ITERATIONS {
            if left < PERIOD_TOLERANCE {
                break;
            }
            lu_solve(&self.jacobian, &self.pivots, k, &mut self.periods);
            for i in 0..m {
                let w = &self.w_quat[i * n..(i + 1) * n];
                let a = Quaternion::imaginary([
                    -self.periods[3 * i],
                    -self.periods[3 * i + 1],
                    -self.periods[3 * i + 2],
                ]);
                for (l, wi) in lambda.iter_mut().zip(w) {
                    *l += *wi * a;
                }
            }
            left = self.evaluate_periods(triangles, face_areas, lambda) / scale;
        }
        Some(left)
    }

    /// Fills `self.periods` with the periods of the face-averaged new edges; returns their norm.
    fn evaluate_periods(
        &mut self,
        triangles: &[[usize; 3]],
        face_areas: &[f64],
        lambda: &[Quaternion],
    ) -> f64 {
        let nf = triangles.len();
        for (j, field) in self.fields.chunks_exact(nf).enumerate() {
            let mut sum = Quaternion::default();
            for ((tri, v), &area) in triangles.iter().zip(field).zip(face_areas) {
                let v = Quaternion::imaginary(*v).scale(area / 12.0);
                let l = [lambda[tri[0]], lambda[tri[1]], lambda[tri[2]]];
                let s = l[0] + l[1] + l[2];
                sum += s.conj() * v * s;
                for l in l {
                    sum += l.conj() * v * l;
                }
            }
            self.periods[3 * j..3 * j + 3].copy_from_slice(&sum.vector());
        }
        self.periods.iter().map(|p| p * p).sum::<f64>().sqrt()
    }
}

const IMAGINARY_UNITS: [Quaternion; 3] = [
    Quaternion::imaginary([1.0, 0.0, 0.0]),
    Quaternion::imaginary([0.0, 1.0, 0.0]),
    Quaternion::imaginary([0.0, 0.0, 1.0]),
];

/// Subtract the (unweighted) mean of `q` on each component.
fn remove_means(
    q: &mut [Quaternion],
    vertex_component: &[usize],
    sums: &mut [f64],
    counts: &mut [f64],
) {
    for part in 0..4 {
        sums.fill(0.0);
        counts.fill(0.0);
        for (v, &c) in q.iter().zip(vertex_component) {
            sums[c] += [v.w, v.x, v.y, v.z][part];
            counts[c] += 1.0;
        }
        for (v, &c) in q.iter_mut().zip(vertex_component) {
            let mean = if counts[c] > 0.0 {
                sums[c] / counts[c]
            } else {
                0.0
            };
            match part {
                0 => v.w -= mean,
                1 => v.x -= mean,
                2 => v.y -= mean,
                _ => v.z -= mean,
            }
        }
    }
}

/// LU factorization with partial pivoting of the dense row-major `k × k` matrix `a`, in place.
/// Returns false if a pivot vanishes (relative to the largest entry).
fn lu_in_place(a: &mut [f64], pivots: &mut [usize], k: usize) -> bool {
    let largest = a.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    if !(largest > 0.0 && largest.is_finite()) {
        return false;
    }
    for col in 0..k {
        let (mut best, mut best_abs) = (col, a[col * k + col].abs());
        for r in col + 1..k {
            if a[r * k + col].abs() > best_abs {
                best = r;
                best_abs = a[r * k + col].abs();
            }
        }
        if best_abs <= 1e-14 * largest {
            return false;
        }
        pivots[col] = best;
        if best != col {
            for c in 0..k {
                a.swap(col * k + c, best * k + c);
            }
        }
        let d = a[col * k + col];
        for r in col + 1..k {
            let f = a[r * k + col] / d;
            a[r * k + col] = f;
            for c in col + 1..k {
                a[r * k + c] -= f * a[col * k + c];
            }
        }
    }
    true
}

/// Solves `A x = b` in place with the factorization of [`lu_in_place`].
fn lu_solve(lu: &[f64], pivots: &[usize], k: usize, b: &mut [f64]) {
    for col in 0..k {
        b.swap(col, pivots[col]);
    }
    for r in 0..k {
        let mut s = b[r];
        for c in 0..r {
            s -= lu[r * k + c] * b[c];
        }
        b[r] = s;
    }
    for r in (0..k).rev() {
        let mut s = b[r];
        for c in r + 1..k {
            s -= lu[r * k + c] * b[c];
        }
        b[r] = s / lu[r * k + r];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lu_solves_a_pivoting_system() {
        // The first pivot is zero: partial pivoting must swap rows.
        let a = [0.0, 2.0, 1.0, 1.0, 1.0, 0.0, 3.0, 0.0, 1.0];
        let x = [1.0, -2.0, 0.5];
        let mut b: Vec<f64> = (0..3)
            .map(|r| (0..3).map(|c| a[r * 3 + c] * x[c]).sum())
            .collect();
        let mut lu = a.to_vec();
        let mut piv = [0; 3];
        assert!(lu_in_place(&mut lu, &mut piv, 3));
        lu_solve(&lu, &piv, 3, &mut b);
        for (got, want) in b.iter().zip(&x) {
            assert!((got - want).abs() < 1e-14, "{got} vs {want}");
        }
        let mut singular = vec![1.0, 2.0, 2.0, 4.0];
        assert!(!lu_in_place(&mut singular, &mut [0; 2], 2));
    }
}
