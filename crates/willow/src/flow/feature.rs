//! Feature scale: remove the detail smaller than a length, keep the shape above it
//! (`FlowParams::feature_size`, issue 29 item 4; docs/algorithm.md §11).
//!
//! Built on the spectral filter of §4 ([`super::filter`]): the flow direction `−2H` is
//! filtered with the crossover at the feature size ([`feature_filter`]), so the curvature of
//! detail below it is removed at nearly the full rate and that of the shape above it hardly at
//! all. That alone does not keep the shape. The filter acts on the *change of curvature* to
//! first order; removing detail of finite amplitude moves the surface at low frequency to
//! second order, because the detail's own curvature and area are quadratic in its amplitude
//! and do not average out over the large shape (measured on a 2:1:1 ellipsoid carrying bumps
//! of wavelength 0.26 and relative amplitude 0.02: three steps at σ = 1e-4, k = 2 take it to
//! 1.64:1:1, while the same ellipsoid without bumps keeps 1.99:1:1; halving the amplitude
//! divides the loss by about 3, doubling it multiplies it by about 3: quadratic). So each
//! step's *motion* is filtered as well: the low-frequency part of the displacement,
//! `(id + σ(−Δ)^k)⁻¹ (f̃ − f)` with the filter's own operator on the surface the step started
//! from ([`remove_low_frequency`]), is taken back. What is left moves the detail only.
//!
//! The size is the large shape's too: under a feature scale the default `preserve: area`
//! keeps only the centroid ([`scale_policy`]).
//!
//! The run ends by itself ([`super::stopping::Outcome::FeatureScaleReached`]) once the energy
//! of the curvature in the filtered band, `Σ_i F(H)_i² A_i` ([`band_energy`], in units of W),
//! has fallen to [`DETAIL_TOLERANCE`] of the input's.

use super::filter::{FilterError, FilterSolver, SpectralFilter};
use super::{FlowError, Preserve};

/// Filter order of a feature scale: k = 2 approximates the norm that position-based Willmore
/// flow uses (§4, Figure 19), and its pattern (two rings) keeps the filter system cheap.
pub const FEATURE_K: u32 = 2;

/// The detail is gone when the band's energy has fallen to this fraction of the input's: its
/// curvature amplitude to a tenth.
pub const DETAIL_TOLERANCE: f64 = 1e-2;

/// The energy of the band a feature scale removes, at the input and now.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeatureDetail {
    /// `Σ F(H)² A` of the input (units of the Willmore energy).
    pub initial: f64,
    /// The same on the surface the flow is on.
    pub current: f64,
}

impl FeatureDetail {
    /// Whether the detail below the feature size is gone ([`DETAIL_TOLERANCE`]).
    pub fn reached(&self) -> bool {
        self.current <= DETAIL_TOLERANCE * self.initial
    }
}

/// A feature size must be one the mesh can hold: at least [`MIN_EDGES_PER_FEATURE`] mean
/// edge lengths. Below that the filter's crossover lies past the mesh's highest frequency,
/// so the flow would pass on nothing and the request would silently do nothing.
/// The limit itself passes, and the message states it rounded *up* (six significant digits),
/// so that the figure it prints is one the check accepts (issue 39: "0.234378 is below … about
/// 0.234378 across" refused the number it had printed).
pub fn check_resolution(length: f64, mean_edge: f64) -> Result<(), FlowError> {
    let limit = MIN_EDGES_PER_FEATURE * mean_edge;
    if length < limit {
        return Err(FlowError::InvalidParameter {
            name: "feature_size",
            reason: format!(
                "{length} is below the mesh's resolution: its mean edge is {mean_edge:.6}, \
                 so the smallest feature_size it can hold is {} ({MIN_EDGES_PER_FEATURE} mean \
                 edges)",
                round_up(limit)
            ),
        });
    }
    Ok(())
}

/// `x` > 0 rounded up to six significant digits.
fn round_up(x: f64) -> f64 {
    if !(x.is_finite() && x > 0.0) {
        return x;
    }
    let scale = 10f64.powi(5 - x.log10().floor() as i32);
    let up = (x * scale).ceil() / scale;
    // Division can land a hair below `x`; step to the next representable value if so.
    if up < x {
        f64::from_bits(up.to_bits() + 1)
    } else {
        up
    }
}

/// The smallest feature size, in mean edge lengths: a bump needs about two edges across to
/// exist on the mesh at all.
pub const MIN_EDGES_PER_FEATURE: f64 = 2.0;

/// What the scale policy keeps under a feature scale: `area` (the default) keeps only the
/// centroid. The detail carries area (bumps 0.13 across and 2% high add about 3% to the
/// ellipsoid's), and restoring it after the detail is gone inflates the whole shape (by 1.6%
/// in length on that ellipsoid: extents 4.065 against 4.000), while the filtered motion
/// already holds the large shape, its size included (extents 4.000 to 1e-5 without the
/// rescale). `volume` is kept as asked.
pub fn scale_policy(preserve: Preserve, feature_size: Option<f64>) -> Preserve {
    match (preserve, feature_size) {
        (Preserve::Area, Some(_)) => Preserve::None,
        (p, _) => p,
    }
}

