//! The constraint basis of §4 / §6.2 and the projection of a flow direction onto it.
//!
//! Constraint functions are orthonormalized by modified Gram–Schmidt in the area inner product
//! `⟨⟨a, b⟩⟩ = Σ a_i b_i A_i` (Table 1, step III) and projected out of the flow direction
//! (step IV). Components of a mesh flow independently, so every inner product is taken per
//! connected component: a basis function is really one function per component, and where it
//! vanishes on a component (after orthogonalization) it is dropped there.

/// Relative norm below which an orthogonalized function is considered dependent and dropped
/// (docs/algorithm.md §3).
const DEPENDENT: f64 = 1e-10;

pub struct ConstraintBasis {
    functions: Vec<Vec<f64>>,
    count: usize,
    vertex_component: Vec<usize>,
    /// Per-component scratch for inner products (one slot per component).
    dots: Vec<f64>,
    norms: Vec<f64>,
}

impl ConstraintBasis {
    /// Room for `capacity` functions on `vertex_component.len()` vertices.
    pub fn new(vertex_component: Vec<usize>, n_components: usize, capacity: usize) -> Self {
        let n = vertex_component.len();
        ConstraintBasis {
            functions: (0..capacity).map(|_| vec![0.0; n]).collect(),
            count: 0,
            vertex_component,
            dots: vec![0.0; n_components],
            norms: vec![0.0; n_components],
        }
    }

    pub fn clear(&mut self) {
        self.count = 0;
    }

    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Orthonormalize the function written by `fill` against the basis and add it.
    /// Panics if more functions are pushed than the capacity given to [`ConstraintBasis::new`]
    /// (a programming error, not an input error).
    pub fn push_with(&mut self, areas: &[f64], fill: impl FnOnce(&mut [f64])) {
        let (done, rest) = self.functions.split_at_mut(self.count);
        let g = &mut rest[0];
        fill(g);
        per_component_dot(&self.vertex_component, g, g, areas, &mut self.norms);
        for b in done.iter() {
            per_component_dot(&self.vertex_component, g, b, areas, &mut self.dots);
            subtract_per_component(&self.vertex_component, &self.dots, b, g);
        }
        per_component_dot(&self.vertex_component, g, g, areas, &mut self.dots);
        for (d, &original) in self.dots.iter_mut().zip(&self.norms) {
            // Store the scale factor: 1/|g| where g is independent, 0 where it is not.
            *d = if *d > DEPENDENT * DEPENDENT * original && *d > 0.0 {
                1.0 / d.sqrt()
            } else {
                0.0
            };
        }
        if let [scale] = self.dots[..] {
            g.iter_mut().for_each(|gi| *gi *= scale);
        } else {
            for (gi, &c) in g.iter_mut().zip(&self.vertex_component) {
                *gi *= self.dots[c];
            }
        }
        self.count += 1;
    }

    /// `v ← v − Σ_k ⟨⟨v, ĉ_k⟩⟩ ĉ_k` (Table 1, step IV).
    pub fn project(&mut self, v: &mut [f64], areas: &[f64]) {
        for b in &self.functions[..self.count] {
            per_component_dot(&self.vertex_component, v, b, areas, &mut self.dots);
            subtract_per_component(&self.vertex_component, &self.dots, b, v);
        }
    }

    /// Largest `|⟨⟨v, ĉ_k⟩⟩|` over basis functions and components (0 when v satisfies every
    /// constraint): for tests and diagnostics.
    pub fn max_violation(&mut self, v: &[f64], areas: &[f64]) -> f64 {
        let mut worst = 0.0f64;
        for b in &self.functions[..self.count] {
            per_component_dot(&self.vertex_component, v, b, areas, &mut self.dots);
            worst = self.dots.iter().fold(worst, |w, d| w.max(d.abs()));
        }
        worst
    }
}

/// `out[c] = Σ_{i ∈ component c} a_i b_i A_i`.
pub fn per_component_dot(
    vertex_component: &[usize],
    a: &[f64],
    b: &[f64],
    areas: &[f64],
    out: &mut [f64],
) {
    if let [total] = out {
        // One component, the common case: a sum over independent lanes, which vectorizes.
        // The general loop adds into `out[c]` through memory, one vertex after the other
        // (a chain of dependent additions: a third of the step's constraint phase at 50k
        // vertices).
        *total = lane_dot(a, b, areas);
        return;
    }
    out.fill(0.0);
    for (((&c, ai), bi), wi) in vertex_component.iter().zip(a).zip(b).zip(areas) {
        out[c] += ai * bi * wi;
    }
}

