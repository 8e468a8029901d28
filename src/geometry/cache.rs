//! The per-step geometry of a moving surface, refilled in place.
//!
//! Connectivity never changes during a flow, so every buffer is sized once; `refresh` after
//! the positions move recomputes everything the flows and metrics read (STYLE.md: explicit
//! cache, explicit refill).

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

    pub fn willmore_energy(&self) -> f64 {
        willmore_energy(&self.mean_curvature, &self.vertex_areas)
    }

    pub fn total_area(&self) -> f64 {
        self.face_areas.iter().sum()
    }
}
