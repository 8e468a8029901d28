//! The per-step geometry of a moving surface, refilled in place.
//!
//! Connectivity never changes during a flow, so every buffer is sized once; `refresh` after
//! the positions move recomputes everything the flows and metrics read: an explicit cache
//! with an explicit refill, never a recomputation hidden in a getter.

use super::operators::{
    barycentric_vertex_areas_into, corner_cotangents_into, cotan_laplacian_apply_into,
    face_areas_into, mean_curvature_into, vertex_normals_into, willmore_energy,
};

pub struct GeometryCache {
    pub face_areas: Vec<f64>,
    pub cotangents: Vec<[f64; 3]>,
    pub vertex_areas: Vec<f64>,
    pub normals: Vec<[f64; 3]>,
    /// `L f` (PSD cotan Laplacian applied to the positions).
    pub laplacian_f: Vec<[f64; 3]>,
    pub mean_curvature: Vec<f64>,
}

impl GeometryCache {
    pub fn new(positions: &[[f64; 3]], triangles: &[[usize; 3]]) -> Self {
        let (nv, nf) = (positions.len(), triangles.len());
        let mut cache = GeometryCache {
            face_areas: vec![0.0; nf],
            cotangents: vec![[0.0; 3]; nf],
            vertex_areas: vec![0.0; nv],
            normals: vec![[0.0; 3]; nv],
            laplacian_f: vec![[0.0; 3]; nv],
            mean_curvature: vec![0.0; nv],
        };
        cache.refresh(positions, triangles);
        cache
    }

    pub fn refresh(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]]) {
        face_areas_into(positions, triangles, &mut self.face_areas);
        corner_cotangents_into(positions, triangles, &mut self.cotangents);
        barycentric_vertex_areas_into(triangles, &self.face_areas, &mut self.vertex_areas);
        vertex_normals_into(positions, triangles, &mut self.normals);
        cotan_laplacian_apply_into(
            positions,
            triangles,
            &self.cotangents,
            &mut self.laplacian_f,
        );
        mean_curvature_into(
            &self.laplacian_f,
            &self.normals,
            &self.vertex_areas,
            &mut self.mean_curvature,
        );
    }

    /// Follow a similarity that scaled each connected component by `scales[c]` (and moved it):
    /// angles, cotangents and normals are unchanged, areas scale by s², `L f` by s and H by 1/s.
    /// Exactly what [`GeometryCache::refresh`] would compute, without the trigonometry.
    pub fn rescale(
        &mut self,
        triangles: &[[usize; 3]],
        vertex_component: &[usize],
        scales: &[f64],
    ) {
        for (a, tri) in self.face_areas.iter_mut().zip(triangles) {
            let s = scales[vertex_component[tri[0]]];
            *a *= s * s;
        }
        for (i, &c) in vertex_component.iter().enumerate() {
            let s = scales[c];
            self.vertex_areas[i] *= s * s;
            self.laplacian_f[i] = [
                self.laplacian_f[i][0] * s,
                self.laplacian_f[i][1] * s,
                self.laplacian_f[i][2] * s,
            ];
            self.mean_curvature[i] /= s;
        }
    }

    pub fn willmore_energy(&self) -> f64 {
        willmore_energy(&self.mean_curvature, &self.vertex_areas)
    }

    pub fn total_area(&self) -> f64 {
        self.face_areas.iter().sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::bumpy_sphere;

    #[test]
    fn rescale_matches_a_fresh_refresh() {
        let mesh = bumpy_sphere(2, 0.2);
        let mut cache = GeometryCache::new(&mesh.positions, &mesh.triangles);
        let s = 1.7;
        let moved: Vec<[f64; 3]> = mesh
            .positions
            .iter()
            .map(|p| [s * p[0] + 3.0, s * p[1] - 1.0, s * p[2]])
            .collect();
        cache.rescale(&mesh.triangles, &vec![0; moved.len()], &[s]);
        let fresh = GeometryCache::new(&moved, &mesh.triangles);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * (1.0 + a.abs().max(b.abs()));
        assert!(cache
            .face_areas
            .iter()
            .zip(&fresh.face_areas)
            .all(|(a, b)| close(*a, *b)));
        assert!(cache
            .vertex_areas
            .iter()
            .zip(&fresh.vertex_areas)
            .all(|(a, b)| close(*a, *b)));
        assert!(cache
            .mean_curvature
            .iter()
            .zip(&fresh.mean_curvature)
            .all(|(a, b)| close(*a, *b)));
        assert!(cache
            .laplacian_f
            .iter()
            .zip(&fresh.laplacian_f)
            .all(|(a, b)| (0..3).all(|k| close(a[k], b[k]))));
        assert!(close(cache.willmore_energy(), fresh.willmore_energy()));
    }
}
