//! Scale policy (docs/algorithm.md §6, decision): after every step each connected component gets
//! back the area-weighted centroid it had in the input, and, as [`Preserve`] asks, its total
//! area (the default: a CAD pipeline receives its part where it was, at its size) or, for a
//! closed component, its enclosed volume. The conformal flow determines positions only up to
//! a similarity (Eq. 6), and implicit MCF shrinks; both use this.
//!
//! Every correction is a uniform scale about the centroid plus a translation: a similarity,
//! so the conformal flow's Q and the curvature it just set are untouched (H scales by 1/s,
//! W not at all).

use super::Preserve;
use crate::geometry::operators::component_volumes_into;
use crate::geometry::vec3::{add, scale, sub};
use crate::mesh::topology::Topology;

pub struct ScalePolicy {
    preserve: Preserve,
    vertex_component: Vec<usize>,
    face_component: Vec<usize>,
    /// Per component: whether it is closed (only a closed component encloses a volume).
    closed: Vec<bool>,
    target_area: Vec<f64>,
    target_volume: Vec<f64>,
    target_centroid: Vec<[f64; 3]>,
    /// Per component: left exactly as it is (pinned vertices already fix it).
    held: Vec<bool>,
    area: Vec<f64>,
    volume: Vec<f64>,
    centroid: Vec<[f64; 3]>,
}

impl ScalePolicy {
    /// Remember the input's per-component area, volume and centroid.
    pub fn new(
        preserve: Preserve,
        topology: &Topology,
        positions: &[[f64; 3]],
        triangles: &[[usize; 3]],
        vertex_areas: &[f64],
    ) -> Self {
        let n_components = topology.components.len();
        let mut policy = ScalePolicy {
            preserve,
            vertex_component: topology.vertex_component.clone(),
            face_component: topology.face_component.clone(),
            closed: topology.components.iter().map(|c| c.is_closed()).collect(),
            target_area: vec![0.0; n_components],
            target_volume: vec![0.0; n_components],
            target_centroid: vec![[0.0; 3]; n_components],
            held: vec![false; n_components],
            area: vec![0.0; n_components],
            volume: vec![0.0; n_components],
            centroid: vec![[0.0; 3]; n_components],
        };
        policy.measure(positions, triangles, vertex_areas);
        policy.target_area.copy_from_slice(&policy.area);
        policy.target_volume.copy_from_slice(&policy.volume);
        policy.target_centroid.copy_from_slice(&policy.centroid);
        policy
    }

    /// Leave the components marked in `held` (one flag per component) untouched: a flow
    /// with pinned vertices there (a region's surroundings, a fixed boundary) must not move
    /// them by a similarity.
    pub fn hold(&mut self, held: &[bool]) {
        self.held.copy_from_slice(held);
    }

    /// Area and area-weighted centroid of each component, and its volume where the policy
    /// needs it (measured about the centroid: see [`component_volumes_into`]).
    fn measure(&mut self, positions: &[[f64; 3]], triangles: &[[usize; 3]], vertex_areas: &[f64]) {
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
        if self.preserve == Preserve::Volume {
            component_volumes_into(
                positions,
                triangles,
                &self.face_component,
                &self.centroid,
                &mut self.volume,
            );
        }
    }

    /// Rescale and translate each component of `positions` (whose barycentric vertex areas
    /// are `vertex_areas`) back to the input's centroid and area or volume. Returns the scale
    /// factor of each component, so cached geometry can follow without being recomputed.
    pub fn restore(
        &mut self,
        positions: &mut [[f64; 3]],
        triangles: &[[usize; 3]],
        vertex_areas: &[f64],
    ) -> &[f64] {
        self.measure(positions, triangles, vertex_areas);
        // Reuse `area` for the factors: it is remeasured on every call.
        for (c, a) in self.area.iter_mut().enumerate() {
            *a = match self.preserve {
                _ if self.held[c] => 1.0,
                Preserve::None => 1.0,
                Preserve::Volume if self.closed[c] => {
                    volume_factor(self.volume[c], self.target_volume[c])
                }
                Preserve::Area | Preserve::Volume => area_factor(*a, self.target_area[c]),
            };
        }
        for (&c, p) in self.vertex_component.iter().zip(positions.iter_mut()) {
            if self.held[c] {
                continue;
            }
            *p = add(
                self.target_centroid[c],
                scale(sub(*p, self.centroid[c]), self.area[c]),
            );
        }
        &self.area
    }
}

/// The uniform scale `s` that brings area `area` to `target`: areas scale by `s²`. 1 when
/// there is no area to scale.
pub fn area_factor(area: f64, target: f64) -> f64 {
    if area > 0.0 {
        (target / area).sqrt()
    } else {
        1.0
    }
}

