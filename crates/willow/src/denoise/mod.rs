//! Feature-preserving denoising before any fairing: guided mesh normal filtering (Zhang,
//! Deng, Zhang, Bouaziz, Liu, "Guided mesh normal filtering", Pacific Graphics 2015) with the
//! vertex update of Sun et al. 2007.
//!
//! Why a stage of its own: a conformal map keeps every triangle's angles, and scanner noise
//! lives partly in those angles (tangential jitter), so no conformal deformation of a noisy
//! mesh is smooth; the flow shrinks the large shapes long before the small noise goes. Normal
//! filtering separates the two scales the other way round: each face normal is averaged with
//! its neighbours' only where their *guidance* normals (the mean normal of the most consistent
//! patch nearby) agree, so noise is averaged away while a crease, where the guidance jumps,
//! stays sharp. The vertices then follow the filtered normals.
//!
//! The parts, each a small function over plain arrays: [`neighbourhood`] (rings, patches,
//! geometric discs, built once), [`normals`] (face frames, patch consistency, guidance, the
//! joint bilateral filter), [`vertex`] (the vertex update), and [`noise`] (what the mesh says
//! about its own noise, for the defaults).

pub mod neighbourhood;
pub mod noise;
pub mod normals;
pub mod score;
pub mod vertex;

use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use neighbourhood::Rows;
use serde::{Deserialize, Serialize};

/// How hard to denoise. `Default` is the reference implementation's setting (one guided
/// filtering pass and 10 vertex updates per outer iteration, σ_r 0.35, a disc of twice the
/// mean distance between adjacent face centroids) with the outer iterations chosen by the
/// mesh ([`DenoiseParams::iterations`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DenoiseParams {
    /// Outer iterations: each recomputes the guidance from the current normals, filters them
    /// once and moves the vertices. `None` (the default): as many as the mesh asks for. A mesh
    /// whose first iteration barely changes its dihedral angles has no noise to remove and is
    /// left as it is ([`noise::is_noisy`]); otherwise iterations go on while the share of
    /// flat edges still grows by [`SETTLED_GROWTH`] an iteration, from [`MIN_AUTO_ITERATIONS`]
    /// to [`MAX_AUTO_ITERATIONS`]. On a CAD part faces keep snapping onto their planes for
    /// a dozen iterations; on an organic surface the share settles after five or six, and
    /// further passes only erode its detail (measured on the denoising pairs: θ to the clean
    /// bunny rises from 5.4° at 5 iterations to 6.7° at 20, while fandisk's falls from 4.8°
    /// to 2.9°).
    pub iterations: Option<usize>,
    /// Vertex updates per outer iteration.
    pub vertex_iterations: usize,
    /// Width of the range kernel, in units of normal difference `|n_i − n_j|` (0.35 ≈ 20°):
    /// neighbours whose guidance differs by much more than this do not mix.
    pub sigma_r: f64,
    /// Radius of each face's filtering disc, in mean distances between adjacent face
    /// centroids; the spatial kernel's width is that mean distance.
    pub radius: f64,
    /// Guided (Zhang et al. 2015) or plain bilateral (Zheng et al. 2011) range weights.
    pub guided: bool,
}

impl Default for DenoiseParams {
    fn default() -> Self {
        DenoiseParams {
            iterations: None,
            vertex_iterations: 10,
            sigma_r: 0.35,
            radius: 2.0,
            guided: true,
        }
    }
}

/// Largest outer and vertex iteration counts accepted (beyond them nothing changes but time).
pub const MAX_ITERATIONS: usize = 200;
/// The widest filtering disc, in mean centroid distances `s`: a disc of radius `r·s` holds
/// about 2.4·r² faces (π r² s² over a face's 1.3 s² on a regular mesh), and the discs are
/// kept for the whole run, so at the upload limit (2M faces) radius 8 would hold 2.5 GB of
/// indices before any work; 4 holds a quarter of that.
pub const MAX_RADIUS: f64 = 4.0;
/// The fewest outer iterations [`DenoiseParams::iterations`]' automatic count takes.
pub const MIN_AUTO_ITERATIONS: usize = 4;
/// The most outer iterations the automatic count takes.
pub const MAX_AUTO_ITERATIONS: usize = 20;
/// The growth of the share of flat edges (dihedral below [`FLAT_DEGREES`]) per iteration
/// below which the automatic count stops.
pub const SETTLED_GROWTH: f64 = 0.02;
/// A dihedral angle below this counts as flat, degrees.
pub const FLAT_DEGREES: f64 = 2.0;

