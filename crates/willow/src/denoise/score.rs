//! The field's two measures of a denoised mesh against its clean original with the same
//! connectivity (Zhang et al. 2015, §6): θ, the mean angle between corresponding face normals,
//! and Dv, the mean distance from the result's vertices to the clean surface.

use super::normals::angle_degrees;
use crate::geometry::bvh::Bvh;
use crate::geometry::operators::face_areas_into;
use crate::geometry::vec3::{cross, norm, scale, sub};

fn unit_normal(p: &[[f64; 3]], t: [usize; 3]) -> [f64; 3] {
    let n = cross(sub(p[t[1]], p[t[0]]), sub(p[t[2]], p[t[0]]));
    let len = norm(n);
    if len > 0.0 {
        scale(n, 1.0 / len)
    } else {
        [0.0; 3]
    }
}

/// θ: the mean angle (degrees) between the normals of the same face on two embeddings of one
/// connectivity.
pub fn mean_normal_angle(a: &[[f64; 3]], b: &[[f64; 3]], triangles: &[[usize; 3]]) -> f64 {
    if triangles.is_empty() {
        return 0.0;
    }
    let sum: f64 = triangles
        .iter()
        .map(|&t| angle_degrees(unit_normal(a, t), unit_normal(b, t)))
        .sum();
    sum / triangles.len() as f64
}

/// The angle (degrees) between the normals of the two faces of every interior edge listed,
/// on one embedding: the dihedral deviation from flat.
pub fn dihedral_angles(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    edge_faces: &[[Option<usize>; 2]],
) -> Vec<f64> {
    edge_faces
        .iter()
        .filter_map(|pair| match *pair {
            [Some(f), Some(g)] => Some(angle_degrees(
                unit_normal(positions, triangles[f]),
                unit_normal(positions, triangles[g]),
            )),
            _ => None,
        })
        .collect()
}

/// Dv: the mean distance from `points` to the surface (`positions`, `triangles`).
pub fn mean_distance_to_surface(
    points: &[[f64; 3]],
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
) -> f64 {
    if points.is_empty() || triangles.is_empty() {
        return 0.0;
    }
    let bvh = Bvh::new(positions, triangles);
    let mut hint = None;
    let mut sum = 0.0;
    for &p in points {
        if let Some((face, d2)) = bvh.nearest(positions, triangles, p, hint) {
            sum += d2.sqrt();
            hint = Some(face);
        }
    }
    sum / points.len() as f64
}

/// θ and Dv of one result against its clean original (same connectivity).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Score {
    /// Mean angle between corresponding face normals, degrees.
    pub theta: f64,
    /// Mean distance from the result's vertices to the clean surface, per mille of the clean
    /// mesh's bounding-box diagonal.
    pub distance: f64,
}

/// [`Score`] of `result` against `clean` on `triangles`.
pub fn score(result: &[[f64; 3]], clean: &[[f64; 3]], triangles: &[[usize; 3]]) -> Score {
    let diagonal = bounding_diagonal(clean).max(f64::MIN_POSITIVE);
    Score {
        theta: mean_normal_angle(result, clean, triangles),
        distance: 1e3 * mean_distance_to_surface(result, clean, triangles) / diagonal,
    }
}

/// The share of faces crowded on `after` against `before` (one connectivity): faces whose
/// share of the total area fell below `1e-3` of their share on `before` — the crumpling a
/// user sees, which Q (angles only) does not.
pub fn crowded_share(before: &[[f64; 3]], after: &[[f64; 3]], triangles: &[[usize; 3]]) -> f64 {
    if triangles.is_empty() {
        return 0.0;
    }
    let mut a0 = vec![0.0; triangles.len()];
    let mut a1 = vec![0.0; triangles.len()];
    face_areas_into(before, triangles, &mut a0);
    face_areas_into(after, triangles, &mut a1);
    let (s0, s1): (f64, f64) = (a0.iter().sum(), a1.iter().sum());
    let crowded = a0
        .iter()
        .zip(&a1)
        .filter(|(x, y)| **y / s1 < 1e-3 * **x / s0)
        .count();
    crowded as f64 / triangles.len() as f64
}

/// The length of the diagonal of the bounding box of `positions`.
pub fn bounding_diagonal(positions: &[[f64; 3]]) -> f64 {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in positions {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    if positions.is_empty() {
        return 0.0;
    }
    norm(sub(hi, lo))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::icosphere;

    #[test]
    fn a_rotation_by_a_known_angle_gives_that_normal_angle() {
        let m = icosphere(2);
        let (s, c) = 10f64.to_radians().sin_cos();
        let turned: Vec<[f64; 3]> = m
            .positions
            .iter()
            .map(|p| [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]])
            .collect();
        assert!(mean_normal_angle(&m.positions, &m.positions, &m.triangles) < 1e-5);
        // A turn about z by 10° turns a normal at polar angle φ by 10° on the equator and by
        // nothing at the poles (cos = cos²φ + sin²φ·cos 10°): the mean lies between.
        let theta = mean_normal_angle(&m.positions, &turned, &m.triangles);
        assert!(theta > 5.0 && theta < 10.0, "{theta}");
    }

    #[test]
    fn points_on_a_sphere_scaled_out_lie_at_the_scale_difference() {
        let m = icosphere(4);
        let out: Vec<[f64; 3]> = m.positions.iter().map(|p| scale(*p, 1.1)).collect();
        // The vertices of the unit icosphere lie on the unit sphere; the faces sag inside it
        // by at most 1 − cos(half an edge's angle), well under 1% at 4 subdivisions.
        let d = mean_distance_to_surface(&out, &m.positions, &m.triangles);
        assert!((d - 0.1).abs() < 0.002, "{d}");
        assert!(mean_distance_to_surface(&m.positions, &m.positions, &m.triangles) < 1e-12);
    }

    #[test]
    fn a_face_squashed_a_million_fold_is_crowded_and_a_scaled_mesh_is_not() {
        let m = icosphere(2);
        let scaled: Vec<[f64; 3]> = m.positions.iter().map(|p| scale(*p, 3.0)).collect();
        assert_eq!(crowded_share(&m.positions, &scaled, &m.triangles), 0.0);
        // Move one vertex of face 0 onto the midpoint of its other two: that face (and only
        // faces around that vertex) loses its area.
        let mut squashed = m.positions.clone();
        let [a, b, c] = m.triangles[0];
        squashed[a] = [0, 1, 2].map(|k| 0.5 * (m.positions[b][k] + m.positions[c][k]));
        let share = crowded_share(&m.positions, &squashed, &m.triangles);
        assert!(share > 0.0 && share < 0.05, "{share}");
    }

    #[test]
    fn a_unit_cube_corner_to_corner_is_root_three() {
        let pts = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.2, 0.9]];
        assert!((bounding_diagonal(&pts) - 3f64.sqrt()).abs() < 1e-12);
    }
}
