//! The job spec in the query string of a raw upload: `?steps=5&filter.sigma=0.01&filter.k=2`.
//!
//! A query string has no nesting, so the [`JobSpec`] is flattened: every scalar of its JSON is
//! a parameter named by its dotted path (as Google's HTTP transcoding spells them), found by
//! walking the spec's own OpenAPI schema. A scalar field added to [`JobSpec`] is a query
//! parameter, documented and parsed, with no edit here. The value is turned into the JSON type
//! the schema names (a type error names the parameter), and the spec is read from that JSON as
//! the `params` part is, so both take the same names and values.
//!
//! The two shapes that are not scalars keep compact forms of their own ([`Compact`]):
//! `boundary` with its `boundary.prescribed.*` parameters (any of which implies
//! `boundary=prescribed`), and the `region.*` parameters (several name their union). Lists in
//! them are comma separated.

use super::params::{bad_field, parse_list, query_str};
use crate::api::problem::{clip, Problem};
use crate::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, PrescribedSpec};
use crate::jobs::JobSpec;
use axum::http::Uri;
use serde::Deserialize;
use serde_json::{Map, Value};
use std::collections::HashMap;
use std::sync::LazyLock;
use utoipa::openapi::path::{Parameter, ParameterBuilder, ParameterIn};
use utoipa::openapi::{RefOr, Required, Schema};
use utoipa::{IntoParams, PartialSchema, ToSchema};
use willow::flow::region::Region;

/// The JSON type a query value becomes.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    String,
    Integer,
    Number,
    Boolean,
}

/// One parameter read by its path: a scalar somewhere in the spec's JSON.
struct Generic {
    /// The dotted path, `tau` or `filter.sigma`.
    name: String,
    scalar: Scalar,
    /// The scalar's schema (nullable dropped: a parameter left out is the null).
    schema: Value,
    description: Option<String>,
}

/// The generic parameters, from [`JobSpec`]'s schema.
static GENERIC: LazyLock<Vec<Generic>> = LazyLock::new(generic_parameters);

/// The top-level fields with compact forms of their own (see [`Compact`]).
const COMPACT_FIELDS: [&str; 3] = ["boundary", "region", "feature_angle"];

fn generic_parameters() -> Vec<Generic> {
    let root = serde_json::to_value(JobSpec::schema()).unwrap_or_default();
    let mut named = Vec::new();
    JobSpec::schemas(&mut named);
    let components: HashMap<String, Value> = named
        .into_iter()
        .map(|(name, s)| (name, serde_json::to_value(s).unwrap_or_default()))
        .collect();
    let mut out = Vec::new();
    flatten(&root, "", &components, &mut out);
    out
}

/// `schema` itself, or what its `$ref` (or a nullable `oneOf: [null, X]`) points at.
fn resolve<'a>(schema: &'a Value, components: &'a HashMap<String, Value>) -> &'a Value {
    if let Some(name) = schema["$ref"].as_str() {
        let name = name.rsplit('/').next().unwrap_or_default();
        return components
            .get(name)
            .map_or(schema, |s| resolve(s, components));
    }
    if let Some(alternatives) = schema["oneOf"].as_array() {
        let not_null: Vec<&Value> = alternatives
            .iter()
            .filter(|a| a["type"] != "null")
            .collect();
        if let [only] = not_null[..] {
            return resolve(only, components);
        }
    }
    schema
}

/// The scalar type of a schema (`"number"`, `["number", "null"]`, a string enum), if it is one.
fn scalar_of(schema: &Value) -> Option<Scalar> {
    let types: Vec<&str> = match &schema["type"] {
        Value::String(t) => vec![t.as_str()],
        Value::Array(ts) => ts.iter().filter_map(Value::as_str).collect(),
        _ => Vec::new(),
    };
    let mut scalars = types.iter().filter_map(|t| match *t {
        "string" => Some(Scalar::String),
        "integer" => Some(Scalar::Integer),
        "number" => Some(Scalar::Number),
        "boolean" => Some(Scalar::Boolean),
        _ => None,
    });
    match (scalars.next(), scalars.next()) {
        (Some(s), None) if types.iter().all(|t| *t != "object" && *t != "array") => Some(s),
        _ => None,
    }
}