/// The uniform scale `s` that brings the enclosed volume `volume` to `target`: volumes scale
/// by `s³`. 1 (no correction) when the two have opposite signs or either is zero: a surface
/// turned inside out, or flattened, cannot be scaled back, and the safeguard's fold and Q
/// checks are the ones to notice it.
pub fn volume_factor(volume: f64, target: f64) -> f64 {
    let ratio = target / volume;
    if ratio.is_finite() && ratio > 0.0 {
        ratio.cbrt()
    } else {
        1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::operators::{barycentric_vertex_areas, enclosed_volume};
    use crate::mesh::generate::{bumpy_cap, bumpy_sphere};
    use crate::mesh::Mesh;

    /// Two components: a closed bumpy sphere and, beside it, an open cap.
    fn sphere_and_cap() -> Mesh {
        let mut mesh = bumpy_sphere(2, 0.2);
        let cap = bumpy_cap(2, 0.1);
        let offset = mesh.vertex_count();
        mesh.positions
            .extend(cap.positions.iter().map(|p| [p[0] + 4.0, p[1], p[2]]));
        mesh.triangles.extend(
            cap.triangles
                .iter()
                .map(|t| [t[0] + offset, t[1] + offset, t[2] + offset]),
        );
        mesh
    }

    /// Shrink the sphere by 0.8 and the cap by 0.5, then move both: each preserve mode puts
    /// back exactly what it promises.
    #[test]
    fn each_mode_restores_what_it_promises() {
        let mesh = sphere_and_cap();
        let topology = Topology::new(&mesh);
        assert_eq!(topology.components.len(), 2);
        let areas0 = barycentric_vertex_areas(&mesh);
        let sphere_faces = &topology.components[0].faces;
        let volume = |p: &[[f64; 3]]| {
            enclosed_volume(
                p,
                sphere_faces.iter().map(|&f| &mesh.triangles[f]),
                [0.0; 3],
            )
        };
        let area_of = |p: &[[f64; 3]], c: usize| {
            let m = Mesh {
                positions: p.to_vec(),
                triangles: mesh.triangles.clone(),
            };
            barycentric_vertex_areas(&m)
                .iter()
                .zip(&topology.vertex_component)
                .filter(|(_, &k)| k == c)
                .map(|(a, _)| a)
                .sum::<f64>()
        };
        let moved: Vec<[f64; 3]> = mesh
            .positions
            .iter()
            .zip(&topology.vertex_component)
            .map(|(p, &c)| {
                let s = if c == 0 { 0.8 } else { 0.5 };
                [s * p[0] + 1.0, s * p[1], s * p[2] - 2.0]
            })
            .collect();
        for preserve in Preserve::ALL {
            let mut policy = ScalePolicy::new(
                preserve,
                &topology,
                &mesh.positions,
                &mesh.triangles,
                &areas0,
            );
            let mut p = moved.clone();
            let m = Mesh {
                positions: p.clone(),
                triangles: mesh.triangles.clone(),
            };
            let factors = policy
                .restore(&mut p, &mesh.triangles, &barycentric_vertex_areas(&m))
                .to_vec();
            let (v0, v) = (volume(&mesh.positions), volume(&p));
            let (a0, a) = (area_of(&mesh.positions, 0), area_of(&p, 0));
            let cap = (area_of(&mesh.positions, 1), area_of(&p, 1));
            match preserve {
                Preserve::Area => {
                    assert!((a / a0 - 1.0).abs() < 1e-12, "area {a} vs {a0}");
                    assert!((factors[0] - 1.25).abs() < 1e-12);
                }
                Preserve::Volume => {
                    assert!((v / v0 - 1.0).abs() < 1e-12, "volume {v} vs {v0}");
                    assert!((factors[0] - 1.25).abs() < 1e-12);
                }
                Preserve::None => {
                    assert!((v / v0 - 0.512).abs() < 1e-12, "volume {v} vs {v0}");
                    assert_eq!(factors, vec![1.0, 1.0]);
                }
            }
            // The open cap keeps its area under `Volume` as under `Area`.
            if preserve != Preserve::None {
                assert!(
                    (cap.1 / cap.0 - 1.0).abs() < 1e-12,
                    "{preserve:?}: cap area"
                );
            }
            // Every mode puts the centroids back.
            let again = ScalePolicy::new(
                Preserve::None,
                &topology,
                &p,
                &mesh.triangles,
                &area_weights(&p, &mesh.triangles),
            );
            for c in 0..2 {
                for k in 0..3 {
                    assert!(
                        (again.centroid[c][k] - policy.target_centroid[c][k]).abs() < 1e-12,
                        "{preserve:?}: centroid of component {c}"
                    );
                }
            }
        }
    }

    fn area_weights(p: &[[f64; 3]], t: &[[usize; 3]]) -> Vec<f64> {
        barycentric_vertex_areas(&Mesh {
            positions: p.to_vec(),
            triangles: t.to_vec(),
        })
    }

    #[test]
    fn factors_follow_the_power_of_their_measure() {
        assert!((area_factor(4.0, 1.0) - 0.5).abs() < 1e-15);
        assert!((volume_factor(8.0, 1.0) - 0.5).abs() < 1e-15);
        // Inside out or flat: left alone.
        assert_eq!(volume_factor(-1.0, 1.0), 1.0);
        assert_eq!(volume_factor(0.0, 1.0), 1.0);
        assert_eq!(area_factor(0.0, 1.0), 1.0);
    }
}
