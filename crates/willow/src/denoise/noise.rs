//! What a mesh says about its own noise: the spread of its dihedral angles.
//!
//! On a smooth surface sampled finely the normals of adjacent faces differ by a few degrees
//! at most; noise of a fraction σ of an edge tilts each face by about σ radians, so adjacent
//! normals differ by tens of degrees. Sharp features are few edges and barely move a median.

use super::score::dihedral_angles;
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;

/// The mesh's noise as its dihedral angles tell it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseEstimate {
    /// The median angle between the normals of edge-adjacent faces, degrees.
    pub median_dihedral: f64,
}

/// [`NoiseEstimate`] of `mesh`.
pub fn estimate(mesh: &Mesh, topology: &Topology) -> NoiseEstimate {
    NoiseEstimate {
        median_dihedral: median_dihedral(&mesh.positions, &mesh.triangles, &topology.edge_faces),
    }
}

/// The median dihedral angle (degrees) of a surface's interior edges; 0 without any.
pub fn median_dihedral(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    edge_faces: &[[Option<usize>; 2]],
) -> f64 {
    let mut angles = dihedral_angles(positions, triangles, edge_faces);
    if angles.is_empty() {
        return 0.0;
    }
    let mid = angles.len() / 2;
    *angles.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// The share of interior edges whose dihedral angle is below `degrees`.
pub fn flat_share(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    edge_faces: &[[Option<usize>; 2]],
    degrees: f64,
) -> f64 {
    let angles = dihedral_angles(positions, triangles, edge_faces);
    if angles.is_empty() {
        return 1.0;
    }
    angles.iter().filter(|&&a| a < degrees).count() as f64 / angles.len() as f64
}

/// A drop of the median dihedral angle by at least this much (degrees) in one filtering
/// iteration means the mesh was noisy ([`is_noisy`]).
pub const NOISE_DROP_DEGREES: f64 = 5.0;

/// Whether one filtering iteration that took the median dihedral angle from `before` to
/// `after` (degrees) removed noise. Noise of 0.2 of an edge puts the median near 20° and one
/// iteration takes it below 10°; a clean surface's median is its curvature over its
/// resolution (2–6° on the shared meshes) and moves by at most 3° (nefertiti, whose slivers
/// flatten). Measured: drops of 15–21° on the four denoising pairs, of −1–3° on their clean
/// originals and on spot, cheburashka, nefertiti, the Stanford bunny, botijo and the duck.
pub fn is_noisy(before: f64, after: f64) -> bool {
    before - after >= NOISE_DROP_DEGREES
}
