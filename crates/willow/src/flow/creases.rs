//! The conformal flow with a part's creases held: each crease is held as a seam with the
//! machinery regions use ([`super::region`]), so the flow fairs every smooth patch between
//! the creases and the creases stay exactly where they were, sharp.
//!
//! Why held and not slid along: a crease vertex of a CAD part lies where two (or three)
//! faces of the design meet, and the flow has no way to know those surfaces. What is held is
//! the *crease band* ([`crease_band`]): the crease vertices and their one-ring, so every face
//! that touches a crease keeps its place and the crease its dihedral angle exactly, and each
//! patch meets the band with its positions and tangent planes given, as a region's `smooth`
//! seam does (§6.3.2, two rings). Holding the crease vertices alone would leave the patches
//! free to turn about them (a fixed boundary, C0): a chamfer's crease error was 16° after 10
//! steps that way. The creases are found on the denoised surface ([`held_creases`]), so the
//! noise of a scan makes none.

use super::region::{self, RegionFlow, Seam};
use super::{Boundary, Flow, FlowError, FlowParams, Method, Preserve};
use crate::denoise::noise::median_dihedral;
use crate::denoise::{denoise, DenoiseParams};
use crate::mesh::creases::{detect_creases, Creases, FeatureAngle};
use crate::mesh::topology::Topology;
use crate::mesh::Mesh;
use crate::metrics::StepMetrics;

/// Why creases cannot be held under `params`, if they cannot: the flows that are not the
/// conformal flow's do not hold vertices, a prescribed or CMC boundary is a condition of its
/// own on the border the crease seams would fight, and held vertices pin a component's size,
/// which `preserve: volume` would rescale. Under [`FeatureAngle::Auto`] these simply hold no
/// creases; an angle the caller named is refused ([`FlowParams::validate`]).
pub fn unheld_reason(params: &FlowParams) -> Option<String> {
    match params.method {
        Method::Conformal | Method::Denoise => {}
        other => {
            return Some(format!(
                "creases are held by the conformal flow and found by `denoise`, not by `{}`",
                other.name()
            ))
        }
    }
    if params.method == Method::Conformal {
        if matches!(params.boundary, Boundary::Prescribed(_) | Boundary::Cmc) {
            return Some(
                "creases cannot be held with a prescribed or CMC boundary: use `fixed` or \
                 `free`, or feature_angle `none`"
                    .into(),
            );
        }
        if params.preserve == Preserve::Volume {
            return Some(
                "held creases pin their component's size, which `preserve: volume` would \
                 rescale: use `area` or `none`, or feature_angle `none`"
                    .into(),
            );
        }
    }
    None
}

/// `metrics` with the count of `creases` ([`StepMetrics::crease_edges`]), when there are any.
pub fn with_crease_count(mut metrics: StepMetrics, creases: &[[usize; 2]]) -> StepMetrics {
    if !creases.is_empty() {
        metrics.crease_edges = Some(u32::try_from(creases.len()).unwrap_or(u32::MAX));
    }
    metrics
}

/// A surface whose median dihedral angle is below this (degrees) is read as it is: clean
/// surfaces have 2–6° at the shared meshes' resolutions, noise of 0.2 of an edge puts the
/// median near 20° (`crate::denoise::noise::is_noisy`'s measurements).
pub const CLEAN_MEDIAN_DIHEDRAL: f64 = 8.0;

/// The creases of `mesh` under `angle`, read off its denoised surface: noise cuts a crease
/// into zigzags and puts sharp edges everywhere, denoising makes it whole again. A surface
/// that is plainly clean ([`CLEAN_MEDIAN_DIHEDRAL`]) is read as it is, which spares the
/// filter (on a clean mesh its noise check would leave the positions as they are anyway, at
/// the cost of a filtering pass: 0.45 s on nefertiti).
pub fn held_creases(mesh: &Mesh, topology: &Topology, angle: FeatureAngle) -> Creases {
    if angle == FeatureAngle::None {
        return Creases::none(mesh.vertex_count());
    }
    let median = median_dihedral(&mesh.positions, &mesh.triangles, &topology.edge_faces);
    if median < CLEAN_MEDIAN_DIHEDRAL {
        return detect_creases(&mesh.positions, &mesh.triangles, topology, angle);
    }
    let denoised = denoise(mesh, DenoiseParams::default());
    detect_creases(&denoised, &mesh.triangles, topology, angle)
}

