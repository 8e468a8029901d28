//! The OpenAPI schemas of the library's types a job spec carries ([`Region`], [`Seam`],
//! [`Preserve`]): the library derives no schema (it may not depend on utoipa), so each is
//! mirrored here, variant for variant, and only ever described, never built. The job spec
//! itself and the service's own spec types derive theirs ([`crate::jobs::JobSpec`],
//! [`crate::jobs::spec`]), their doc comments being the descriptions.
//! `schema_names_match_the_core_types` below fails when a mirrored type gains, loses or
//! renames a variant that its mirror does not.
//!
//! [`Region`]: willow::flow::region::Region
//! [`Seam`]: willow::flow::region::Seam
//! [`Preserve`]: willow::flow::Preserve

#![allow(dead_code)] // described to utoipa, never constructed

use utoipa::ToSchema;

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

/// Which edges are creases: an angle in degrees (0 < angle < 180), or `auto` / `none`.
#[derive(ToSchema)]
#[schema(as = FeatureAngle)]
#[serde(untagged)]
pub enum FeatureAngleSchema {
    /// Edges sharper than this many degrees.
    Degrees(f64),
    /// `auto` (30°, only where a part has creases) or `none`.
    Named(FeatureAngleName),
}

/// The named feature angles.
#[derive(ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FeatureAngleName {
    Auto,
    None,
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
            properties(&doc, "DenoiseSpec"),
            fields(serde_json::to_value(spec.denoise).expect("json"))
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
