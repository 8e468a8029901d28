//! The OpenAPI schemas of the job core's spec types, kept at the edge: the core
//! ([`crate::jobs::JobSpec`], [`crate::jobs::spec`]) knows no wire format and derives no
//! schema. Each type here mirrors one core type field for field and is only ever described,
//! never built; `schema_names_match_the_core_types` below fails when a core type gains,
//! loses or renames a field that its mirror does not.

#![allow(dead_code)] // described to utoipa, never constructed

use utoipa::ToSchema;

/// What to run on an uploaded mesh (a job's `params`, as reported and as accepted).
#[derive(ToSchema)]
#[schema(as = JobSpec)]
pub struct JobSpecSchema {
    /// Which flow: `conformal` (the paper), `mcf` (the yardstick), `cmcf`, `bilaplacian` or
    /// `taubin`.
    #[schema(example = "conformal")]
    pub method: String,
    /// Number of flow steps to take (step 0 is the input).
    #[schema(minimum = 1)]
    pub steps: usize,
    /// Time step τ (conformal: the curvature update `u ← (1 − 2τ)u`, stable for τ < 1).
    pub tau: f64,
    /// Inverse power iterations per step (conformal flow).
    pub iterations: usize,
    /// Every `frame_interval`-th step (and step 0 and the last step) keeps its positions.
    pub frame_interval: usize,
    /// Whether live and replayed frames carry positions at all (metrics are always sent).
    pub include_positions: bool,
    /// Wall-clock budget from submission, in seconds; null takes the server default.
    pub deadline_secs: Option<f64>,
    /// Exactness constraints on surfaces of genus > 0 (§6.2, App. C); conformal flow only.
    pub exactness: bool,
    /// Möbius balancing toward the input's area distribution (App. E.1); conformal only.
    pub mobius_balancing: bool,
    /// Spectral filter of the flow direction (§4); null is the paper's plain flow.
    pub filter: Option<FilterSpecSchema>,
    /// Boundary condition (§6.3); anything but `free` is for the conformal flow only.
    pub boundary: BoundarySpecSchema,
    /// Safeguarded steps: a step that raises W or damages the mesh is retried at a smaller τ.
    pub safeguard: bool,
    /// The part of the surface that moves (their union); empty: the whole surface. Every
    /// vertex outside stays bit-identical. Accepted as one region or a list; reported as a
    /// list. Conformal flow only.
    pub region: Vec<RegionSchema>,
    /// How a region meets the surface around it: `smooth` (positions and tangent planes
    /// held) or `fixed` (positions only).
    pub seam: SeamSchema,
    /// What each connected component keeps after every step: `area` (default), `volume`
    /// (closed components keep their enclosed volume, by a uniform scale: Q is untouched) or
    /// `none`. Taubin smoothing refuses `volume`.
    pub preserve: PreserveSchema,
    /// Stop once the Willmore energy is at most this (outcome `target_reached`); ≥ 0.
    pub until_willmore: Option<f64>,
    /// Stop once W has stopped falling: its relative change stayed below 1e-4 per step for 3
    /// steps (outcome `converged`). Default true; false runs every step.
    pub until_converged: bool,
    /// Stop before the first step that would move the surface further than this from the
    /// input, in model units (outcome `max_deviation`): the result is the last surface within
    /// it. ≥ 0; turns `measure_deviation` on.
    pub max_deviation: Option<f64>,
    /// Report each frame's two-sided distance from the input (`deviation_max`,
    /// `deviation_mean`, model units). Off by default: it costs a share of every step.
    pub measure_deviation: bool,
    /// Remove the detail smaller than this length (model units, > 0, at least two mean edge
    /// lengths) and keep the shape above it: the spectral filter (§4) with its crossover at
    /// this size; the job ends `feature_scale_reached` once the detail is gone. Conformal flow
    /// only; `filter`, when given, replaces the derived σ and k.
    pub feature_size: Option<f64>,
    /// Width (model units, > 0) over which a region's motion blends to zero toward its
    /// border. Needs a region.
    pub falloff: Option<f64>,
    /// Repair the upload before the flow: drop degenerate faces and split non-manifold
    /// vertices and edges; the job reports `repairs`. Default false: such a file
    /// is refused, naming its own vertex and face numbers.
    pub repair: bool,
    /// Loop-subdivide the upload toward ~16k triangles before the flow (UVs interpolated per
    /// corner), for tessellations too coarse to fair (`already_fair`). Frames then carry the
    /// refined mesh's vertices (the file's own first, then the new ones; `vertex_count` of
    /// them) and frame 0 says `connectivity_changed`: fetch its mesh for the faces.
    pub refine: bool,
    /// Where the job's end (`job.succeeded`, `job.failed`, `job.cancelled`) is POSTed as a
    /// Standard Webhooks event (`webhook-id`, `webhook-timestamp`, `webhook-signature:
    /// v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">`, keyed by the tenant's webhook
    /// secret), retried with backoff until answered 2xx. `https` to a public address only,
    /// unless the server runs with `--allow-insecure-callbacks`.
    pub callback_url: Option<String>,
}