/// Every scalar under `schema`'s properties, named by its dotted path.
fn flatten(
    schema: &Value,
    prefix: &str,
    components: &HashMap<String, Value>,
    out: &mut Vec<Generic>,
) {
    let Some(properties) = resolve(schema, components)["properties"].as_object() else {
        return;
    };
    for (key, property) in properties {
        if prefix.is_empty() && COMPACT_FIELDS.contains(&key.as_str()) {
            continue;
        }
        let name = format!("{prefix}{key}");
        let target = resolve(property, components);
        match scalar_of(target) {
            Some(scalar) => out.push(Generic {
                description: property["description"].as_str().map(str::to_string),
                schema: parameter_schema(property, target),
                name,
                scalar,
            }),
            // An object: its fields are parameters in turn (`filter.sigma`). A list has no
            // generic form; it needs a compact one.
            None => flatten(target, &format!("{name}."), components, out),
        }
    }
}

/// A parameter's schema: the property's, without its description (the parameter has it) and
/// without `null` (a parameter left out is the null).
fn parameter_schema(property: &Value, target: &Value) -> Value {
    let mut schema = if property.get("$ref").is_some() || property.get("oneOf").is_some() {
        target.clone()
    } else {
        property.clone()
    };
    if let Some(map) = schema.as_object_mut() {
        map.remove("description");
        if map.get("default") == Some(&Value::Null) {
            map.remove("default");
        }
        if let Some(Value::Array(types)) = map.get_mut("type") {
            types.retain(|t| t != "null");
            if let [only] = &types[..] {
                let only = only.clone();
                map.insert("type".into(), only);
            }
        }
    }
    schema
}

/// The compact forms: `boundary` by name with its `boundary.prescribed.*` parameters, and the
/// `region.*` parameters, each in the library's text form.
#[derive(Debug, Default, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
struct Compact {
    /// `free` (default), `fixed`, `cmc` or `prescribed`. Conformal flow only.
    boundary: Option<String>,
    /// Sharp edges kept sharp: `auto` (the default), `none`, or an angle in degrees
    /// (0 < angle < 180): edges whose faces meet at more than it are creases.
    feature_angle: Option<String>,
    /// Prescribed vectors: φ in radians, |φ| ≤ 1.5 (default 0).
    #[serde(rename = "boundary.prescribed.frame_angle")]
    #[param(rename = "boundary.prescribed.frame_angle")]
    frame_angle: Option<f64>,
    /// Prescribed vectors: `tangent` (the default rotation axis).
    #[serde(rename = "boundary.prescribed.axis")]
    #[param(rename = "boundary.prescribed.axis")]
    axis: Option<String>,
    /// Prescribed vectors: a fixed rotation axis `x,y,z`, finite and non-zero.
    #[serde(rename = "boundary.prescribed.axis.fixed")]
    #[param(rename = "boundary.prescribed.axis.fixed")]
    axis_fixed: Option<String>,
    /// Prescribed vectors: one rotation angle in radians for every boundary vertex (default 0).
    #[serde(rename = "boundary.prescribed.angles.uniform")]
    #[param(rename = "boundary.prescribed.angles.uniform")]
    angles_uniform: Option<f64>,
    /// Prescribed vectors: one angle per boundary loop, `a,b,…` (as many as the mesh has loops).
    #[serde(rename = "boundary.prescribed.angles.per_loop")]
    #[param(rename = "boundary.prescribed.angles.per_loop")]
    angles_per_loop: Option<String>,
    /// A spherical region that moves, `x,y,z,r` (everything else stays bit-identical).
    #[serde(rename = "region.sphere")]
    #[param(rename = "region.sphere")]
    region_sphere: Option<String>,
    /// A box region that moves, `xmin,ymin,zmin,xmax,ymax,zmax`.
    #[serde(rename = "region.box")]
    #[param(rename = "region.box")]
    region_box: Option<String>,
    /// A region of these file vertices, `i,j,k,...` (OBJ `v` lines from 0, glTF accessor
    /// vertices). Several `region.*` parameters name their union.
    #[serde(rename = "region.vertices")]
    #[param(rename = "region.vertices")]
    region_vertices: Option<String>,
    /// A region of the faces of this file group: an OBJ `g`/`o` name, a glTF node or mesh name.
    #[serde(rename = "region.group")]
    #[param(rename = "region.group")]
    region_group: Option<String>,
}

/// The query parameters of a raw upload, for the OpenAPI document: the generic ones from
/// [`JobSpec`]'s schema, then the compact forms.
pub struct JobQuery;

impl IntoParams for JobQuery {
    fn into_params(parameter_in_provider: impl Fn() -> Option<ParameterIn>) -> Vec<Parameter> {
        // utoipa's path macro passes no location for a type that names its own: these are
        // the query string's.
        let parameter_in = parameter_in_provider().unwrap_or(ParameterIn::Query);
        let generic = GENERIC.iter().map(|g| {
            ParameterBuilder::new()
                .name(&g.name)
                .parameter_in(parameter_in.clone())
                .required(Required::False)
                .description(g.description.clone())
                .schema(serde_json::from_value::<RefOr<Schema>>(g.schema.clone()).ok())
                .build()
        });
        generic
            .chain(Compact::into_params(parameter_in_provider))
            .collect()
    }
}