impl DenoiseParams {
    /// Checks each field, naming it under `denoise.`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if let Some(n) = self.iterations {
            if n == 0 || n > MAX_ITERATIONS {
                return Err((
                    "denoise.iterations",
                    format!("must be between 1 and {MAX_ITERATIONS}, got {n}"),
                ));
            }
        }
        if self.vertex_iterations == 0 || self.vertex_iterations > MAX_ITERATIONS {
            return Err((
                "denoise.vertex_iterations",
                format!(
                    "must be between 1 and {MAX_ITERATIONS}, got {}",
                    self.vertex_iterations
                ),
            ));
        }
        if !(self.sigma_r.is_finite() && self.sigma_r > 0.0 && self.sigma_r <= 2.0) {
            return Err((
                "denoise.sigma_r",
                format!(
                    "must be in (0, 2] (a difference of unit normals), got {}",
                    self.sigma_r
                ),
            ));
        }
        if !(self.radius.is_finite() && self.radius >= 0.5 && self.radius <= MAX_RADIUS) {
            return Err((
                "denoise.radius",
                format!(
                    "must be between 0.5 and {MAX_RADIUS} (mean centroid distances), got {}",
                    self.radius
                ),
            ));
        }
        Ok(())
    }
}

/// A denoiser bound to one mesh: the neighbourhoods built once, the scratch for every pass,
/// and the input it measures its displacement from.
pub struct Denoiser {
    params: DenoiseParams,
    triangles: Vec<[usize; 3]>,
    edge_faces: Vec<[Option<usize>; 2]>,
    vertex_faces: Rows,
    rings: Rows,
    inner_edges: Vec<Vec<[usize; 2]>>,
    discs: Rows,
    origin: Vec<[f64; 3]>,
    held: Vec<bool>,
    max_displacement: Option<f64>,
    normals: Vec<[f64; 3]>,
    areas: Vec<f64>,
    centroids: Vec<[f64; 3]>,
    consistency: Vec<f64>,
    patch_normals: Vec<[f64; 3]>,
    guidance: Vec<[f64; 3]>,
    filtered: Vec<[f64; 3]>,
    moved: Vec<[f64; 3]>,
    done: usize,
    /// The share of flat edges after each iteration taken (the automatic count's measure).
    flat_shares: Vec<f64>,
    /// No noise found (the automatic count's verdict before the first iteration).
    clean: bool,
    /// The first iteration, taken by the noise check and handed out by the first call.
    pilot: Option<Vec<[f64; 3]>>,
}

