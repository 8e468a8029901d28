//! The flow options of a job beyond method and step size: the spectral filter (§4) and the
//! boundary condition (§6.3), as a job spec carries them.
//!
//! They mirror the library's [`SpectralFilter`] and [`Boundary`] and serialize to the same
//! JSON (`"cmc"`, `{"prescribed": {"frame_angle": 0.2, "axis": {"fixed": [0, 0, 1]},
//! "angles": {"per_loop": [0.1, -0.1]}}}`), with two differences that make them fit for input
//! from the network: unknown fields are errors (a misspelt `frame_angel` must not silently
//! become 0), and [`BoundaryAngles::PerVertex`] has no counterpart (it names mesh vertex
//! indices, which a client of the service sees only in the welded order; it stays in the
//! library). The same names are the field paths errors report: `filter.k`,
//! `boundary.prescribed.axis.fixed`, and so on.

use serde::{Deserialize, Serialize};
use willow::flow::filter::SpectralFilter;
use willow::flow::{
    Boundary, BoundaryAngles, FlowError, FlowParams, Method, PrescribedVectors, RotationAxis,
};

/// Largest filter order: the library's `FilterSolver` builds `L (M⁻¹L)^{k−1}` for k ≤ 3.
pub const MAX_FILTER_K: u32 = willow::flow::filter::MAX_K;

/// Spectral filter of the flow direction (§4): `v ← v − (id + σ(−Δ)^k)⁻¹ v`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FilterSpec {
    // Whatever the mesh's size: see `willow::flow::filter`.
    /// Strength σ, unitless and > 0: σ = (l(l+1))^−k puts the crossover at spherical degree l.
    pub sigma: f64,
    /// Shape k ∈ 0..=3; k = 2 approximates position-based Willmore flow (Figure 19).
    pub k: u32,
}

impl FilterSpec {
    /// The library's filter.
    pub fn to_flow(self) -> SpectralFilter {
        SpectralFilter {
            sigma: self.sigma,
            k: self.k,
        }
    }
}

/// The filter of method `denoise` (guided mesh normal filtering, Zhang et al. 2015, with the
/// vertex update of Sun et al. 2007). Every field has a default; the defaults read the
/// iteration count off the mesh.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct DenoiseSpec {
    /// Outer iterations (1–200), each one guided filtering pass of the face normals and the
    /// vertex updates; null (the default): read off the mesh — none on a mesh with no noise,
    /// otherwise until the share of flat edges settles (4–20).
    pub iterations: Option<usize>,
    /// Vertex updates per outer iteration (1–200); default 10.
    pub vertex_iterations: usize,
    /// Width of the range kernel in unit-normal difference, (0, 2]; default 0.35 (≈ 20°):
    /// neighbours whose guidance normals differ by much more do not mix, so creases stay.
    pub sigma_r: f64,
    /// Radius of each face's filtering disc in mean distances between adjacent face
    /// centroids, 0.5–4; default 2.
    pub radius: f64,
    /// Guided range weights (default true); false is Zheng et al.'s bilateral normal filter.
    pub guided: bool,
}

impl Default for DenoiseSpec {
    fn default() -> Self {
        DenoiseSpec::from_flow(willow::denoise::DenoiseParams::default())
    }
}

impl DenoiseSpec {
    pub fn from_flow(p: willow::denoise::DenoiseParams) -> Self {
        DenoiseSpec {
            iterations: p.iterations,
            vertex_iterations: p.vertex_iterations,
            sigma_r: p.sigma_r,
            radius: p.radius,
            guided: p.guided,
        }
    }

    /// The library's filter parameters.
    pub fn to_flow(self) -> willow::denoise::DenoiseParams {
        willow::denoise::DenoiseParams {
            iterations: self.iterations,
            vertex_iterations: self.vertex_iterations,
            sigma_r: self.sigma_r,
            radius: self.radius,
            guided: self.guided,
        }
    }
}

/// Boundary condition for surfaces with boundary (§6.3); closed surfaces ignore it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default, utoipa::ToSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum BoundarySpec {
    /// The default: the border stays where it is. The conformal flow holds it (`fixed`):
    /// free, the boundary of an open scan is not elliptic (§6.2, Bohle and Pinkall 2013) and
    /// a raw rabbit scan crumpled into a fan moved 360‰ of its diagonal (issue 39). Free
    /// where the flow keeps the border itself: the other methods move boundary vertices like
    /// any other, and a region holds its own surroundings.
    #[default]
    Auto,
    /// The boundary moves freely (§6.2): an open surface may shrink away from its border.
    Free,
    /// Boundary vertices stay exactly where they are (§6.3.2).
    Fixed,
    /// `V = B` held at the input's conormals: converges to constant mean curvature (§6.3.1).
    Cmc,
    /// Prescribed boundary vectors (§6.3.1).
    Prescribed(PrescribedSpec),
}

