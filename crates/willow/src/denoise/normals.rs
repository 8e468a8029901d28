//! Face normals and their filtering: the bilateral normal filter (Zheng et al. 2011) and its
//! guided form (Zhang et al. 2015), which takes the range weight from the normal of the most
//! consistent patch around each face instead of from the noisy normal itself.

use super::neighbourhood::Rows;
use crate::geometry::vec3::{add, cross, dot, norm, norm2, scale, sub};

/// Unit normals, areas and centroids of every face. A face of zero area gets the zero normal
/// (it then weighs nothing: its area is zero too).
pub fn face_frames(
    positions: &[[f64; 3]],
    triangles: &[[usize; 3]],
    normals: &mut [[f64; 3]],
    areas: &mut [f64],
    centroids: &mut [[f64; 3]],
) {
    for (f, t) in triangles.iter().enumerate() {
        let [a, b, c] = t.map(|v| positions[v]);
        let n = cross(sub(b, a), sub(c, a));
        let len = norm(n);
        areas[f] = 0.5 * len;
        normals[f] = if len > 0.0 {
            scale(n, 1.0 / len)
        } else {
            [0.0; 3]
        };
        centroids[f] = scale(add(add(a, b), c), 1.0 / 3.0);
    }
}

/// How consistent a patch's normals are (Zhang et al. 2015, Eq. 4): the largest normal
/// difference in the patch times its relative total variation (the largest difference across
/// an inner edge over their sum). Small for a flat patch, and for one crossed by a single
/// sharp edge much smaller than for one that straddles noise everywhere.
pub fn patch_consistency(patch: &[usize], inner_edges: &[[usize; 2]], normals: &[[f64; 3]]) -> f64 {
    const EPSILON: f64 = 1e-9;
    let mut max_difference: f64 = 0.0;
    for (i, &a) in patch.iter().enumerate() {
        for &b in &patch[i + 1..] {
            max_difference = max_difference.max(norm2(sub(normals[a], normals[b])));
        }
    }
    let (mut sum, mut max) = (0.0, 0.0f64);
    for &[a, b] in inner_edges {
        let d = norm(sub(normals[a], normals[b]));
        sum += d;
        max = max.max(d);
    }
    max_difference.sqrt() * max / (sum + EPSILON)
}

/// The guidance normal of every face: the area-weighted mean normal of the most consistent
/// patch among those (the rings of its ring's faces) that contain it (Zhang et al. 2015, §4.1).
/// `consistency` and `patch_normals` are scratch, one entry per face.
#[allow(clippy::too_many_arguments)]
pub fn guidance_normals(
    rings: &Rows,
    inner_edges: &[Vec<[usize; 2]>],
    normals: &[[f64; 3]],
    areas: &[f64],
    consistency: &mut [f64],
    patch_normals: &mut [[f64; 3]],
    guidance: &mut [[f64; 3]],
) {
    for j in 0..rings.len() {
        let patch = rings.row(j);
        consistency[j] = patch_consistency(patch, &inner_edges[j], normals);
        let mut mean = [0.0; 3];
        for &f in patch {
            mean = add(mean, scale(normals[f], areas[f]));
        }
        let len = norm(mean);
        patch_normals[j] = if len > 0.0 {
            scale(mean, 1.0 / len)
        } else {
            normals[j]
        };
    }
    for (i, g) in guidance.iter_mut().enumerate() {
        let best = rings
            .row(i)
            .iter()
            .copied()
            .min_by(|&a, &b| consistency[a].total_cmp(&consistency[b]))
            .unwrap_or(i);
        *g = patch_normals[best];
    }
}

