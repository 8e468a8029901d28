//! The per-step geometry of a moving surface, refilled in place.
//!
//! Connectivity never changes during a flow, so every buffer is sized once; `refresh` after
//! the positions move recomputes everything the flows and metrics read: an explicit cache
//! with an explicit refill, never a recomputation hidden in a getter.

use super::intrinsic::IntrinsicDelaunay;
use super::operators::{
    barycentric_vertex_areas_into, corner_cotangents_into, cotan_laplacian_apply_into,
    face_areas_into, mean_curvature_into, vertex_normals_into, willmore_energy,
};

pub struct GeometryCache {
    pub face_areas: Vec<f64>,
    pub cotangents: Vec<[f64; 3]>,
    pub vertex_areas: Vec<f64>,
    pub normals: Vec<[f64; 3]>,
    /// `L f` (PSD cotan Laplacian of the mesh's own triangles applied to the positions): what
    /// the `|Δf|` form of W reports, as other tools compute it (libigl).
    pub laplacian_f: Vec<[f64; 3]>,
    /// `L f` with L on the intrinsic Delaunay triangulation, when [`GeometryCache::intrinsic`]
    /// is set (empty otherwise): H is built from it.
    pub intrinsic_laplacian_f: Vec<[f64; 3]>,
    pub mean_curvature: Vec<f64>,
    /// The intrinsic Delaunay triangulation of the current surface, refilled by `refresh`,
    /// when the owner builds its Laplacian there (the conformal flow: docs/algorithm.md §1,
    /// docs/cheburashka-collapse.md). `cotangents` stay the input triangles' own.
    pub intrinsic: Option<IntrinsicDelaunay>,
    /// Each face's share of the total area at `new` (the input), for [`Self::clamp_crowded`].
    input_shares: Vec<f64>,
    /// When set, `refresh` clamps the corner cotangents of every face whose area share fell
    /// below [`CROWDED_SHARE`] of its input share at `max(cot θ, 0)`, *after* `L f` and H
    /// were built from the true ones: `cotangents` then feed a Poisson solve with
    /// non-negative weights where the surface crowds, H and W stay the mesh's own. Known
    /// trade-off: the clamp loses linear precision on obtuse triangles (the identity on a
    /// face without an obtuse angle, so on icospheres); it is consistent where triangles are
    /// non-obtuse. Set by the conformal flow only after the safeguard refused a try for
    /// folds or collapse (docs/cheburashka-collapse.md, "A fallback").
    pub clamp_crowded: bool,
}

/// A face is crowded when its share of the total area fell below this fraction of its input
/// share. Measured (docs/cheburashka-collapse.md): cheburashka reaches W/4π 1.176 / 1.171 /
/// 1.455 in 20 default steps with 3e-2 / 1e-2 / 1e-3.
pub const CROWDED_SHARE: f64 = 1e-2;