impl BoundarySpec {
    /// The library's boundary condition for a flow of `method`, with regions or not
    /// ([`BoundarySpec::Auto`] resolves here).
    pub fn to_flow(&self, method: Method, regions: bool) -> Boundary {
        match self {
            BoundarySpec::Auto if method == Method::Conformal && !regions => Boundary::Fixed,
            BoundarySpec::Auto | BoundarySpec::Free => Boundary::Free,
            BoundarySpec::Fixed => Boundary::Fixed,
            BoundarySpec::Cmc => Boundary::Cmc,
            BoundarySpec::Prescribed(p) => Boundary::Prescribed(p.to_flow()),
        }
    }
}

/// §6.3.1: at each boundary vertex `V = cos φ·B + sin φ·N` is mapped to a target, the input's
/// `V` rotated by an angle about an axis. Every field may be left out.
// All defaults: the CMC condition.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct PrescribedSpec {
    // `flow::prescribed::MAX_FRAME_ANGLE`: at ±π/2, `V = ±N`.
    /// φ in radians, |φ| ≤ 1.5 (at ±π/2 the boundary problem is not elliptic).
    pub frame_angle: f64,
    /// Axis of the rotation from `V` to its target (default: the boundary tangent).
    pub axis: AxisSpec,
    /// Rotation angles in radians (default: 0 everywhere).
    pub angles: AnglesSpec,
}

impl PrescribedSpec {
    pub fn to_flow(&self) -> PrescribedVectors {
        PrescribedVectors {
            frame_angle: self.frame_angle,
            axis: match self.axis {
                AxisSpec::Tangent => RotationAxis::Tangent,
                AxisSpec::Fixed(a) => RotationAxis::Fixed(a),
            },
            angles: match &self.angles {
                AnglesSpec::Uniform(a) => BoundaryAngles::Uniform(*a),
                AnglesSpec::PerLoop(a) => BoundaryAngles::PerLoop(a.clone()),
            },
        }
    }
}

/// Axis of the rotation that makes the target from the input's `V`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default, utoipa::ToSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum AxisSpec {
    /// The boundary tangent at each vertex (flares or tucks the boundary).
    #[default]
    Tangent,
    // It need not be unit length; it tilts a whole loop.
    /// One direction in space for every vertex, `[x, y, z]`, finite and non-zero.
    Fixed([f64; 3]),
}

/// Rotation angles in radians.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum AnglesSpec {
    /// The same angle at every boundary vertex.
    Uniform(f64),
    // The count must match the uploaded mesh (checked against it at submission).
    /// One angle per boundary loop, in the order of the mesh's boundary loops.
    PerLoop(Vec<f64>),
}

impl Default for AnglesSpec {
    fn default() -> Self {
        AnglesSpec::Uniform(0.0)
    }
}