impl Denoiser {
    /// `held`: vertices that never move (empty: none); `max_displacement`: no vertex moves
    /// further than this from where it is now (model units).
    pub fn new(
        mesh: &Mesh,
        topology: &Topology,
        params: DenoiseParams,
        held: Vec<bool>,
        max_displacement: Option<f64>,
    ) -> Denoiser {
        let f = mesh.face_count();
        let vertex_faces = neighbourhood::vertex_faces(mesh.vertex_count(), &mesh.triangles);
        let rings = neighbourhood::face_rings(&mesh.triangles, &vertex_faces);
        let inner_edges =
            neighbourhood::patch_inner_edges(&rings, &topology.edge_faces, &topology.face_edges);
        let mut normals = vec![[0.0; 3]; f];
        let mut areas = vec![0.0; f];
        let mut centroids = vec![[0.0; 3]; f];
        normals::face_frames(
            &mesh.positions,
            &mesh.triangles,
            &mut normals,
            &mut areas,
            &mut centroids,
        );
        let spacing =
            neighbourhood::mean_adjacent_centroid_distance(&centroids, &topology.edge_faces);
        let discs = neighbourhood::centroid_discs(&centroids, &rings, params.radius * spacing);
        let mut denoiser = Denoiser {
            params,
            triangles: mesh.triangles.clone(),
            edge_faces: topology.edge_faces.clone(),
            vertex_faces,
            rings,
            inner_edges,
            discs,
            origin: mesh.positions.clone(),
            held,
            max_displacement,
            normals,
            areas,
            centroids,
            consistency: vec![0.0; f],
            patch_normals: vec![[0.0; 3]; f],
            guidance: vec![[0.0; 3]; f],
            filtered: vec![[0.0; 3]; f],
            moved: vec![[0.0; 3]; mesh.vertex_count()],
            done: 0,
            flat_shares: Vec::new(),
            clean: false,
            pilot: None,
        };
        if params.iterations.is_none() {
            // The noise check: the first iteration, on a copy.
            let before =
                noise::median_dihedral(&mesh.positions, &mesh.triangles, &topology.edge_faces);
            let mut first = mesh.positions.clone();
            denoiser.filter_and_move(&mut first);
            let after = noise::median_dihedral(&first, &mesh.triangles, &topology.edge_faces);
            denoiser.clean = !noise::is_noisy(before, after);
            // A clean mesh takes no iteration: the copy is only kept for the first one.
            denoiser.pilot = (!denoiser.clean).then_some(first);
        }
        denoiser
    }

    /// Whether the automatic count found no noise (nothing will move).
    pub fn found_clean(&self) -> bool {
        self.clean
    }

    pub fn params(&self) -> &DenoiseParams {
        &self.params
    }

    /// Outer iterations taken so far.
    pub fn iterations_done(&self) -> usize {
        self.done
    }

    /// Whether every outer iteration has been taken: all that were asked for, or, with the
    /// automatic count, none on a clean mesh and otherwise until the flat share settles.
    pub fn finished(&self) -> bool {
        match self.params.iterations {
            Some(n) => self.done >= n,
            None => {
                if self.clean {
                    return true;
                }
                if self.done >= MAX_AUTO_ITERATIONS {
                    return true;
                }
                if self.done < MIN_AUTO_ITERATIONS {
                    return false;
                }
                match self.flat_shares.as_slice() {
                    [.., a, b] => b - a < SETTLED_GROWTH,
                    _ => false,
                }
            }
        }
    }

    /// One outer iteration on `positions` (the mesh's vertex order, where the last call left
    /// them): guidance from the current normals, one filtering pass, then the vertex updates.
    pub fn iterate(&mut self, positions: &mut [[f64; 3]]) {
        match self.pilot.take() {
            Some(first) if self.done == 0 => positions.copy_from_slice(&first),
            _ => self.filter_and_move(positions),
        }
        self.done += 1;
        if self.params.iterations.is_none() {
            let share =
                noise::flat_share(positions, &self.triangles, &self.edge_faces, FLAT_DEGREES);
            self.flat_shares.push(share);
        }
    }

    fn filter_and_move(&mut self, positions: &mut [[f64; 3]]) {
        normals::face_frames(
            positions,
            &self.triangles,
            &mut self.normals,
            &mut self.areas,
            &mut self.centroids,
        );
        let sigma_s =
            neighbourhood::mean_adjacent_centroid_distance(&self.centroids, &self.edge_faces);
        if self.params.guided {
            normals::guidance_normals(
                &self.rings,
                &self.inner_edges,
                &self.normals,
                &self.areas,
                &mut self.consistency,
                &mut self.patch_normals,
                &mut self.guidance,
            );
        } else {
            self.guidance.copy_from_slice(&self.normals);
        }
        if sigma_s > 0.0 {
            normals::filter_normals(
                &self.discs,
                &self.normals,
                &self.guidance,
                &self.areas,
                &self.centroids,
                sigma_s,
                self.params.sigma_r,
                &mut self.filtered,
            );
        } else {
            self.filtered.copy_from_slice(&self.normals);
        }
        for _ in 0..self.params.vertex_iterations {
            vertex::update_vertices(
                positions,
                &self.triangles,
                &self.vertex_faces,
                &self.filtered,
                &self.held,
                &self.origin,
                self.max_displacement,
                &mut self.centroids,
                &mut self.moved,
            );
        }
    }
}