/// What each component keeps after every step.
#[derive(ToSchema)]
#[schema(as = Preserve)]
#[serde(rename_all = "snake_case")]
pub enum PreserveSchema {
    /// Its input area (the default).
    Area,
    /// Its enclosed volume (closed components; the others keep their area).
    Volume,
    /// Nothing: the size is the flow's.
    None,
}

/// One way to name the vertices that move, in the file's units and numbering.
#[derive(ToSchema)]
#[schema(as = Region)]
#[serde(rename_all = "snake_case")]
pub enum RegionSchema {
    /// Every vertex within `radius` of `center` (world space).
    Sphere { center: [f64; 3], radius: f64 },
    /// Every vertex with `min ≤ p ≤ max` in each coordinate.
    Box { min: [f64; 3], max: [f64; 3] },
    /// These file vertices: OBJ `v` lines from 0, glTF accessor vertices (the numbering of
    /// frames' positions).
    Vertices(Vec<usize>),
    /// The faces of a named group of the file: an OBJ `g` or `o` name, a glTF node or mesh
    /// name.
    Group(String),
}

/// How a region meets the surface around it.
#[derive(ToSchema)]
#[schema(as = Seam)]
#[serde(rename_all = "snake_case")]
pub enum SeamSchema {
    /// The border's positions stay (C0).
    Fixed,
    /// The border's positions and tangent planes stay (G1).
    Smooth,
}

/// Spectral filter of the flow direction (§4): `v ← v − (id + σ(−Δ)^k)⁻¹ v`.
#[derive(ToSchema)]
#[schema(as = FilterSpec)]
pub struct FilterSpecSchema {
    /// Strength σ, unitless and > 0: σ = (l(l+1))^−k puts the crossover at spherical degree l.
    pub sigma: f64,
    /// Shape k ∈ 0..=3; k = 2 approximates position-based Willmore flow (Figure 19).
    pub k: u32,
}

/// Boundary condition for surfaces with boundary (§6.3); closed surfaces ignore it.
#[derive(ToSchema)]
#[schema(as = BoundarySpec)]
#[serde(rename_all = "snake_case")]
pub enum BoundarySpecSchema {
    /// The boundary moves freely (§6.2).
    Free,
    /// Boundary vertices stay exactly where they are (§6.3.2).
    Fixed,
    /// `V = B` held at the input's conormals: converges to constant mean curvature (§6.3.1).
    Cmc,
    /// Prescribed boundary vectors (§6.3.1).
    Prescribed(PrescribedSpecSchema),
}

/// §6.3.1: at each boundary vertex `V = cos φ·B + sin φ·N` is mapped to a target, the input's
/// `V` rotated by an angle about an axis. Every field may be left out.
#[derive(ToSchema)]
#[schema(as = PrescribedSpec)]
pub struct PrescribedSpecSchema {
    /// φ in radians, |φ| ≤ 1.5 (at ±π/2 the boundary problem is not elliptic).
    pub frame_angle: f64,
    /// Axis of the rotation from `V` to its target (default: the boundary tangent).
    pub axis: AxisSpecSchema,
    /// Rotation angles in radians (default: 0 everywhere).
    pub angles: AnglesSpecSchema,
}