/// The spectral filter whose crossover lies at the feature size `length` on a surface of area
/// `4π R²` (`radius` R), in the unitless σ of [`SpectralFilter`].
///
/// Detail of size `L` (a bump `L` across) is half a wavelength: the wavelength `2L` is the
/// eigenvalue `μ_c = (2π / 2L)² = (π / L)²` of −Δ. The filter keeps the fraction
/// `σ' μ^k / (1 + σ' μ^k)` of a mode with `σ'` in model units, so `σ' = μ_c^{−k}` puts the
/// half-way point at `μ_c`; the filter takes `σ = σ' / R^{2k}`.
pub fn feature_filter(length: f64, radius: f64) -> SpectralFilter {
    let k = FEATURE_K;
    let crossover = (std::f64::consts::PI / length).powi(2);
    SpectralFilter {
        sigma: crossover.powi(-(k as i32)) / radius.powi(2 * k as i32),
        k,
    }
}

/// `Σ_i v_i² A_i / 4` over the vertices that may move (all but those marked `held`), for the
/// filtered direction `v = F(−2H)`: the Willmore energy of the filtered band.
pub fn band_energy(direction: &[f64], areas: &[f64], held: Option<&[bool]>) -> f64 {
    direction
        .iter()
        .zip(areas)
        .enumerate()
        .filter(|(i, _)| !held.is_some_and(|h| h[*i]))
        .map(|(_, (v, a))| 0.25 * v * v * a)
        .sum()
}

/// Take back the low-frequency part of a step's motion: `f̃ ← f̃ − (id + σ(−Δ)^k)⁻¹ (f̃ − f)`,
/// with the operator of the filter's last [`FilterSolver::apply`] (the surface `before`, with
/// vertex areas `areas`). Vertices marked `held` do not move (their displacement is zero and
/// stays zero). `column` is scratch of one entry per vertex.
pub fn remove_low_frequency(
    filter: &mut FilterSolver,
    areas: &[f64],
    before: &[[f64; 3]],
    positions: &mut [[f64; 3]],
    held: Option<&[bool]>,
    column: &mut [f64],
) -> Result<(), FilterError> {
    for axis in 0..3 {
        for (c, (p, b)) in column.iter_mut().zip(positions.iter().zip(before)) {
            *c = p[axis] - b[axis];
        }
        filter.low_pass(areas, column)?;
        for (i, (p, c)) in positions.iter_mut().zip(column.iter()).enumerate() {
            if !held.is_some_and(|h| h[i]) {
                p[axis] -= c;
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod resolution_tests {
    use super::*;

    #[test]
    fn the_limit_passes_and_the_figure_the_message_prints_passes_too() {
        for mean_edge in [0.117189, 1.0, 3.3e-4, 12345.678] {
            let limit = MIN_EDGES_PER_FEATURE * mean_edge;
            assert!(check_resolution(limit, mean_edge).is_ok());
            let Err(FlowError::InvalidParameter { name, reason }) =
                check_resolution(0.999 * limit, mean_edge)
            else {
                panic!("below the limit is refused");
            };
            assert_eq!(name, "feature_size");
            let printed: f64 = reason
                .split("can hold is ")
                .nth(1)
                .and_then(|rest| rest.split(' ').next())
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("a number in {reason}"));
            assert!(
                printed >= limit && printed <= limit * (1.0 + 1e-5),
                "{printed} vs {limit}"
            );
            assert!(check_resolution(printed, mean_edge).is_ok(), "{reason}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a unit sphere the eigenvalues of −Δ are l(l+1): a feature size of π/√(l(l+1))
    /// puts the crossover (σ μ^k = 1) at degree l.
    #[test]
    fn the_crossover_lies_at_the_feature_size() {
        for l in [4.0_f64, 10.0, 28.0] {
            let mu = l * (l + 1.0);
            let f = feature_filter(std::f64::consts::PI / mu.sqrt(), 1.0);
            assert!((f.sigma * mu.powi(f.k as i32) - 1.0).abs() < 1e-12);
            // Twice the radius: the same length is a higher degree, σ scales by R^{−2k}.
            let g = feature_filter(std::f64::consts::PI / mu.sqrt(), 2.0);
            assert!((g.sigma / f.sigma - 2f64.powi(-4)).abs() < 1e-15);
        }
    }

    #[test]
    fn area_keeps_only_the_centroid_under_a_feature_scale() {
        assert_eq!(scale_policy(Preserve::Area, Some(0.1)), Preserve::None);
        assert_eq!(scale_policy(Preserve::Volume, Some(0.1)), Preserve::Volume);
        assert_eq!(scale_policy(Preserve::Area, None), Preserve::Area);
    }

    #[test]
    fn band_energy_leaves_out_held_vertices() {
        let v = [2.0, 4.0];
        let a = [1.0, 0.5];
        assert_eq!(band_energy(&v, &a, None), 1.0 + 2.0);
        assert_eq!(band_energy(&v, &a, Some(&[true, false])), 2.0);
    }
}