/// `max(cot θ, 0)` at the corners of every face whose area share is below
/// [`CROWDED_SHARE`] of its `input_shares` entry (see [`GeometryCache::clamp_crowded`]).
pub fn clamp_crowded_cotangents(
    face_areas: &[f64],
    input_shares: &[f64],
    cotangents: &mut [[f64; 3]],
) {
    let total: f64 = face_areas.iter().sum();
    for ((cots, &a), &s0) in cotangents.iter_mut().zip(face_areas).zip(input_shares) {
        if a < CROWDED_SHARE * s0 * total {
            for c in cots.iter_mut() {
                *c = c.max(0.0);
            }
        }
    }
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
            intrinsic_laplacian_f: Vec::new(),
            mean_curvature: vec![0.0; nv],
            intrinsic: None,
            input_shares: Vec::new(),
            clamp_crowded: false,
        };
        cache.refresh(positions, triangles);
        let total: f64 = cache.face_areas.iter().sum();
        cache.input_shares = cache.face_areas.iter().map(|a| a / total).collect();
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
        let curvature_normal = match &mut self.intrinsic {
            Some(idt) => {
                idt.flip_to_delaunay(positions, &self.cotangents);
                // L applied to the coordinate functions: each intrinsic edge's weight times
                // the chord between its ends (the coordinates are functions on the vertices).
                cotan_laplacian_apply_into(
                    positions,
                    &idt.triangles,
                    &idt.cotangents,
                    &mut self.intrinsic_laplacian_f,
                );
                &self.intrinsic_laplacian_f
            }
            None => &self.laplacian_f,
        };
        mean_curvature_into(
            curvature_normal,
            &self.normals,
            &self.vertex_areas,
            &mut self.mean_curvature,
        );
        if self.clamp_crowded {
            clamp_crowded_cotangents(&self.face_areas, &self.input_shares, &mut self.cotangents);
        }
    }

    /// Build `L f` and H on the intrinsic Delaunay triangulation from now on (`idt` built on
    /// these `triangles`), and refresh.
    pub fn use_intrinsic_delaunay(
        &mut self,
        idt: IntrinsicDelaunay,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
    ) {
        self.intrinsic = Some(idt);
        self.intrinsic_laplacian_f = vec![[0.0; 3]; positions.len()];
        self.refresh(positions, triangles);
    }

    /// Follow a similarity that scaled each connected component by `scales[c]` (and moved it):
    /// angles, cotangents, normals and the intrinsic Delaunay flips are unchanged, areas scale by s², `L f` by s and H by 1/s.
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
            if let Some(l) = self.intrinsic_laplacian_f.get_mut(i) {
                *l = [l[0] * s, l[1] * s, l[2] * s];
            }
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
    use crate::mesh::generate::{bumpy_sphere, irregular_sphere};

    /// Only the corners of crowded faces are clamped, and only their negative cotangents;
    /// H is built before the clamp, so it stays the mesh's own.
    #[test]
    fn only_crowded_faces_lose_their_negative_cotangents() {
        // Face 0: obtuse at corner 0 (cot 120° < 0), crowded (share 1e-3 of its input share).
        // Face 1: the same obtuse shape, not crowded.
        let s3 = 3f64.sqrt();
        let mut cots = vec![[-1.0 / s3, s3, s3]; 2];
        let areas = [1e-3, 1.0 - 1e-3];
        clamp_crowded_cotangents(&areas, &[0.5, 0.5], &mut cots);
        assert_eq!(cots[0], [0.0, s3, s3]);
        assert_eq!(cots[1], [-1.0 / s3, s3, s3]);

        let mesh = irregular_sphere(3, 7);
        let plain = GeometryCache::new(&mesh.positions, &mesh.triangles);
        let mut clamped = GeometryCache::new(&mesh.positions, &mesh.triangles);
        clamped.clamp_crowded = true;
        // Shrink the surface uniformly: no face is crowded, nothing changes.
        let moved: Vec<[f64; 3]> = mesh.positions.iter().map(|p| p.map(|x| 0.5 * x)).collect();
        clamped.refresh(&moved, &mesh.triangles);
        assert_eq!(clamped.cotangents, plain.cotangents);
        // Move one vertex onto its neighbour: its faces collapse and lose their negative
        // cotangents; H is the unclamped one.
        let mut pinched = mesh.positions.clone();
        let [a, b, _] = mesh.triangles[0];
        pinched[a] = pinched[b];
        let reference = GeometryCache::new(&pinched, &mesh.triangles);
        clamped.refresh(&pinched, &mesh.triangles);
        assert_eq!(clamped.mean_curvature, reference.mean_curvature);
        let mut crowded_faces = 0;
        for (f, (c, r)) in clamped
            .cotangents
            .iter()
            .zip(&reference.cotangents)
            .enumerate()
        {
            let crowded = reference.face_areas[f]
                < CROWDED_SHARE * plain.face_areas[f] * reference.face_areas.iter().sum::<f64>()
                    / plain.face_areas.iter().sum::<f64>();
            crowded_faces += usize::from(crowded);
            for k in 0..3 {
                let want = if crowded { r[k].max(0.0) } else { r[k] };
                assert_eq!(c[k], want, "face {f} corner {k}");
            }
        }
        assert!(crowded_faces >= 2, "{crowded_faces} crowded faces");
    }

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

    /// On the intrinsic Delaunay triangulation: the flips of an irregular sphere do not depend
    /// on its scale, so a rescale matches a fresh refresh there too; the mesh's own `L f` stays
    /// the mesh's, and H differs from the mesh-cotan H only where edges flipped.
    #[test]
    fn intrinsic_mean_curvature_rescales_and_differs_only_where_flipped() {
        let mesh = irregular_sphere(3, 7);
        let with_idt = |p: &[[f64; 3]]| {
            let mut c = GeometryCache::new(p, &mesh.triangles);
            c.use_intrinsic_delaunay(IntrinsicDelaunay::new(&mesh.triangles), p, &mesh.triangles);
            c
        };
        let plain = GeometryCache::new(&mesh.positions, &mesh.triangles);
        let mut cache = with_idt(&mesh.positions);
        let flips = cache.intrinsic.as_ref().map_or(0, |i| i.flip_count());
        assert!(flips > 0, "the test mesh needs non-Delaunay edges");
        assert_eq!(cache.laplacian_f, plain.laplacian_f);
        let idt = cache.intrinsic.as_ref().expect("set");
        let mut touched = vec![false; mesh.vertex_count()];
        for (f, &c) in idt.changed.iter().enumerate() {
            if c {
                for v in mesh.triangles[f].iter().chain(&idt.triangles[f]) {
                    touched[*v] = true;
                }
            }
        }
        for (v, (a, b)) in cache
            .mean_curvature
            .iter()
            .zip(&plain.mean_curvature)
            .enumerate()
        {
            if !touched[v] {
                assert!(
                    (a - b).abs() <= 1e-9 * (1.0 + b.abs()),
                    "vertex {v}: {a} vs {b}"
                );
            }
        }
        assert!(cache.mean_curvature != plain.mean_curvature);
        let s = 0.3;
        let moved: Vec<[f64; 3]> = mesh
            .positions
            .iter()
            .map(|p| [s * p[0], s * p[1] + 2.0, s * p[2]])
            .collect();
        cache.rescale(&mesh.triangles, &vec![0; moved.len()], &[s]);
        let fresh = with_idt(&moved);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-10 * (1.0 + a.abs().max(b.abs()));
        assert!(cache
            .mean_curvature
            .iter()
            .zip(&fresh.mean_curvature)
            .all(|(a, b)| close(*a, *b)));
        assert!(cache
            .intrinsic_laplacian_f
            .iter()
            .zip(&fresh.intrinsic_laplacian_f)
            .all(|(a, b)| (0..3).all(|k| close(a[k], b[k]))));
    }
}