/// One pass of the joint bilateral filter of face normals (Zhang et al. 2015, Eq. 2):
/// `n'_i ∝ Σ_{j ∈ disc(i)} A_j · K_s(|c_i − c_j|) · K_r(|g_i − g_j|) · n_j` with Gaussian
/// kernels of widths `sigma_s` (length) and `sigma_r` (normal difference). With the noisy
/// normals as guidance `g = n` it is Zheng et al.'s bilateral normal filter.
#[allow(clippy::too_many_arguments)]
pub fn filter_normals(
    discs: &Rows,
    normals: &[[f64; 3]],
    guidance: &[[f64; 3]],
    areas: &[f64],
    centroids: &[[f64; 3]],
    sigma_s: f64,
    sigma_r: f64,
    filtered: &mut [[f64; 3]],
) {
    let inv_s = -0.5 / (sigma_s * sigma_s);
    let inv_r = -0.5 / (sigma_r * sigma_r);
    for (i, out) in filtered.iter_mut().enumerate() {
        let mut sum = [0.0; 3];
        for &j in discs.row(i) {
            let ds = norm2(sub(centroids[i], centroids[j]));
            let dr = norm2(sub(guidance[i], guidance[j]));
            let w = areas[j] * (ds * inv_s + dr * inv_r).exp();
            sum = add(sum, scale(normals[j], w));
        }
        let len = norm(sum);
        *out = if len > 0.0 {
            scale(sum, 1.0 / len)
        } else {
            normals[i]
        };
    }
}

/// The angle between two unit normals, in degrees (0 for a zero normal).
pub fn angle_degrees(a: [f64; 3], b: [f64; 3]) -> f64 {
    if norm2(a) == 0.0 || norm2(b) == 0.0 {
        return 0.0;
    }
    dot(a, b).clamp(-1.0, 1.0).acos().to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flat_patch_is_perfectly_consistent_and_a_crease_less_so_than_noise() {
        let up = [0.0, 0.0, 1.0];
        let flat = [up; 4];
        let edges = [[0, 1], [1, 2], [2, 3]];
        assert_eq!(patch_consistency(&[0, 1, 2, 3], &edges, &flat), 0.0);
        // One sharp edge between two flat halves: the whole variation sits on one edge, so
        // the relative total variation is 1 and the measure is the crease's normal jump.
        let side = [1.0, 0.0, 0.0];
        let crease = [up, up, side, side];
        let c = patch_consistency(&[0, 1, 2, 3], &edges, &crease);
        assert!((c - 2f64.sqrt()).abs() < 1e-9 * 2f64.sqrt() + 1e-9);
        // Mild noise spread over every edge scores lower still (relative variation 1/3):
        // guidance prefers a patch on one side of a crease to one that straddles it.
        let tilt = |x: f64| {
            let n = [x, 0.0, 1.0];
            scale(n, 1.0 / norm(n))
        };
        let noisy = [tilt(0.2), tilt(-0.2), tilt(0.2), tilt(-0.2)];
        let n = patch_consistency(&[0, 1, 2, 3], &edges, &noisy);
        assert!(n < c, "noise {n} against crease {c}");
    }

    #[test]
    fn filtering_identical_normals_leaves_them_unchanged() {
        let n = [[0.6, 0.0, 0.8]; 3];
        let discs = Rows {
            start: vec![0, 3, 6, 9],
            items: vec![0, 1, 2, 1, 0, 2, 2, 0, 1],
        };
        let mut out = [[0.0; 3]; 3];
        let c = [[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        filter_normals(&discs, &n, &n, &[1.0; 3], &c, 1.0, 0.35, &mut out);
        for o in out {
            assert!(angle_degrees(o, n[0]) < 1e-6);
        }
    }

    #[test]
    fn the_range_weight_keeps_a_crease_that_the_spatial_weight_alone_would_blur() {
        // Two faces up, two faces sideways, all within one disc.
        let up = [0.0, 0.0, 1.0];
        let side = [1.0, 0.0, 0.0];
        let n = [up, up, side, side];
        let discs = Rows {
            start: vec![0, 4, 8, 12, 16],
            items: vec![0, 1, 2, 3, 1, 0, 2, 3, 2, 0, 1, 3, 3, 0, 1, 2],
        };
        let c = [[0.0; 3]; 4];
        let mut sharp = [[0.0; 3]; 4];
        filter_normals(&discs, &n, &n, &[1.0; 4], &c, 1.0, 0.35, &mut sharp);
        assert!(angle_degrees(sharp[0], up) < 0.05, "{:?}", sharp[0]);
        let mut blurred = [[0.0; 3]; 4];
        filter_normals(&discs, &n, &n, &[1.0; 4], &c, 1.0, 100.0, &mut blurred);
        assert!((angle_degrees(blurred[0], up) - 45.0).abs() < 0.01);
    }
}
