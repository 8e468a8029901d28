//! Scale policy (docs/algorithm.md §6, decision): after every step each connected component gets
//! back the area-weighted centroid and the total area it had in the input, so a CAD pipeline
//! receives its part where it was, at its size. The conformal flow determines positions only
//! up to a similarity (Eq. 6), and implicit MCF shrinks; both use this.

use crate::geometry::vec3::{add, scale, sub};

pub struct ScalePolicy {
    vertex_component: Vec<usize>,
    target_area: Vec<f64>,
    target_centroid: Vec<[f64; 3]>,
    area: Vec<f64>,
    centroid: Vec<[f64; 3]>,
}

impl ScalePolicy {
    /// Remember the input's per-component area and centroid.
    pub fn new(
        vertex_component: Vec<usize>,
        n_components: usize,
        positions: &[[f64; 3]],
        vertex_areas: &[f64],
    ) -> Self {
        let mut policy = ScalePolicy {
            vertex_component,
            target_area: vec![0.0; n_components],
            target_centroid: vec![[0.0; 3]; n_components],
            area: vec![0.0; n_components],
            centroid: vec![[0.0; 3]; n_components],
        };
        policy.measure(positions, vertex_areas);
        policy.target_area.copy_from_slice(&policy.area);
        policy.target_centroid.copy_from_slice(&policy.centroid);
        policy
    }

    fn measure(&mut self, positions: &[[f64; 3]], vertex_areas: &[f64]) {
        self.area.fill(0.0);
        self.centroid.fill([0.0; 3]);
        for ((&c, p), &a) in self
            .vertex_component
            .iter()
            .zip(positions)
            .zip(vertex_areas)
        {
            self.area[c] += a;
            self.centroid[c] = add(self.centroid[c], scale(*p, a));
        }
        for (centroid, &area) in self.centroid.iter_mut().zip(&self.area) {
            if area > 0.0 {
                *centroid = scale(*centroid, 1.0 / area);
            }
        }
    }

    /// Rescale and translate each component of `positions` (whose barycentric vertex areas
    /// are `vertex_areas`) back to the input's area and centroid. Returns the scale factor of
    /// each component, so cached geometry can follow without being recomputed.
    pub fn restore(&mut self, positions: &mut [[f64; 3]], vertex_areas: &[f64]) -> &[f64] {
        self.measure(positions, vertex_areas);
        // Reuse `area` for the factors: it is remeasured on every call.
        for (a, &target) in self.area.iter_mut().zip(&self.target_area) {
            *a = if *a > 0.0 { (target / *a).sqrt() } else { 1.0 };
        }
        for (&c, p) in self.vertex_component.iter().zip(positions.iter_mut()) {
            *p = add(
                self.target_centroid[c],
                scale(sub(*p, self.centroid[c]), self.area[c]),
            );
        }
        &self.area
    }
}