/// The job spec the query string of a raw upload asks for (validated later by the core). An
/// unknown parameter, a parameter given twice or a value of the wrong type is 400
/// `invalid_parameter` naming it.
pub fn spec_from_query(uri: &Uri) -> Result<JobSpec, Problem> {
    let raw = uri.query().unwrap_or("");
    let compact_names: Vec<String> = Compact::into_params(|| None)
        .into_iter()
        .map(|p| p.name)
        .collect();
    let mut json = Map::new();
    let mut compact_pairs = Vec::new();
    for (key, value) in form_urlencoded::parse(raw.as_bytes()) {
        if compact_names.iter().any(|n| *n == key) {
            compact_pairs.push((key, value));
            continue;
        }
        let Some(generic) = GENERIC.iter().find(|g| g.name == key) else {
            return Err(bad_field(&key, "unknown parameter"));
        };
        insert(&mut json, &key, json_value(&key, generic.scalar, &value)?)?;
    }
    let mut spec = spec_from_json_value(Value::Object(json))?;
    let compact: Compact = query_str(
        &form_urlencoded::Serializer::new(String::new())
            .extend_pairs(compact_pairs)
            .finish(),
    )?;
    compact.apply(&mut spec)?;
    Ok(spec)
}

/// The query value as the JSON type the spec expects there.
fn json_value(field: &str, scalar: Scalar, text: &str) -> Result<Value, Problem> {
    let not = |what: &str| bad_field(field, format!("expected {what}, got `{}`", clip(text)));
    Ok(match scalar {
        Scalar::String => Value::String(text.to_string()),
        // Any case, as the names (`method=MCF`, `boundary=Fixed`): a query value is text,
        // and `True` is what Python's `str(True)` sends.
        Scalar::Boolean if text.eq_ignore_ascii_case("true") => Value::Bool(true),
        Scalar::Boolean if text.eq_ignore_ascii_case("false") => Value::Bool(false),
        Scalar::Boolean => return Err(not("`true` or `false`")),
        Scalar::Integer => match (text.parse::<u64>(), text.parse::<i64>()) {
            (Ok(n), _) => Value::from(n),
            (_, Ok(n)) => Value::from(n),
            _ => return Err(not("an integer")),
        },
        Scalar::Number => {
            let x: f64 = text.parse().map_err(|_| not("a number"))?;
            // JSON has no NaN or infinity (either would be read as null, i.e. left out);
            // every number of a spec must be finite anyway.
            if !x.is_finite() {
                return Err(not("a finite number"));
            }
            Value::from(x)
        }
    })
}

/// Set the value at a dotted path, making the objects on the way; twice is an error.
fn insert(root: &mut Map<String, Value>, path: &str, value: Value) -> Result<(), Problem> {
    let (parents, leaf) = match path.rsplit_once('.') {
        Some((parents, leaf)) => (Some(parents), leaf),
        None => (None, path),
    };
    let mut map = root;
    for part in parents.into_iter().flat_map(|p| p.split('.')) {
        map = match map
            .entry(part.to_string())
            .or_insert_with(|| Value::Object(Map::new()))
        {
            Value::Object(m) => m,
            _ => return Err(bad_field(path, "given more than once")),
        };
    }
    if map.insert(leaf.to_string(), value).is_some() {
        return Err(bad_field(path, "given more than once"));
    }
    Ok(())
}

/// The spec from the generic parameters' JSON, with the defaults for the rest. A type error
/// names its path; a missing field of a nested object names the field (`filter.k` when only
/// `filter.sigma` is given).
fn spec_from_json_value(json: Value) -> Result<JobSpec, Problem> {
    serde_path_to_error::deserialize(json).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner().to_string();
        let missing = inner
            .strip_prefix("missing field `")
            .and_then(|rest| rest.split_once('`'))
            .map(|(name, _)| name);
        let field = match (path.as_str(), missing) {
            ("." | "", Some(name)) => name.to_string(),
            (parent, Some(name)) => format!("{parent}.{name}"),
            (".", None) => "query".to_string(),
            (path, None) => path.to_string(),
        };
        bad_field(&field, clip(&inner))
    })
}