/// What is wrong with a filter or boundary spec, as (field path, reason).
pub type SpecViolation = (&'static str, String);

/// Check a filter against the library's rules ([`FlowParams::validate`]), naming the field.
pub fn check_filter(filter: &FilterSpec) -> Result<(), SpecViolation> {
    library_check(FlowParams {
        filter: Some(filter.to_flow()),
        ..FlowParams::default()
    })
}

/// Check a boundary spec's numbers (the per-loop count needs the mesh: [`check_loop_count`])
/// against the library's rules (`PrescribedVectors::validate`), naming the field.
pub fn check_boundary(boundary: &BoundarySpec) -> Result<(), SpecViolation> {
    match boundary {
        BoundarySpec::Prescribed(p) => p
            .to_flow()
            .validate()
            .map_err(|(field, e)| (field, e.to_string())),
        _ => Ok(()),
    }
}

/// The library's verdict on parameters the spec sets, as (field path, reason).
fn library_check(params: FlowParams) -> Result<(), SpecViolation> {
    params.validate().map_err(|e| match e {
        FlowError::InvalidParameter { name, reason } => (name, reason),
        other => ("params", other.to_string()),
    })
}

/// A per-loop angle list must have one angle per boundary loop of the mesh.
pub fn check_loop_count(boundary: &BoundarySpec, loops: usize) -> Result<(), SpecViolation> {
    if let BoundarySpec::Prescribed(PrescribedSpec {
        angles: AnglesSpec::PerLoop(list),
        ..
    }) = boundary
    {
        if list.len() != loops {
            return Err((
                "boundary.prescribed.angles.per_loop",
                format!(
                    "gives {} angle(s) but the mesh has {loops} boundary loop(s)",
                    list.len()
                ),
            ));
        }
    }
    Ok(())
}

/// `region` in JSON: one region (`{"sphere": {...}}`) or a list of them, serialized as a list.
/// A visitor rather than an untagged enum, so a bad region gets the region's own error
/// (`unknown variant `cube``) instead of "did not match any variant".
pub mod one_or_many_regions {
    use serde::de::{self, MapAccess, SeqAccess, Visitor};
    use serde::{Deserialize, Deserializer};
    use std::fmt;
    use willow::flow::region::Region;

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Region>, D::Error> {
        struct Regions;
        impl<'de> Visitor<'de> for Regions {
            type Value = Vec<Region>;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a region ({\"sphere\": ...}, {\"box\": ...}, {\"vertices\": [...]}, {\"group\": \"name\"}) or a list of them")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
                let mut out = Vec::new();
                while let Some(r) = seq.next_element::<Region>()? {
                    out.push(r);
                }
                Ok(out)
            }
            fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<Self::Value, A::Error> {
                Region::deserialize(de::value::MapAccessDeserializer::new(map)).map(|r| vec![r])
            }
        }
        d.deserialize_any(Regions)
    }

    /// [`deserialize`] for an optional field (with `#[serde(default)]`).
    pub fn deserialize_opt<'de, D: Deserializer<'de>>(
        d: D,
    ) -> Result<Option<Vec<Region>>, D::Error> {
        deserialize(d).map(Some)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The JSON of these types is the library's JSON for the same boundary condition, so a
    /// spec written for `FlowParams` reads here and back.
    #[test]
    fn boundary_json_is_the_librarys() {
        let cases = [
            BoundarySpec::Free,
            BoundarySpec::Fixed,
            BoundarySpec::Cmc,
            BoundarySpec::Prescribed(PrescribedSpec {
                frame_angle: 0.25,
                axis: AxisSpec::Fixed([0.0, 0.0, 2.0]),
                angles: AnglesSpec::PerLoop(vec![0.1, -0.3]),
            }),
            BoundarySpec::Prescribed(PrescribedSpec::default()),
        ];
        for spec in cases {
            let ours = serde_json::to_value(&spec).expect("serializes");
            let library =
                serde_json::to_value(spec.to_flow(Method::Conformal, false)).expect("serializes");
            assert_eq!(ours, library);
            let back: BoundarySpec = serde_json::from_value(library).expect("reads back");
            assert_eq!(back, spec);
        }
    }

    #[test]
    fn unknown_fields_and_per_vertex_are_refused() {
        for text in [
            r#"{"prescribed": {"frame_angel": 0.1}}"#,
            r#"{"prescribed": {"angles": {"per_vertex": [[3, 0.1]]}}}"#,
            r#"{"prescribed": {"axis": {"fixed": [0, 0]}}}"#,
            r#""clamped""#,
        ] {
            assert!(
                serde_json::from_str::<BoundarySpec>(text).is_err(),
                "{text} was accepted"
            );
        }
        assert!(serde_json::from_str::<FilterSpec>(r#"{"sigma": 1, "k": 2, "x": 0}"#).is_err());
        let defaults: BoundarySpec =
            serde_json::from_str(r#"{"prescribed": {}}"#).expect("all fields default");
        assert_eq!(
            defaults,
            BoundarySpec::Prescribed(PrescribedSpec::default())
        );
    }

    #[test]
    fn checks_name_the_field() {
        let field = |b: BoundarySpec| check_boundary(&b).err().map(|(f, _)| f);
        let prescribed = |frame_angle, axis, angles| {
            BoundarySpec::Prescribed(PrescribedSpec {
                frame_angle,
                axis,
                angles,
            })
        };
        let tangent = AxisSpec::Tangent;
        let zero = AnglesSpec::Uniform(0.0);
        assert_eq!(field(prescribed(1.5, tangent, zero.clone())), None);
        assert_eq!(
            field(prescribed(1.55, tangent, zero.clone())),
            Some("boundary.prescribed.frame_angle"),
            "the library's bound, short of π/2"
        );
        assert_eq!(
            field(prescribed(f64::NAN, tangent, zero.clone())),
            Some("boundary.prescribed.frame_angle")
        );
        assert_eq!(
            field(prescribed(0.0, AxisSpec::Fixed([0.0; 3]), zero.clone())),
            Some("boundary.prescribed.axis.fixed")
        );
        assert_eq!(
            field(prescribed(
                0.0,
                AxisSpec::Fixed([1e300, 1e300, 0.0]),
                zero.clone()
            )),
            Some("boundary.prescribed.axis.fixed"),
            "the length overflows"
        );
        assert_eq!(
            field(prescribed(0.0, tangent, AnglesSpec::Uniform(f64::INFINITY))),
            Some("boundary.prescribed.angles.uniform")
        );
        assert_eq!(
            field(prescribed(
                0.0,
                tangent,
                AnglesSpec::PerLoop(vec![0.0, f64::NAN])
            )),
            Some("boundary.prescribed.angles.per_loop")
        );
        let per_loop = prescribed(0.0, tangent, AnglesSpec::PerLoop(vec![0.1, 0.2]));
        assert!(check_loop_count(&per_loop, 2).is_ok());
        assert_eq!(
            check_loop_count(&per_loop, 1).err().map(|(f, _)| f),
            Some("boundary.prescribed.angles.per_loop")
        );
        assert!(check_loop_count(&BoundarySpec::Cmc, 3).is_ok());
        let filter = |sigma, k| check_filter(&FilterSpec { sigma, k }).err().map(|(f, _)| f);
        assert_eq!(filter(0.01, 3), None);
        assert_eq!(filter(0.01, 4), Some("filter.k"));
        assert_eq!(filter(0.0, 2), Some("filter.sigma"));
        assert_eq!(filter(f64::NAN, 2), Some("filter.sigma"));
    }
}