/// Axis of the rotation that makes the target from the input's `V`.
#[derive(ToSchema)]
#[schema(as = AxisSpec)]
#[serde(rename_all = "snake_case")]
pub enum AxisSpecSchema {
    /// The boundary tangent at each vertex (flares or tucks the boundary).
    Tangent,
    /// One direction in space for every vertex, `[x, y, z]`, finite and non-zero.
    Fixed([f64; 3]),
}

/// Rotation angles in radians.
#[derive(ToSchema)]
#[schema(as = AnglesSpec)]
#[serde(rename_all = "snake_case")]
pub enum AnglesSpecSchema {
    /// The same angle at every boundary vertex.
    Uniform(f64),
    /// One angle per boundary loop, in the order of the mesh's boundary loops.
    PerLoop(Vec<f64>),
}

#[cfg(test)]
mod tests {
    use crate::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, PrescribedSpec};
    use crate::jobs::JobSpec;
    use utoipa::OpenApi;
    use willow::flow::region::{Region, Seam};

    /// The property names of schema `name` in the served OpenAPI document.
    fn properties(doc: &serde_json::Value, name: &str) -> Vec<String> {
        let mut keys: Vec<String> = doc["components"]["schemas"][name]["properties"]
            .as_object()
            .unwrap_or_else(|| panic!("schema {name} has properties"))
            .keys()
            .cloned()
            .collect();
        keys.sort();
        keys
    }

    fn fields(v: serde_json::Value) -> Vec<String> {
        let mut keys: Vec<String> = v.as_object().expect("an object").keys().cloned().collect();
        keys.sort();
        keys
    }

    #[test]
    fn schema_names_match_the_core_types() {
        let doc = serde_json::to_value(crate::api::http::ApiDoc::openapi()).expect("json");
        let spec = JobSpec {
            filter: Some(crate::jobs::spec::FilterSpec { sigma: 0.1, k: 2 }),
            ..JobSpec::default()
        };
        assert_eq!(
            properties(&doc, "JobSpec"),
            fields(serde_json::to_value(&spec).expect("json"))
        );
        assert_eq!(
            properties(&doc, "FilterSpec"),
            fields(serde_json::to_value(spec.filter).expect("json"))
        );
        assert_eq!(
            properties(&doc, "PrescribedSpec"),
            fields(serde_json::to_value(PrescribedSpec::default()).expect("json"))
        );
        // The enums' variant names, as serde writes them.
        let text = doc["components"]["schemas"].to_string();
        for v in [
            serde_json::to_value(BoundarySpec::Cmc),
            serde_json::to_value(BoundarySpec::Prescribed(PrescribedSpec::default())),
            serde_json::to_value(AxisSpec::Fixed([0.0, 0.0, 1.0])),
            serde_json::to_value(AnglesSpec::PerLoop(vec![0.1])),
            serde_json::to_value(AnglesSpec::Uniform(0.1)),
            serde_json::to_value(Region::Sphere {
                center: [0.0; 3],
                radius: 1.0,
            }),
            serde_json::to_value(Region::Box {
                min: [0.0; 3],
                max: [1.0; 3],
            }),
            serde_json::to_value(Region::Vertices(vec![1])),
            serde_json::to_value(Region::Group("ear".into())),
            serde_json::to_value(Seam::Fixed),
            serde_json::to_value(Seam::Smooth),
            serde_json::to_value(willow::flow::Preserve::Volume),
            serde_json::to_value(willow::flow::Preserve::None),
        ] {
            let v = v.expect("json");
            let name = match &v {
                serde_json::Value::String(s) => s.clone(),
                serde_json::Value::Object(o) => o.keys().next().expect("a variant").clone(),
                other => panic!("unexpected {other}"),
            };
            assert!(
                text.contains(&format!("\"{name}\"")),
                "variant {name} is described"
            );
        }
    }
}