impl Compact {
    /// Set the boundary and the regions these parameters name on `spec`.
    fn apply(self, spec: &mut JobSpec) -> Result<(), Problem> {
        if let Some(boundary) = self.boundary()? {
            spec.boundary = boundary;
        }
        if let Some(text) = &self.feature_angle {
            spec.feature_angle = willow::mesh::creases::FeatureAngle::parse(text)
                .map_err(|reason| bad_field("feature_angle", reason))?;
        }
        spec.region = query_regions(
            self.region_sphere.as_deref(),
            self.region_box.as_deref(),
            self.region_vertices.as_deref(),
        )?
        .unwrap_or_default()
        .into_iter()
        .chain(self.region_group.map(Region::Group))
        .collect();
        Ok(())
    }

    /// The boundary `boundary` and `boundary.prescribed.*` name; `None` when none is given.
    fn boundary(&self) -> Result<Option<BoundarySpec>, Problem> {
        let prescribed_given = self.frame_angle.is_some()
            || self.axis.is_some()
            || self.axis_fixed.is_some()
            || self.angles_uniform.is_some()
            || self.angles_per_loop.is_some();
        let boundary = match self.boundary.as_deref().map(str::to_ascii_lowercase) {
            None if !prescribed_given => None,
            None => Some(BoundarySpec::Prescribed(PrescribedSpec::default())),
            Some(name) => Some(match name.as_str() {
                "auto" => BoundarySpec::Auto,
                "free" => BoundarySpec::Free,
                "fixed" => BoundarySpec::Fixed,
                "cmc" => BoundarySpec::Cmc,
                "prescribed" => BoundarySpec::Prescribed(PrescribedSpec::default()),
                other => {
                    return Err(bad_field(
                        "boundary",
                        format!(
                            "expected `auto`, `free`, `fixed`, `cmc` or `prescribed`, got \
                             `{other}`"
                        ),
                    ))
                }
            }),
        };
        Ok(match boundary {
            Some(BoundarySpec::Prescribed(mut p)) => {
                if let Some(a) = self.frame_angle {
                    p.frame_angle = a;
                }
                p.axis = match (self.axis.as_deref(), self.axis_fixed.as_deref()) {
                    (Some(_), Some(_)) => {
                        return Err(bad_field(
                            "boundary.prescribed.axis",
                            "give either `boundary.prescribed.axis=tangent` or `boundary.prescribed.axis.fixed=x,y,z`, not both",
                        ))
                    }
                    (Some(name), None) if name.eq_ignore_ascii_case("tangent") => {
                        AxisSpec::Tangent
                    }
                    (Some(other), None) => {
                        return Err(bad_field(
                            "boundary.prescribed.axis",
                            format!(
                                "expected `tangent` (a fixed axis is `boundary.prescribed.axis.fixed=x,y,z`), got `{other}`"
                            ),
                        ))
                    }
                    (None, Some(text)) => {
                        let field = "boundary.prescribed.axis.fixed";
                        let v = parse_list(field, text)?;
                        let xyz: [f64; 3] = v.try_into().map_err(|v: Vec<f64>| {
                            bad_field(field, format!("expected 3 numbers x,y,z, got {}", v.len()))
                        })?;
                        AxisSpec::Fixed(xyz)
                    }
                    (None, None) => AxisSpec::Tangent,
                };
                p.angles = match (self.angles_uniform, self.angles_per_loop.as_deref()) {
                    (Some(_), Some(_)) => {
                        return Err(bad_field(
                            "boundary.prescribed.angles",
                            "give either `angles.uniform` or `angles.per_loop`, not both",
                        ))
                    }
                    (Some(a), None) => AnglesSpec::Uniform(a),
                    (None, Some(text)) => AnglesSpec::PerLoop(parse_list(
                        "boundary.prescribed.angles.per_loop",
                        text,
                    )?),
                    (None, None) => AnglesSpec::default(),
                };
                Some(BoundarySpec::Prescribed(p))
            }
            Some(other) if prescribed_given => {
                return Err(bad_field(
                    "boundary",
                    format!(
                        "`boundary.prescribed.*` parameters need `boundary=prescribed`, got `{}`",
                        serde_json::to_string(&other)
                            .unwrap_or_default()
                            .trim_matches('"')
                    ),
                ))
            }
            other => other,
        })
    }
}