/// `Σ a_i b_i w_i` summed in [`LANES`] interleaved partial sums.
fn lane_dot(a: &[f64], b: &[f64], w: &[f64]) -> f64 {
    let n = a.len().min(b.len()).min(w.len());
    let (a, b, w) = (&a[..n], &b[..n], &w[..n]);
    let mut partial = [0.0; LANES];
    let whole = n - n % LANES;
    for ((a, b), w) in a[..whole]
        .chunks_exact(LANES)
        .zip(b[..whole].chunks_exact(LANES))
        .zip(w[..whole].chunks_exact(LANES))
    {
        for l in 0..LANES {
            partial[l] += a[l] * b[l] * w[l];
        }
    }
    let tail: f64 = (whole..n).map(|i| a[i] * b[i] * w[i]).sum();
    partial.iter().sum::<f64>() + tail
}

/// Partial sums of [`lane_dot`]: enough independent additions to hide their latency.
const LANES: usize = 8;

/// `v_i −= dots[c(i)] b_i`, with `c(i)` vertex `i`'s component.
fn subtract_per_component(vertex_component: &[usize], dots: &[f64], b: &[f64], v: &mut [f64]) {
    if let [d] = dots {
        v.iter_mut().zip(b).for_each(|(vi, bi)| *vi -= d * bi);
        return;
    }
    for ((vi, bi), &c) in v.iter_mut().zip(b).zip(vertex_component) {
        *vi -= dots[c] * bi;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one-component sum in lanes is the same sum as the per-component loop, to rounding,
    /// tail included.
    #[test]
    fn one_component_dot_matches_the_per_component_sum() {
        for n in [0, 1, 7, 8, 9, 100, 1001] {
            let a: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
            let b: Vec<f64> = (0..n).map(|i| 1.0 + (i as f64 * 0.11).cos()).collect();
            let w: Vec<f64> = (0..n).map(|i| 0.5 + (i % 5) as f64).collect();
            let expected: f64 = (0..n).map(|i| a[i] * b[i] * w[i]).sum();
            let mut one = [0.0];
            per_component_dot(&vec![0; n], &a, &b, &w, &mut one);
            assert!(
                (one[0] - expected).abs() <= 1e-12 * expected.abs().max(1.0),
                "n = {n}"
            );
            // Two components, one of them empty: the general loop gives the same total.
            let mut two = [0.0; 2];
            per_component_dot(&vec![1; n], &a, &b, &w, &mut two);
            assert_eq!(two[0], 0.0);
            assert!((two[1] - one[0]).abs() <= 1e-12 * expected.abs().max(1.0));
        }
    }

    #[test]
    fn projection_removes_constraint_components_per_component() {
        // Two components of 4 vertices each, unequal areas.
        let comp = vec![0, 0, 0, 0, 1, 1, 1, 1];
        let areas = [1.0, 2.0, 0.5, 1.5, 3.0, 1.0, 1.0, 2.0];
        let x = [0.0, 1.0, 2.0, 3.0, -1.0, 0.5, 2.0, 1.0];
        let mut basis = ConstraintBasis::new(comp, 2, 3);
        basis.push_with(&areas, |g| g.fill(1.0));
        basis.push_with(&areas, |g| g.copy_from_slice(&x));
        // A dependent function (a multiple of 1 plus x) is dropped, not divided by ~0.
        basis.push_with(&areas, |g| {
            for (gi, xi) in g.iter_mut().zip(&x) {
                *gi = 2.0 + 3.0 * xi;
            }
        });
        let mut v = [0.3, -1.0, 2.0, 0.7, 1.0, 1.0, -2.0, 0.25];
        basis.project(&mut v, &areas);
        assert!(basis.max_violation(&v, &areas) < 1e-12);
        let mut dots = [0.0; 2];
        per_component_dot(&[0, 0, 0, 0, 1, 1, 1, 1], &v, &[1.0; 8], &areas, &mut dots);
        assert!(dots.iter().all(|d| d.abs() < 1e-12));
        per_component_dot(&[0, 0, 0, 0, 1, 1, 1, 1], &v, &x, &areas, &mut dots);
        assert!(dots.iter().all(|d| d.abs() < 1e-12));
        // Projecting twice changes nothing: it is a projection.
        let before = v;
        basis.project(&mut v, &areas);
        for (a, b) in v.iter().zip(&before) {
            assert!((a - b).abs() < 1e-12);
        }
    }
}