/// The crease vertices and every vertex that shares a triangle with one: what the conformal
/// flow holds (see the module notes).
pub fn crease_band(on_crease: &[bool], triangles: &[[usize; 3]]) -> Vec<bool> {
    let mut band = on_crease.to_vec();
    for t in triangles {
        if t.iter()
            .any(|&v| on_crease.get(v).copied().unwrap_or(false))
        {
            for &v in t {
                if let Some(b) = band.get_mut(v) {
                    *b = true;
                }
            }
        }
    }
    band
}

/// The conformal flow of `params` with the creases of `mesh` held, when it has creases and
/// they can be held; `None` otherwise (the caller builds the flow as it would without).
pub(crate) fn crease_flow(
    mesh: &Mesh,
    params: &FlowParams,
) -> Result<Option<Box<dyn Flow>>, FlowError> {
    if params.method != Method::Conformal || params.feature_angle == FeatureAngle::None {
        return Ok(None);
    }
    params.validate()?;
    if unheld_reason(params).is_some() {
        return Ok(None);
    }
    let topology = Topology::new(mesh);
    let creases = held_creases(mesh, &topology, params.feature_angle);
    if creases.is_empty() {
        return Ok(None);
    }
    let invalid = |name, reason: String| FlowError::InvalidParameter { name, reason };
    let mut moving = if params.regions.is_empty() {
        vec![true; mesh.vertex_count()]
    } else {
        region::select(&mesh.positions, &params.regions).map_err(|e| invalid("region", e))?
    };
    if params.boundary == Boundary::Fixed {
        for (m, b) in moving
            .iter_mut()
            .zip(topology.boundary_vertex_mask(mesh.vertex_count()))
        {
            *m &= !b;
        }
    }
    for (m, c) in moving
        .iter_mut()
        .zip(crease_band(&creases.vertices, &mesh.triangles))
    {
        *m &= !c;
    }
    if !moving.iter().any(|&m| m) {
        // A tessellation so coarse that every vertex is on a crease band: `auto` steps aside
        // (the flow then finds it `already_fair`, or fairs it as it would without creases);
        // an angle the caller named is refused.
        if params.feature_angle == FeatureAngle::Auto {
            return Ok(None);
        }
        return Err(invalid(
            "feature_angle",
            format!(
                "every vertex the flow would move lies on or next to one of the {} crease edges \
                 found: nothing is left to fair between them (feature_angle `none` fairs \
                 across them)",
                creases.edges.len()
            ),
        ));
    }
    let seam_params = FlowParams {
        // Without a region the crease seams are the only held vertices, and a crease is a
        // C0 seam by definition: its two sides meet at an angle.
        seam: if params.regions.is_empty() {
            Seam::Fixed
        } else {
            params.seam
        },
        boundary: Boundary::Free,
        regions: Vec::new(),
        feature_angle: FeatureAngle::None,
        ..params.clone()
    };
    let mut flow = RegionFlow::with_moving(mesh, &seam_params, &moving)?;
    flow.set_creases(creases.vertex_pairs(&topology));
    Ok(Some(Box::new(flow)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_band_is_the_creases_and_the_triangles_touching_them() {
        // Two triangles sharing the edge 1–2, and a third apart.
        let triangles = [[0, 1, 2], [1, 3, 2], [4, 5, 6]];
        let on_crease = [true, false, false, false, false, false, false];
        assert_eq!(
            crease_band(&on_crease, &triangles),
            [true, true, true, false, false, false, false]
        );
        let on_edge = [false, true, true, false, false, false, false];
        assert_eq!(
            crease_band(&on_edge, &triangles),
            [true, true, true, true, false, false, false]
        );
    }
}