/// The regions the `region.*` query parameters name (`None` if none is given), each in the
/// library's text form.
fn query_regions(
    sphere: Option<&str>,
    cuboid: Option<&str>,
    vertices: Option<&str>,
) -> Result<Option<Vec<Region>>, Problem> {
    type Parse = fn(&str) -> Result<Region, String>;
    let forms: [(&str, Option<&str>, Parse); 3] = [
        ("region.sphere", sphere, Region::parse_sphere),
        ("region.box", cuboid, Region::parse_box),
        ("region.vertices", vertices, Region::parse_vertices),
    ];
    let mut regions = Vec::new();
    for (field, text, parse) in forms {
        if let Some(text) = text {
            regions.push(parse(text).map_err(|e| bad_field(field, clip(&e)))?);
        }
    }
    Ok((!regions.is_empty()).then_some(regions))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(query: &str) -> Result<JobSpec, Problem> {
        spec_from_query(&format!("/v1/jobs?{query}").parse::<Uri>().expect("uri"))
    }

    /// Every field of the spec's JSON is reachable from the query: the scalars (and the
    /// filter's two) by name, the rest through a compact form.
    #[test]
    fn every_spec_field_has_a_parameter() {
        let names: Vec<&str> = GENERIC.iter().map(|g| g.name.as_str()).collect();
        let json = serde_json::to_value(JobSpec::default()).expect("json");
        for key in json.as_object().expect("an object").keys() {
            let reached = names.contains(&key.as_str())
                || names.iter().any(|n| n.starts_with(&format!("{key}.")))
                || COMPACT_FIELDS.contains(&key.as_str());
            assert!(reached, "`{key}` has no query parameter");
        }
        assert!(names.contains(&"filter.sigma") && names.contains(&"filter.k"));
    }

    /// Values become the types the spec expects, strings included where a value looks like a
    /// number; the compact forms fill in the rest.
    #[test]
    fn values_take_the_spec_types() {
        let s = spec(
            "method=MCF&steps=7&tau=0.125&include_positions=false&deadline_secs=30\
             &filter.sigma=0.01&filter.k=2&seam=fixed&preserve=volume&until_willmore=3\
             &callback_url=https://a.example/1&region.group=12&region.sphere=0,0,0,1\
             &boundary.prescribed.angles.per_loop=0.1,-0.1",
        )
        .expect("a spec");
        let want = JobSpec {
            method: willow::flow::Method::Mcf,
            steps: 7,
            tau: 0.125,
            include_positions: false,
            deadline_secs: Some(30.0),
            filter: Some(crate::jobs::spec::FilterSpec { sigma: 0.01, k: 2 }),
            seam: willow::flow::region::Seam::Fixed,
            preserve: willow::flow::Preserve::Volume,
            until_willmore: Some(3.0),
            callback_url: Some("https://a.example/1".into()),
            region: vec![
                Region::Sphere {
                    center: [0.0; 3],
                    radius: 1.0,
                },
                Region::Group("12".into()),
            ],
            boundary: BoundarySpec::Prescribed(PrescribedSpec {
                angles: AnglesSpec::PerLoop(vec![0.1, -0.1]),
                ..PrescribedSpec::default()
            }),
            ..JobSpec::default()
        };
        assert_eq!(s, want);
        assert_eq!(spec("").expect("defaults"), JobSpec::default());
    }

    /// Issue 42: one rule for the names the API defines, any case, booleans included.
    #[test]
    fn names_and_booleans_are_read_in_any_case() {
        let s =
            spec("method=Conformal&boundary=FIXED&safeguard=True&exactness=FALSE").expect("a spec");
        assert_eq!(s.method, willow::flow::Method::Conformal);
        assert_eq!(s.boundary, BoundarySpec::Fixed);
        assert!(s.safeguard && !s.exactness);
        for query in ["safeguard=yes", "safeguard=1", "method=Conformale"] {
            assert!(spec(query).is_err(), "{query}");
        }
    }

    /// Each refusal names the parameter.
    #[test]
    fn refusals_name_the_parameter() {
        for (query, field) in [
            ("steps=abc", "steps"),
            ("steps=1.5", "steps"),
            ("steps=-1", "steps"),
            ("tau=NaN", "tau"),
            ("exactness=yes", "exactness"),
            ("stepz=1", "stepz"),
            ("filter=1", "filter"),
            ("steps=1&steps=2", "steps"),
            ("filter.sigma=0.1", "filter.k"),
            ("filter.k=1", "filter.sigma"),
            ("filter.k=99999999999", "filter.k"),
            ("method=nope", "method"),
            ("region.box=1,2", "region.box"),
            (
                "boundary=fixed&boundary.prescribed.frame_angle=0.1",
                "boundary",
            ),
        ] {
            let p = spec(query).expect_err(query);
            let body = serde_json::to_value(&p).expect("json");
            assert_eq!(body["field"], field, "{query}: {body}");
            assert_eq!(body["status"], 400, "{query}: {body}");
        }
    }
}