/// Every outer iteration of `params` on `mesh`: the denoised positions.
pub fn denoise(mesh: &Mesh, params: DenoiseParams) -> Vec<[f64; 3]> {
    let topology = Topology::new(mesh);
    let mut denoiser = Denoiser::new(mesh, &topology, params, Vec::new(), None);
    let mut positions = mesh.positions.clone();
    while !denoiser.finished() {
        denoiser.iterate(&mut positions);
    }
    positions
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::{icosphere, mean_edge_length, with_noise};

    #[test]
    fn a_noisy_sphere_comes_out_closer_to_round() {
        let clean = icosphere(4);
        let noisy = with_noise(clean.clone(), 0.3, 7);
        let out = denoise(&noisy, DenoiseParams::default());
        assert_ne!(out, noisy.positions, "the noise check found noise");
        let theta =
            |p: &[[f64; 3]]| score::mean_normal_angle(p, &clean.positions, &clean.triangles);
        let before = theta(&noisy.positions);
        let after = theta(&out);
        assert!(after < before / 3.0, "θ {before:.2}° → {after:.2}°");
        // Still the unit sphere: its vertices a tenth of an edge from radius 1 on average and
        // none further than half an edge (the noise put them 0.3 of an edge off it, in each
        // coordinate: 0.5 on average).
        let h = mean_edge_length(&clean);
        let off: Vec<f64> = out
            .iter()
            .map(|p| ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 1.0).abs())
            .collect();
        let mean = off.iter().sum::<f64>() / off.len() as f64;
        let worst = off.iter().cloned().fold(0.0, f64::max);
        assert!(
            mean < 0.1 * h && worst < 0.5 * h,
            "mean {mean}, worst {worst}, edge {h}"
        );
    }
}

#[cfg(test)]
mod count_tests {
    use super::*;
    use crate::mesh::generate::{icosphere, with_noise};

    #[test]
    fn a_clean_mesh_is_left_alone_and_a_fixed_count_is_taken_exactly() {
        let clean = icosphere(4);
        let topology = Topology::new(&clean);
        let d = Denoiser::new(
            &clean,
            &topology,
            DenoiseParams::default(),
            Vec::new(),
            None,
        );
        assert!(d.found_clean() && d.finished());
        assert_eq!(denoise(&clean, DenoiseParams::default()), clean.positions);
        let noisy = with_noise(clean, 0.3, 1);
        let topology = Topology::new(&noisy);
        let mut d = Denoiser::new(
            &noisy,
            &topology,
            DenoiseParams {
                iterations: Some(3),
                ..DenoiseParams::default()
            },
            Vec::new(),
            None,
        );
        let mut p = noisy.positions.clone();
        while !d.finished() {
            d.iterate(&mut p);
        }
        assert_eq!(d.iterations_done(), 3);
    }

    #[test]
    fn the_automatic_count_stays_within_its_bounds() {
        let noisy = with_noise(icosphere(4), 0.3, 2);
        let topology = Topology::new(&noisy);
        let mut d = Denoiser::new(
            &noisy,
            &topology,
            DenoiseParams::default(),
            Vec::new(),
            None,
        );
        assert!(!d.found_clean());
        let mut p = noisy.positions.clone();
        while !d.finished() {
            d.iterate(&mut p);
        }
        let n = d.iterations_done();
        assert!(
            (MIN_AUTO_ITERATIONS..=MAX_AUTO_ITERATIONS).contains(&n),
            "{n}"
        );
    }
}
